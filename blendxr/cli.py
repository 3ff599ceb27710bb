"""The ``blendxr`` command: one verb per job.

Errors in input print one line and exit with status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["main"]

DEFAULT_MIX_SCENE = "drum-2d"  # an analytic flow: mixing alone, in seconds
DEFAULT_RUN_SCENE = "tote-small"  # flow solver + mixing + report, in minutes


#: Shell flags that are shorthands for scene keys (``--k1 0.02`` is ``--set mixing.k1=0.02``).
MIX_FLAGS = {
    "scheme": "numerics.scheme",
    "k1": "mixing.k1",
    "k2": "mixing.k2",
    "revolutions": "mixing.revolutions",
    "cells": "numerics.cells",
    "output_every": "mixing.output_every",
    "initial": "mixing.loading",
}
FLOW_FLAGS = {
    "cell": "solver.cell",
    "revolutions": "solver.revolutions",
    "stiffness_scaling": "solver.stiffness_scaling",
}


def _scene_from_args(args, flags: dict):
    """The scene with ``--set`` values and the flag shorthands applied (flags last)."""
    from .scene import load_scene, parse_assignment

    values = dict(parse_assignment(text) for text in (args.set or []))
    for name, key in flags.items():
        value = getattr(args, name, None)
        if value is not None:  # a flag given as 0 is a value too, and is validated
            values[key] = value
    return load_scene(args.scene, values)


def _mix_overrides(args) -> dict:
    overrides = {}
    if getattr(args, "dt", None) is not None:
        overrides["dt"] = args.dt
    if args.checkpoint:
        overrides["checkpoint"] = args.checkpoint
        overrides["resume"] = not args.no_resume
    return overrides


def _cmd_run(args) -> int:
    """``run`` and ``mix``: flow -> mixing -> report (``mix`` writes flow.nc on request)."""
    from .pipeline import report_lines, run_scene

    scene = _scene_from_args(args, MIX_FLAGS)
    report = run_scene(
        scene,
        args.output,
        cache=args.cache,
        use_cache=not args.no_cache,
        flow_path=args.flow,
        progress=not args.quiet,
        save_flow=args.save_flow,
        **_mix_overrides(args),
    )
    for line in report_lines(report):
        print(line)
    out = Path(args.output)
    print(f"wrote {', '.join(str(out / name) for name in report['files'])}")
    return 0


def _cmd_flow(args) -> int:
    from . import solve_flow
    from .io import write_dataset
    from .pipeline import check_output_folder, flow_lines, flow_summary

    scene = _scene_from_args(args, FLOW_FLAGS)
    out = check_output_folder(args.output)
    result = solve_flow(
        scene,
        particles=args.particles,
        checkpoint=args.checkpoint,
        resume=not args.no_resume,
        progress=not args.quiet,
        wall_time=args.wall_time,
    )
    flow, particles = result if args.particles else (result, None)
    write_dataset(flow, out / "flow.nc")
    a = flow.attrs
    print(
        f"{a['particles']} particles, {a['steps']} steps, {a['wall_time_s']:.1f} s wall, "
        f"{a['particle_updates_per_s'] / 1e6:.2f} M particle updates/s"
    )
    for line in flow_lines(flow_summary(flow)):
        print(line)
    if particles is not None:
        from .io import _atomic_path

        with _atomic_path(out / "particles.nc") as tmp:
            particles.to_netcdf(tmp)
    print(f"wrote {out / 'flow.nc'}")
    return 0


def _cmd_calibrate(args) -> int:
    from .io import write_result
    from .pipeline import check_output_folder
    from .plot import save_figure
    from .studies import calibrate_k1, calibration_figure

    scene = _scene_from_args(args, {})
    out = check_output_folder(args.output)
    grid = None
    if args.k1:
        try:
            grid = [float(v) for v in args.k1.split(",")]
        except ValueError:
            raise ValueError(f"--k1 {args.k1!r}: give comma-separated numbers") from None
    result = calibrate_k1(
        args.data,
        scene,
        flow=args.flow,
        k1=grid,
        cache=args.cache,
        progress=not args.quiet,
    )
    write_result(result, out / "calibration.nc", scene=scene, title="blendxr calibration of k1")
    save_figure(calibration_figure(result), out / "calibration.png")
    a = result.attrs
    print(
        f"best k1 = {a['best_k1']:.4g} (cost {a['best_cost']:.4g}, summed absolute "
        f"difference of {a['metric']}; grid best {a['grid_best_k1']:g})"
    )
    for k, cost in zip(result["k1"].values, result["cost"].values, strict=True):
        print(f"  k1 {k:<8g} cost {cost:.4g}")
    print(f"wrote {out / 'calibration.nc'} and {out / 'calibration.png'}")
    return 0


def _parse_vary(texts) -> dict:
    """``--vary key=v1,v2`` (repeatable) as ``{key: [v1, v2]}``, each value parsed as
    ``--set`` parses one."""
    from .scene import parse_assignment

    grid = {}
    for text in texts or []:
        key, _, values = text.partition("=")
        if not key or not values:
            raise ValueError(f"--vary {text!r}: give KEY=VALUE,VALUE,...")
        grid[key.strip()] = [parse_assignment(f"{key}={v}")[1] for v in values.split(",")]
    if not grid:
        raise ValueError("sweep: give at least one --vary KEY=VALUE,VALUE,...")
    return grid


def _cmd_sweep(args) -> int:
    import numpy as np

    from .io import write_result
    from .pipeline import check_output_folder
    from .sweep import summary_line, sweep

    scene = _scene_from_args(args, {})
    grid = _parse_vary(args.vary)
    out = check_output_folder(args.output)
    client = None
    if args.scheduler:
        from dask.distributed import Client

        client = Client(args.scheduler)
        print(f"dask scheduler {args.scheduler}; dashboard {client.dashboard_link}")
    try:
        result = sweep(
            scene,
            grid,
            client=client,
            store=out / "cases",
            workers=args.workers,
            cache=args.cache,
            progress=not args.quiet,
        )
    finally:
        if client is not None:
            client.close()
    write_result(result, out / "sweep.nc", scene=scene, title=f"blendxr sweep of {scene.name}")
    print(summary_line(result))
    keys = list(grid)
    levels = [f"N({lv:g})" for lv in result["rsd_level"].values]
    print("  ".join([*keys, *levels, "status"]))
    for index in np.ndindex(*result["status"].shape):
        point = {k: result[k].values[i] for k, i in zip(keys, index, strict=True)}
        to_level = result["revolutions_to_rsd"].values[index]
        cells = [f"{point[k]}" for k in keys]
        cells += ["-" if not np.isfinite(v) else f"{v:.2f}" for v in to_level]
        status = str(result["status"].values[index])
        if status != "ok":
            status += f" ({result['error'].values[index]})"
        print("  ".join([*cells, status]))
    print(f"wrote {out / 'sweep.nc'} (cases in {out / 'cases'})")
    failed = int((result["status"] != "ok").sum())
    return 1 if failed else 0


def _one_line(err: BaseException) -> str:
    """An error as one line: an OSError by its own words and file, not its errno."""
    if isinstance(err, OSError) and err.strerror:
        text = err.strerror
        if err.filename and str(err.filename) not in text:
            text = f"{err.filename}: {text}"
        return " ".join(text.split())
    return " ".join(str(err).split())


def _cmd_validate(args) -> int:
    """Every file checked and named; status 2 when any fails."""
    from .io import open_dataset
    from .schema import validate

    faults = []
    for path in args.files:
        try:
            with open_dataset(path) as ds:
                validate(ds)
                print(f"{path}: valid {ds.attrs.get('blendxr_schema')}")
        except (ValueError, OSError) as err:
            message = _one_line(err)
            faults.append(message if str(path) in message else f"{path}: {message}")
    if len(args.files) == 1 and faults:
        print(f"blendxr: error: {faults[0]}", file=sys.stderr)
    elif faults:
        for line in faults:
            print(f"blendxr: error: {line}", file=sys.stderr)
        print(f"blendxr: {len(faults)} of {len(args.files)} files not valid", file=sys.stderr)
    return 2 if faults else 0


def _cmd_info(args) -> int:
    from .io import open_dataset

    with open_dataset(args.file) as ds:
        print(ds)
    return 0


def _cmd_scenes(args) -> int:
    from .scene import builtin_scenes, load_scene

    for name in builtin_scenes():
        scene = load_scene(name)
        first = scene.get("description", "").strip().splitlines()
        print(f"{name:24s} {first[0] if first else ''}")
    return 0


def _cmd_scene(args) -> int:
    scene = _scene_from_args(args, {})
    print(json.dumps(scene.to_dict(), indent=2) if args.json else scene.to_toml())
    return 0


def _parser() -> argparse.ArgumentParser:
    from ._version import __version__

    parser = argparse.ArgumentParser(
        prog="blendxr", description="Mixing of powders in tumbling blenders, from flow to RSD."
    )
    parser.add_argument("--version", action="version", version=f"blendxr {__version__}")
    parser.add_argument(
        "--debug", action="store_true", help="show the traceback of an error (before the verb)"
    )
    sub = parser.add_subparsers(dest="command", required=True)

    from .scene import _key_schema

    # the scene schema is the one list of schemes (the CLI does not import the kernels)
    scheme_names = _key_schema("numerics.scheme")["enum"]

    def add_mix_arguments(p):
        p.add_argument("--flow", help="a flow netCDF file (default: the scene's own flow)")
        p.add_argument("-o", "--output", default=".", help="output folder (default: .)")
        p.add_argument("--scheme", choices=scheme_names)
        p.add_argument("--k1", type=float)
        p.add_argument("--k2", type=float)
        p.add_argument("--revolutions", type=float)
        p.add_argument("--cells", type=int, help="ADE cells along the longest axis")
        p.add_argument("--output-every", dest="output_every", type=float)
        p.add_argument("--dt", type=float, help="time step in s (refused above the limit)")
        p.add_argument("--initial", help="loading: top-bottom, axial, transverse")
        p.add_argument("--checkpoint", help="checkpoint file; an existing one is resumed")
        add_no_resume(p)
        p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
        add_set(p)
        p.add_argument(
            "--cache", help="folder of cached flows (default: $BLENDXR_CACHE, else the user cache)"
        )
        p.add_argument(
            "--no-cache", dest="no_cache", action="store_true", help="solve the flow anew"
        )

    def add_no_resume(p):
        p.add_argument(
            "--no-resume",
            dest="no_resume",
            action="store_true",
            help="start afresh, overwriting an existing --checkpoint file",
        )

    def add_set(p):
        p.add_argument(
            "--set",
            action="append",
            metavar="KEY=VALUE",
            help="set a scene value by dotted key, e.g. --set mixing.k1=0.02 (repeatable)",
        )

    p = sub.add_parser("mix", help="run the mixing model on a scene's flow or a flow file")
    p.add_argument("scene", nargs="?", default=DEFAULT_MIX_SCENE)
    add_mix_arguments(p)
    p.add_argument("--save-flow", action="store_true", help="also write flow.nc")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("run", help="flow + mixing + report for a scene (writes flow.nc too)")
    p.add_argument("scene", nargs="?", default=DEFAULT_RUN_SCENE)
    add_mix_arguments(p)
    p.set_defaults(func=_cmd_run, save_flow=True)

    p = sub.add_parser("flow", help="compute a scene's flow with the built-in solver")
    p.add_argument("scene")
    p.add_argument("-o", "--output", default=".", help="output folder (default: .)")
    p.add_argument("--cell", type=float, help="solver cell in m")
    p.add_argument("--revolutions", type=int, help="revolutions turned (>= 2)")
    p.add_argument("--stiffness-scaling", dest="stiffness_scaling", type=float)
    p.add_argument("--checkpoint", help="checkpoint file; an existing one is resumed")
    add_no_resume(p)
    p.add_argument("--wall-time", dest="wall_time", type=float, help="stop after S seconds")
    p.add_argument("--particles", action="store_true", help="also write particles.nc")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_set(p)
    p.set_defaults(func=_cmd_flow)

    p = sub.add_parser("calibrate", help="fit k1 to a measured intensity or RSD curve")
    p.add_argument("scene")
    p.add_argument("data", help="CSV with columns revolution and intensity (or rsd)")
    p.add_argument("--k1", help="comma-separated k1 values to try (default: 0 to 0.03)")
    p.add_argument("--flow", help="a flow netCDF file (default: the scene's own flow)")
    p.add_argument("-o", "--output", default=".", help="output folder (default: .)")
    p.add_argument("--cache", help="folder of cached flows")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_set(p)
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("sweep", help="a parameter study: every combination, on dask")
    p.add_argument("scene")
    p.add_argument(
        "--vary",
        action="append",
        metavar="KEY=V1,V2,...",
        help="a scene key and its values (repeatable: every combination is run)",
    )
    p.add_argument("--scheduler", help="address of a dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, help="processes of the local cluster (default: cores)")
    p.add_argument("-o", "--output", default=".", help="output folder (default: .)")
    p.add_argument("--cache", help="folder of cached flows")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    add_set(p)
    p.set_defaults(func=_cmd_sweep)

    p = sub.add_parser("validate", help="check netCDF files against the blendxr schemas")
    p.add_argument("files", nargs="+")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("info", help="print a dataset's summary")
    p.add_argument("file")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("scenes", help="list the built-in scenes")
    p.set_defaults(func=_cmd_scenes)

    p = sub.add_parser("scene", help="print a scene with its defaults filled in")
    p.add_argument("scene")
    p.add_argument("--json", action="store_true")
    add_set(p)
    p.set_defaults(func=_cmd_scene)
    return parser


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one line, like the errors (the source line means nothing to a user)."""
    print(f"blendxr: warning: {' '.join(str(message).split())}", file=sys.stderr)


def main(argv=None) -> int:
    """Entry point of the ``blendxr`` command."""
    import warnings

    args = _parser().parse_args(argv)
    if args.debug:
        return args.func(args)
    try:
        with warnings.catch_warnings():  # restored on return, for callers in the process
            warnings.showwarning = _show_warning
            return args.func(args)
    except KeyboardInterrupt:
        print("blendxr: interrupted", file=sys.stderr)
        return 130
    except (ValueError, FileNotFoundError, NotImplementedError, OSError, FloatingPointError) as err:
        message = _one_line(err)
        print(f"blendxr: error: {message}", file=sys.stderr)
        return 2
    except RuntimeError as err:  # a run that went unstable or stopped early
        message = " ".join(str(err).split())
        print(f"blendxr: stopped: {message}", file=sys.stderr)
        return 1
    except Exception as err:  # a fault of blendxr's own: one line, the traceback on request
        message = " ".join(str(err).split())
        print(
            f"blendxr: internal error: {type(err).__name__}: {message} (run `blendxr --debug "
            "...` for the traceback, and report it)",
            file=sys.stderr,
        )
        return 3


if __name__ == "__main__":
    sys.exit(main())
