"""The main job: a scene's flow (cached), its mixing, and the report a user reads.

``run_scene`` is what ``blendxr run`` does: flow -> mixing -> report. The flow of a
solver scene is cached under a key made from every input that changes it (the scene's
``vessel``, ``operation``, ``material``, ``fill``, ``flow`` and ``solver`` sections and
the blendxr version), so a second run that changes only mixing values (k1, loading,
ADE cells, scheme) reads the flow instead of solving it again. Each stage's wall time
and peak memory go into the report.
"""

from __future__ import annotations

import contextlib
import difflib
import functools
import hashlib
import inspect
import json
import math
import os
import resource
import sys
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ._version import __version__
from .scene import Scene, SceneError, load_scene

if TYPE_CHECKING:
    import xarray as xr

__all__ = [
    "FLOW_SECTIONS",
    "RSD_LEVELS",
    "cache_folder",
    "flow_key",
    "revolutions_to_level",
    "run_scene",
    "scene_flow",
]

#: The scene sections whose values change the flow (the cache key is made of them).
FLOW_SECTIONS = ("vessel", "operation", "material", "fill", "flow", "solver")
#: RSD levels whose crossing the report gives (0.05: the usual blend-uniformity acceptance).
RSD_LEVELS = (0.2, 0.1, 0.05)


# ------------------------------------------------------------------------------ cache


def flow_key(scene) -> str:
    """The cache key of a scene's flow: a hash of every input that changes it.

    Parameters
    ----------
    scene : Scene, str or mapping

    Returns
    -------
    str
        24 hexadecimal digits; equal for two scenes exactly when their flow sections
        (:data:`FLOW_SECTIONS`, defaults filled in), the blendxr version and the solver's
        source (:func:`solver_source_digest`) are equal.
    """
    text = json.dumps(_flow_inputs(load_scene(scene)), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:24]


def cache_folder(cache: str | os.PathLike | None = None) -> Path:
    """The folder of cached flows: ``cache``, else ``$BLENDXR_CACHE``, else the user's
    cache folder (``~/.cache/blendxr`` on Linux)."""
    if cache is not None:
        return Path(cache)
    env = os.environ.get("BLENDXR_CACHE")
    if env:
        return Path(env)
    import platformdirs

    return Path(platformdirs.user_cache_dir("blendxr", appauthor=False))


@dataclass
class FlowSource:
    """Where a run's flow came from."""

    kind: str  # "solver", "analytic", "file"
    cache: str = "off"  # "hit", "miss" (solved and stored), "off"
    key: str = ""
    path: str = ""

    def describe(self) -> str:
        if self.kind != "solver":
            return f"flow: {self.kind}{f' {self.path}' if self.path else ''}"
        if self.cache == "hit":
            return f"flow: reused from the cache ({self.path}); only mixing values changed"
        if self.cache == "miss":
            return f"flow: solved and cached as {self.path}"
        return "flow: solved (cache off)"


#: analytic flow parameters that come from the scene's other sections, never twice
ANALYTIC_FROM_SCENE = {"rpm": "operation.rpm", "gravity": "operation.gravity"}
#: scene values that only the solver's flows use
SOLVER_ONLY = ("flow.cell", "flow.phases")


def analytic_flow(scene) -> xr.Dataset:
    """The analytic flow a scene names (``flow.analytic``), made with its
    ``flow.parameters`` and the scene's ``operation.rpm`` and ``operation.gravity``.

    Raises
    ------
    SceneError
        A parameter the flow does not take (with the nearest one it does), rpm or
        gravity given as a parameter (they are the scene's ``operation`` values), or a
        value set that only the solver's flows use (``flow.cell``, ``flow.phases``,
        the ``solver`` section), named.
    """
    from . import flows

    scene = load_scene(scene)
    name = scene["flow"]["analytic"]
    maker = getattr(flows, name)
    params = dict(scene["flow"].get("parameters", {}))
    allowed = list(inspect.signature(maker).parameters)
    faults = []
    for key in params:
        if key in ANALYTIC_FROM_SCENE:
            faults.append(
                f"flow.parameters.{key}: set {ANALYTIC_FROM_SCENE[key]} instead (one value "
                "for the flow and the mixing)"
            )
        elif key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f"did you mean flow.parameters.{close[0]}?" if close else "allowed: "
            allowed_here = [a for a in allowed if a not in ANALYTIC_FROM_SCENE]
            faults.append(
                f"flow.parameters.{key} is not a parameter of the analytic flow {name}; "
                + (hint if close else hint + ", ".join(allowed_here))
            )
    for key in SOLVER_ONLY:
        if scene.given(key) is not None:
            faults.append(
                f"{key} is used by the solver's flows only; the analytic flow {name} "
                "makes its own grid (flow.parameters.cells)"
            )
    if scene.given("solver") is not None:
        faults.append(
            f"the solver section is used by flow.source = 'solver' only, not by the "
            f"analytic flow {name}"
        )
    if faults:
        raise SceneError(faults)
    for key, dotted in ANALYTIC_FROM_SCENE.items():
        section, field = dotted.split(".")
        if key in allowed:
            params[key] = scene[section][field]
    return maker(**params)


def scene_flow(
    scene,
    *,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    flow_path: str | os.PathLike | None = None,
    progress: bool | None = None,
    checkpoint: str | os.PathLike | None = None,
):
    """The flow a scene asks for: a file, an analytic flow, or the solver's (cached).

    Parameters
    ----------
    scene : Scene, str or mapping
    cache : path, optional
        Folder of cached flows (default :func:`cache_folder`).
    use_cache : bool
        Read a cached flow when there is one, and store a newly solved one.
    flow_path : path, optional
        A flow file to use instead of the scene's own flow.
    progress : bool, optional
        Progress bar of the solver.
    checkpoint : path, optional
        Solver checkpoint; with the cache on, one is kept beside the cached flow, so a
        killed solve resumes where it stopped.

    Returns
    -------
    flow : xarray.Dataset
    source : FlowSource
    """
    from . import solve_flow
    from .io import open_flow, write_dataset, write_json

    scene = load_scene(scene)
    if flow_path is not None:
        return open_flow(flow_path), FlowSource("file", path=str(flow_path))
    spec = scene["flow"]
    if spec["source"] == "analytic":
        return analytic_flow(scene), FlowSource("analytic", path=spec["analytic"])
    if spec["source"] == "file":
        return open_flow(spec["path"]), FlowSource("file", path=spec["path"])
    if not use_cache:
        return solve_flow(scene, progress=progress, checkpoint=checkpoint), FlowSource("solver")
    key = flow_key(scene)
    folder = cache_folder(cache) / "flows"
    path = folder / f"{key}.nc"
    if path.is_file():
        return open_flow(path), FlowSource("solver", "hit", key, str(path))
    folder.mkdir(parents=True, exist_ok=True)
    resume = Path(checkpoint) if checkpoint is not None else folder / f"{key}.checkpoint"
    flow = solve_flow(scene, progress=progress, checkpoint=resume)
    write_dataset(flow, path)
    write_json({"key": key, "scene": scene.name, **_flow_inputs(scene)}, folder / f"{key}.json")
    if checkpoint is None:
        with contextlib.suppress(FileNotFoundError):
            resume.unlink()
    return open_flow(path), FlowSource("solver", "miss", key, str(path))


@functools.cache
def solver_source_digest() -> str:
    """A hash of the flow solver's source (``blendxr/flow/*.py`` and ``vessels.py``).

    In the cache key beside the version, so that a changed solver between two releases
    (a development install) never reads a flow the old code solved.
    """
    package = Path(__file__).parent
    digest = hashlib.sha256()
    for path in sorted([*(package / "flow").glob("*.py"), package / "vessels.py"]):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def _flow_inputs(scene: Scene) -> dict:
    return {
        "blendxr_version": __version__,
        "solver_source": solver_source_digest(),
        **{name: scene[name] for name in FLOW_SECTIONS if name in scene},
    }


# ------------------------------------------------------------------------------ stages


def _reset_peak_memory() -> bool:
    """Reset the kernel's record of this process's peak resident memory (Linux)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _peak_memory_mb() -> float:
    """Peak resident memory since the last reset (Linux), else since the start, MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / 2**20 if sys.platform == "darwin" else peak / 1024.0


@dataclass
class Stages:
    """Wall time and peak resident memory of each stage of a run."""

    records: dict = field(default_factory=dict)

    @contextlib.contextmanager
    def measure(self, name: str) -> Iterator[None]:
        resettable = _reset_peak_memory()
        started = time.perf_counter()
        try:
            yield
        finally:
            self.records[name] = {
                "wall_s": time.perf_counter() - started,
                "peak_memory_mb": _peak_memory_mb(),
                "peak_memory_scope": "stage" if resettable else "process so far",
            }


# ------------------------------------------------------------------------------ report


def revolutions_to_level(revolution, values, level: float) -> float | None:
    """The revolution at which a decaying curve first reaches ``level``, or None.

    Between the two records that bracket the crossing the curve is taken as exponential
    in revolutions (log-linear interpolation, exact for a curve that decays at a constant
    rate; linear where a value is not positive).

    Parameters
    ----------
    revolution, values : array_like
        The curve (NaN values are skipped).
    level : float

    Returns
    -------
    float or None
        None when no value is at or below ``level``.
    """
    r = np.asarray(revolution, float)
    v = np.asarray(values, float)
    keep = np.isfinite(r) & np.isfinite(v)
    r, v = r[keep], v[keep]
    below = np.flatnonzero(v <= level)
    if len(below) == 0:
        return None
    i = int(below[0])
    if i == 0:
        return float(r[0])
    r0, r1, v0, v1 = r[i - 1], r[i], v[i - 1], v[i]
    if v0 > 0 and v1 > 0 and level > 0 and v0 != v1:
        f = (math.log(level) - math.log(v0)) / (math.log(v1) - math.log(v0))
    elif v0 != v1:
        f = (level - v0) / (v1 - v0)
    else:
        f = 1.0
    return float(r0 + min(max(f, 0.0), 1.0) * (r1 - r0))


def _finite(value) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _last_finite(values) -> float | None:
    values = np.asarray(values, float)
    finite = values[np.isfinite(values)]
    return float(finite[-1]) if len(finite) else None


def flow_summary(flow) -> dict:
    """The flow's own figures of merit, from its attributes: periodicity (eq. 30, the
    last two revolutions and every two successive ones recorded), the bed's volume and
    the fill's share of the material, and what the solve cost."""
    a = flow.attrs
    out = {"frame": a.get("frame"), "rpm": _finite(a.get("rpm", math.nan))}
    periodicity = {
        c: float(a[f"periodicity_{c}"]) for c in ("vx", "vy", "vz") if f"periodicity_{c}" in a
    }
    if periodicity:
        out["periodicity_eq30"] = periodicity
        out["averaged_revolutions"] = int(a.get("averaged_revolutions", 1) or 1)
    if "periodicity_history_revolution" in a:
        history = {"revolution": np.atleast_1d(a["periodicity_history_revolution"]).tolist()}
        for c in ("vx", "vy", "vz"):
            if f"periodicity_history_{c}" in a:
                history[c] = np.atleast_1d(a[f"periodicity_history_{c}"]).tolist()
        out["periodicity_history"] = history
    if "occupied_volume_over_seeded" in a:
        out["volume_over_seeded"] = {
            "by_J": float(a["current_volume_over_seeded"]),
            "by_spacing": float(a["occupied_volume_over_seeded"]),
        }
    if "fill_volume_m3" in a and a.get("material_volume_m3"):
        out["fill_share"] = float(a["fill_volume_m3"]) / float(a["material_volume_m3"])
        out["fill_clipped_max"] = float(a.get("fill_clipped_max", math.nan))
    for name in (
        "particles",
        "steps",
        "wall_time_s",
        "particle_updates_per_s",
        "stiffness_scaling",
        "cell",
    ):
        if name in a:
            value = a[name]
            out[name] = value.item() if hasattr(value, "item") else value
    return out


def _blocks(last: int, n: int) -> str:
    """``"3-4"`` for revolution 4 against 3; ``"1-2 to 3-4"`` for blocks of two (the
    first block may be shorter: ``"1 to 2-4"``)."""
    if n == 1:
        return f"{last - 1}-{last}"

    def span(first, end):
        return f"{first}" if first == end else f"{first}-{end}"

    return f"{span(max(1, last - 2 * n + 1), last - n)} to {span(last - n + 1, last)}"


def flow_lines(summary: Mapping) -> list[str]:
    """The lines that say how good a solved flow is (:func:`flow_summary`)."""
    lines = []
    n = summary.get("averaged_revolutions", 1)
    if "periodicity_eq30" in summary:
        between = (
            "the last two revolutions"
            if n == 1
            else f"the averages of the last {n} revolutions and of the {n} before"
        )
        lines.append(
            f"periodicity between {between} (eq. 30): "
            + ", ".join(f"{c} {v:.1%}" for c, v in summary["periodicity_eq30"].items())
        )
    if "periodicity_history" in summary:
        history = dict(summary["periodicity_history"])
        turned = history.pop("revolution")
        parts = " / ".join(c[1] for c in history)
        lines.append(
            f"eq. 30 by revolution ({parts}): "
            + "; ".join(
                _blocks(int(j), n) + " " + " / ".join(f"{v:.1%}" for v in row)
                for j, row in zip(turned, zip(*history.values(), strict=True), strict=True)
            )
        )
    if "volume_over_seeded" in summary:
        # a dilating bed keeps changing its flow (docs/flow.md, the dilation angle)
        v = summary["volume_over_seeded"]
        lines.append(
            f"bed volume over the seeded at the end: {v['by_J']:.3f} as the solver carries "
            f"it (J), {v['by_spacing']:.3f} by the particles' spacing"
        )
    if "fill_share" in summary:
        # cells packed past a full cell are clipped, and the flow's bed loses that much
        lines.append(
            f"the flow's fill holds {summary['fill_share']:.1%} of the bed's material "
            f"(largest cell {summary['fill_clipped_max']:.2f} before clipping)"
        )
    return lines


def mixing_summary(mixed, levels=RSD_LEVELS) -> dict:
    """Revolutions to each RSD level, the final RSD and intensity, the floors."""
    a = mixed.attrs
    rev = mixed["revolution"].values
    rsd = mixed["rsd"].values
    intensity = mixed["intensity"].values
    reached = {}
    for level in levels:
        r = revolutions_to_level(rev, rsd, level)
        reached[f"{level:g}"] = r
    cells = mixed["intensity_cells"].values if "intensity_cells" in mixed else None
    return {
        "scheme": a.get("scheme"),
        "grid_cells": [int(n) for n in np.atleast_1d(a.get("grid_cells", []))],
        "k1": float(a.get("k1", math.nan)),
        "loading": a.get("initial"),
        "revolutions_run": float(rev[-1]),
        "stopped_by": a.get("stopped_by"),
        "revolutions_to_rsd": reached,
        "final_rsd": float(rsd[-1]),
        "final_intensity": _last_finite(intensity),
        "random_mixture_intensity": _finite(a.get("random_mixture_intensity", math.nan)),
        "random_mixture_rsd": _finite(a.get("random_mixture_rsd", math.nan)),
        "sampling_cell_m": float(a.get("sampling_cell", math.nan)),
        "intensity_cells": (
            [int(cells.min()), int(cells.max())] if cells is not None and len(cells) else None
        ),
        "species_mass_drift": float(a.get("mass_a_relative_drift", math.nan)),
        "steps": int(a.get("steps", 0)),
        "dt_s": [float(a.get("dt_min", math.nan)), float(a.get("dt_max", math.nan))],
        "wall_time_s": float(a.get("wall_time_s", math.nan)),
        "cell_updates_per_s": float(a.get("cell_updates_per_s", math.nan)),
    }


def report_lines(report: Mapping) -> list[str]:
    """The report as the lines ``blendxr run`` prints."""
    m = report["mixing"]
    f = report["flow"]
    lines = [report["flow_source"], *flow_lines(f)]
    lines.append(
        f"mixing: {m['scheme']}, grid {m['grid_cells']}, k1 = {m['k1']:g}, {m['steps']} steps, "
        f"dt {m['dt_s'][0]:.3g}..{m['dt_s'][1]:.3g} s, wall time {m['wall_time_s']:.2f} s, "
        f"{m['cell_updates_per_s'] / 1e6:.3g} M cell updates/s, "
        f"species mass drift {m['species_mass_drift']:.2e}"
    )
    parts = []
    for level, r in m["revolutions_to_rsd"].items():
        parts.append(f"{level}: {r:.2f}" if r is not None else f"{level}: not reached")
    lines.append("revolutions to RSD " + "; ".join(parts))
    floor_rsd, floor_i = m["random_mixture_rsd"], m["random_mixture_intensity"]
    last_i = m["final_intensity"]
    lines.append(
        f"after {m['revolutions_run']:g} revolutions ({m['stopped_by']}): RSD {m['final_rsd']:.4f}"
        + (f", intensity {last_i:.4f}" if last_i is not None else ", intensity n/a")
    )
    if floor_i is not None:
        lines.append(
            f"random-mixture floor on {1e3 * m['sampling_cell_m']:.3g} mm sampling cells: "
            f"intensity {floor_i:.4f}, RSD {floor_rsd:.4f}"
        )
    stages = report["stages"]
    lines.append(
        "cost: "
        + "; ".join(
            f"{name} {s['wall_s']:.1f} s, {s['peak_memory_mb']:.0f} MiB peak"
            for name, s in stages.items()
        )
    )
    return lines


# ------------------------------------------------------------------------------ run


def check_output_folder(output: str | os.PathLike) -> Path:
    """The output folder, created; refused before any work if it is a file."""
    from .io import remove_stale_temporaries

    out = Path(output)
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"output folder {out} is an existing file; give a folder")
    out.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(out)
    return out


def run_scene(
    scene,
    output: str | os.PathLike = ".",
    *,
    cache: str | os.PathLike | None = None,
    use_cache: bool = True,
    flow_path: str | os.PathLike | None = None,
    progress: bool | None = None,
    checkpoint: str | os.PathLike | None = None,
    save_flow: bool = True,
    **mix_overrides,
) -> dict:
    """Flow -> mixing -> report for a scene, as ``blendxr run`` does.

    Writes ``flow.nc`` (unless ``save_flow`` is False), ``mixing.nc``, ``report.json``,
    ``mixing.png`` (RSD and intensity against revolutions) and ``snapshots.png``
    (concentration on the mid-planes) into ``output``.

    Parameters
    ----------
    scene : Scene, str or mapping
    output : path
        Output folder (created; an existing file is refused before any work).
    cache, use_cache, flow_path, progress
        As for :func:`scene_flow`.
    checkpoint : path, optional
        Mixing checkpoint (the flow solve checkpoints beside the cache by itself).
    save_flow : bool
        Also write the flow into ``output``.
    **mix_overrides
        Passed to :func:`blendxr.mix`.

    Returns
    -------
    dict
        The report (as written to ``report.json``).
    """
    from . import mix
    from .io import staged_outputs, write_dataset, write_json
    from .plot import save_mixing_figure, save_snapshot_figure

    scene = load_scene(scene)
    out = check_output_folder(output)
    stages = Stages()
    with stages.measure("flow"):
        flow, source = scene_flow(
            scene, cache=cache, use_cache=use_cache, flow_path=flow_path, progress=progress
        )
    with stages.measure("mixing"):
        mixed = mix(flow, scene, progress=progress, checkpoint=checkpoint, **mix_overrides)
    # every output staged, then renamed together: a folder holds one run's outputs
    with staged_outputs(out) as stage:
        with stages.measure("report"):
            write_dataset(mixed, stage("mixing.nc"))
            if save_flow:
                stored = flow.copy()
                stored.attrs["scene"] = scene.to_toml()  # same flow inputs by the cache key
                write_dataset(stored, stage("flow.nc"))
            save_mixing_figure(mixed, stage("mixing.png"))
            save_snapshot_figure(mixed, stage("snapshots.png"))
        report = _report(scene, source, flow, mixed, stages, save_flow)
        write_json(report, stage("report.json"))
    return report


def _report(scene, source, flow, mixed, stages, save_flow: bool) -> dict:
    """The run's report (``report.json``)."""
    return {
        "scene": scene.name,
        "blendxr_version": __version__,
        "flow_source": source.describe(),
        "flow_cache": {"state": source.cache, "key": source.key, "path": source.path},
        "flow": flow_summary(flow),
        "mixing": mixing_summary(mixed),
        "stages": stages.records,
        "files": ["mixing.nc", "mixing.png", "snapshots.png", "report.json"]
        + (["flow.nc"] if save_flow else []),
    }
