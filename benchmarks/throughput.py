"""ADE throughput on a 100^3 grid, memory bandwidth, and where a step's time goes.

Cases (every scheme, ``cells=100``, shear diffusivity k1 = 0.01, d = 2 mm):

- ``swirl-3d``: the 72-phase transient 3-D swirl in a full 0.2 m box
  (``bx.flows.swirl(ndim=3, cells=50, n_phases=72, rpm=10, size=0.2)``): every cell is
  material, so this is the throughput of a full grid;
- ``sbr-3d-40pct``: solid-body rotation of a cylinder 40 % full
  (``bx.flows.solid_body_rotation(ndim=3, radius=0.1, cells=50, fill_fraction=0.4,
  n_phases=72)``): the work skipped in empty cells;
- ``tote-40pct``: the solver's flow of ``tote-small`` (a Tote 40 % full, 12 phases, 20 mm
  flow cell; solved once into the flow cache), mixed for a quarter revolution on 100^3
  cells: a real vessel, with many steps between two stored phases (about 80).

Each scheme is compiled on a tiny run first; then two windows are timed. The short window
is a fixed simulated time (enough for at least 20 steps) with records at its ends only,
where each phase pair's set-up (stable dt, first reading of its phases) weighs as much as
the steps; the steady window (Lax-Wendroff and finite-volume, the schemes with targets)
runs two revolutions with the default records (the schema's mixing.output_every), the
share a long run pays for that set-up. Each is run and timed twice (up to four times
while other work on the machine slows the runs, see ``_common.best_of``); the fastest run
is kept.
Reported per run: steps, seconds per step, the ``cell_updates_per_s`` attribute of the
result (cells counted by the driver over the whole ``mix`` call), and an independent
figure: steps x material cells / wall time, with the material cells taken from the
flow's fill (material volume / ADE cell volume).

A second, profiled run (cProfile) of each case and scheme splits the wall time into the step
kernels and the rest (stability limits, blending of phases, records, set-up); the kernel
share and a kernel-only rate go into the JSON.

Memory bandwidth: a STREAM-like triad ``a[i] = b[i] + s c[i]`` (numba prange, 40 M
float64 per array, best of 5, 24 bytes per element counted as STREAM does), and the
bound it implies for an update that only reads and writes c (16 bytes per cell update).
For scale, two plain 19-point stencils (numba prange, 102^3 doubles, 100^3 updated) are
timed on the same machine: one with constant coefficients, and the reference the targets
are stated against: the Lax-Wendroff stencil's arithmetic with six per-cell coefficient
arrays (what a step must read at the least), no classes, no free surface. Each whole
``bx.mix`` run's rate is printed as a ratio to that reference (targets: Lax-Wendroff
>= 0.3, finite-volume >= 0.2), and its wall time per simulated revolution, the figure
that compares schemes whose steps differ in length (semi-Lagrangian steps are several
times the advective limit, so fewer, dearer updates).

Run: ``python benchmarks/throughput.py`` (5-15 minutes on 2 cores, the more the busier
the machine). Writes ``benchmarks/results/throughput.json``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import cProfile  # noqa: E402
import math  # noqa: E402
import pstats  # noqa: E402
import time  # noqa: E402

import numba  # noqa: E402
import numpy as np  # noqa: E402
from _common import (
    Contention,
    best_of,
    cpu_pressure,
    echo,
    load_average,
    machine,
    machine_line,
    table,
    wait_for_quiet,
    write_json,
)  # noqa: E402
from numba import njit, prange  # noqa: E402

import blendxr as bx  # noqa: E402
from blendxr.scene import default_of  # noqa: E402

CELLS = 100
MIN_STEPS = 20
REVOLUTIONS = 0.1  # about 50 steps of either scheme on these flows; doubled if too few
#: the steady window: a run long enough that each phase pair's set-up (stable dt, first
#: reading of the phases) is a share a long run also pays, with the scene schema's default
#: records; Lax-Wendroff and finite-volume only (the schemes with targets)
STEADY_REVOLUTIONS = 2.0
STEADY_OUTPUT_EVERY = default_of("mixing.output_every")
REPEATS = 2  # timed runs per case and scheme; the fastest is kept
MAX_REPEATS = 4  # more while every run so far was stalled by other work on the machine
BUDGET_S = 150.0  # seconds of timed runs per case and scheme, at most
PHYSICS = {"initial": "top-bottom", "k1": 0.01, "d": 0.002}
#: whole-run rate as a share of the per-cell-coefficient stencil's, per scheme (targets)
RATIO_TARGET = {"lax-wendroff": 0.3, "finite-volume": 0.2}  # none for semi-lagrangian
TRIAD_N = 40_000_000
TRIAD_REPEATS = 5
BYTES_C_ONLY = 16  # read c, write c_next: 2 x 8 bytes per cell update


#: the solver's flow of a real vessel: tote-small's (40 % fill, 20 mm cell, 12 phases),
#: solved once and cached (about a minute), mixed for this many revolutions
TOTE_SCENE = "tote-small"
TOTE_REVOLUTIONS = 0.25


def tote_flow():
    """tote-small's flow from the flow cache (solved on the first run)."""
    from _common import flow_cache

    from blendxr import pipeline

    flow, _ = pipeline.scene_flow(bx.load_scene(TOTE_SCENE), cache=flow_cache(), progress=False)
    return flow


def flows():
    return {
        "swirl-3d": bx.flows.swirl(ndim=3, cells=50, n_phases=72, rpm=10.0, size=0.2),
        "sbr-3d-40pct": bx.flows.solid_body_rotation(
            ndim=3, radius=0.1, cells=50, fill_fraction=0.4, n_phases=72
        ),
        "tote-40pct": tote_flow(),
    }


def warm_up() -> float:
    """Compile every 3-D kernel (and the driver's paths) on tiny runs."""
    started = time.perf_counter()
    tiny = [
        bx.flows.swirl(ndim=3, cells=8, n_phases=4, rpm=10.0, size=0.2),
        bx.flows.solid_body_rotation(ndim=3, radius=0.1, cells=8, fill_fraction=0.4, n_phases=4),
    ]
    for flow in tiny:
        for scheme in bx.SCHEMES:
            bx.mix(flow, scheme=scheme, cells=12, revolutions=0.02, progress=False, **PHYSICS)
    return time.perf_counter() - started


def material_cells(flow, cells: int) -> float:
    """Material volume of the flow (mean over phases) in ADE cells of the ``cells`` grid."""
    dims = [d for d in ("x", "y", "z") if d in flow.dims]
    coords = [np.asarray(flow[d].values, float) for d in dims]
    spacing = [c[1] - c[0] for c in coords]
    extent = max(len(c) * h for c, h in zip(coords, spacing, strict=True))
    h_ade = extent / cells
    volume = float(flow["fill"].sum(dim=dims).mean()) * float(np.prod(spacing))
    return volume / h_ade ** len(dims)


def run(flow, scheme: str, revolutions: float, output_every: float | None = None):
    """Timed runs (see ``best_of``): the fastest, with its wall time and contention."""

    def once():
        return bx.mix(
            flow,
            scheme=scheme,
            cells=CELLS,
            revolutions=revolutions,
            output_every=output_every or revolutions,
            progress=False,
            **PHYSICS,
        )

    return best_of(once, min_runs=REPEATS, max_runs=MAX_REPEATS, budget_s=BUDGET_S)


def _stat(stats: dict, funcname: str, file_suffix: str, field: int) -> float | None:
    """Sum of one pstats field over the functions of that name in that file (None: absent)."""
    found = [
        values[field]
        for (filename, _line, name), values in stats.items()
        if name == funcname and filename.replace(os.sep, "/").endswith(file_suffix)
    ]
    return sum(found) if found else None


def profile_split(
    flow, scheme: str, revolutions: float, material: float, output_every: float | None = None
) -> dict:
    """Profile one run; split its wall time into the stepping kernels and the rest.

    Buckets are cumulative times of the scheme's methods (``blendxr/ade/schemes``):
    ``step`` (the kernels of one step and their call), ``prepare`` (per-cell data of the
    flow blended between two phases, made a few times per interval), ``begin_interval``
    (diffusion sub-steps), ``max_dt`` (stable dt per phase pair), and the driver's
    ``record`` + ``check`` (mixing curves, bounds); the rest is set-up, phase reading on
    the main thread and the result.
    """

    def once():
        profiler = cProfile.Profile()
        profiler.enable()
        mixed = bx.mix(
            flow,
            scheme=scheme,
            cells=CELLS,
            revolutions=revolutions,
            output_every=output_every or revolutions,
            progress=False,
            **PHYSICS,
        )
        profiler.disable()
        return mixed, pstats.Stats(profiler).stats

    timed = best_of(once, min_runs=1, max_runs=MAX_REPEATS, budget_s=BUDGET_S, quiet_wait_s=60)
    (mixed, stats), wall = timed["result"], timed["wall_s"]
    module = f"ade/schemes/{scheme.replace('-', '_')}.py"
    # a method the scheme does not override is the base class's
    cum = {
        name: _stat(stats, name, module, 3) or _stat(stats, name, "ade/schemes/base.py", 3)
        for name in ("step", "prepare", "max_dt", "begin_interval")
    }
    cum.update({name: _stat(stats, name, "ade/stepper.py", 3) for name in ("record", "check")})
    missing = sorted(name for name, value in cum.items() if value is None)
    cum = {name: value or 0.0 for name, value in cum.items()}
    buckets = {
        "step_kernels": cum["step"],
        "prepare_blended_flow": cum["prepare"],
        "interval_setup": cum["begin_interval"],
        "stability_limits": cum["max_dt"],
        "records_and_checks": cum["record"] + cum["check"],
    }
    buckets["other_setup_phase_reading_result"] = max(wall - sum(buckets.values()), 0.0)
    # own time of every function of the kernels module (numba dispatchers count the
    # compiled kernel's time as their own)
    all_kernels = sum(
        v[2]
        for (filename, _line, _name), v in stats.items()
        if filename.replace(os.sep, "/").endswith("ade/kernels.py")
    )
    top = sorted(stats.items(), key=lambda kv: kv[1][2], reverse=True)[:12]
    steps = int(mixed.attrs["steps"])
    step_time = buckets["step_kernels"]
    return {
        "wall_s": wall,
        "steps": steps,
        "seconds": buckets,
        "share": {k: v / wall for k, v in buckets.items()},
        "kernel_share": step_time / wall,
        "outside_kernels_share": 1.0 - step_time / wall,
        "all_kernels_module_share": all_kernels / wall,
        "kernel_s_per_step": step_time / steps,
        "outside_kernels_s_per_step": (wall - step_time) / steps,
        "kernel_only_cell_updates_per_s": steps * material / step_time if step_time else None,
        "kernels_with_preparation_cell_updates_per_s": (
            steps * material / (step_time + buckets["prepare_blended_flow"]) if step_time else None
        ),
        "contention": timed["contention"],
        "profiled_runs_wall_s": timed["walls"],
        "driver_methods_not_found": missing,
        "top_by_own_time": [
            {
                "function": f"{os.path.basename(f)}:{line}({name})",
                "calls": int(v[1]),
                "own_s": round(v[2], 4),
                "cumulative_s": round(v[3], 4),
            }
            for (f, line, name), v in top
        ],
        "note": "cProfile sees the main thread only; the phase prefetch thread is not in it. "
        "kernel_share = time in the scheme's step (the stepping kernels) / wall time.",
    }


# ------------------------------------------------------------------------------ bandwidth


@njit(parallel=True, cache=False)
def _triad(a, b, c, s):
    for i in prange(a.size):
        a[i] = b[i] + s * c[i]


@njit(parallel=True, cache=False)
def _stencil19(c, out, w0, w1, w2):
    nx, ny, nz = c.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            for k in range(1, nz - 1):
                face = (
                    c[i - 1, j, k]
                    + c[i + 1, j, k]
                    + c[i, j - 1, k]
                    + c[i, j + 1, k]
                    + c[i, j, k - 1]
                    + c[i, j, k + 1]
                )
                edge = (
                    c[i - 1, j - 1, k]
                    + c[i - 1, j + 1, k]
                    + c[i + 1, j - 1, k]
                    + c[i + 1, j + 1, k]
                    + c[i - 1, j, k - 1]
                    + c[i - 1, j, k + 1]
                    + c[i + 1, j, k - 1]
                    + c[i + 1, j, k + 1]
                    + c[i, j - 1, k - 1]
                    + c[i, j - 1, k + 1]
                    + c[i, j + 1, k - 1]
                    + c[i, j + 1, k + 1]
                )
                out[i, j, k] = w0 * c[i, j, k] + w1 * face + w2 * edge


@njit(parallel=True, cache=False)
def _stencil19_per_cell(c, out, coef):
    """The Lax-Wendroff stencil's arithmetic, six per-cell coefficients, every cell."""
    nx, ny, nz = c.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            for k in range(1, nz - 1):
                nux, nuy, nuz = coef[0, i, j, k], coef[1, i, j, k], coef[2, i, j, k]
                c0 = c[i, j, k]
                xp, xm, yp, ym = c[i + 1, j, k], c[i - 1, j, k], c[i, j + 1, k], c[i, j - 1, k]
                zp, zm = c[i, j, k + 1], c[i, j, k - 1]
                dxy = c[i + 1, j + 1, k] - c[i - 1, j + 1, k] - c[i + 1, j - 1, k]
                dxy += c[i - 1, j - 1, k]
                dyz = c[i, j + 1, k + 1] - c[i, j - 1, k + 1] - c[i, j + 1, k - 1]
                dyz += c[i, j - 1, k - 1]
                dzx = c[i + 1, j, k + 1] - c[i - 1, j, k + 1] - c[i + 1, j, k - 1]
                dzx += c[i - 1, j, k - 1]
                out[i, j, k] = (
                    c0
                    - 0.5 * (nux * (xp - xm) + nuy * (yp - ym) + nuz * (zp - zm))
                    + coef[3, i, j, k] * (xp - 2.0 * c0 + xm)
                    + coef[4, i, j, k] * (yp - 2.0 * c0 + ym)
                    + coef[5, i, j, k] * (zp - 2.0 * c0 + zm)
                    + 0.25 * (nux * nuy * dxy + nuy * nuz * dyz + nuz * nux * dzx)
                )


def triad_bandwidth(threads: int) -> dict:
    numba.set_num_threads(threads)
    a = np.zeros(TRIAD_N)
    b = np.full(TRIAD_N, 1.0)
    c = np.full(TRIAD_N, 2.0)
    _triad(a[:8], b[:8], c[:8], 3.0)  # compile
    times = []
    with Contention() as meter:
        for _ in range(TRIAD_REPEATS):
            started = time.perf_counter()
            _triad(a, b, c, 3.0)
            times.append(time.perf_counter() - started)
    assert a[0] == 7.0
    best = min(times)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return {
        "threads": threads,
        "elements": TRIAD_N,
        "array_mb": TRIAD_N * 8 / 1e6,
        "best_s": best,
        "times_s": times,
        "gb_per_s": 3 * 8 * TRIAD_N / best / 1e9,
        "bytes_counted_per_element": 24,
        "contention": meter.as_dict(),
    }


def stencil19_rate(threads: int, per_cell: bool = False) -> dict:
    numba.set_num_threads(threads)
    n = CELLS + 2
    rng = np.random.default_rng(1)
    c = rng.random((n, n, n))
    out = np.zeros_like(c)
    coef = 0.05 * rng.random((6, n, n, n))

    def once():
        if per_cell:
            _stencil19_per_cell(c, out, coef)
        else:
            _stencil19(c, out, 0.5, 0.05, 0.0167)

    once()  # compile
    times = []
    with Contention() as meter:
        for _ in range(10):
            started = time.perf_counter()
            once()
            times.append(time.perf_counter() - started)
    best = min(times)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    return {
        "threads": threads,
        "grid": [n, n, n],
        "updated_cells": CELLS**3,
        "best_s": best,
        "cell_updates_per_s": CELLS**3 / best,
        "contention": meter.as_dict(),
        "per_cell_coefficients": per_cell,
        "note": (
            "six per-cell coefficient arrays (the Lax-Wendroff stencil's arithmetic)"
            if per_cell
            else "constant coefficients, one array read, one written"
        )
        + "; best of 10",
    }


# ------------------------------------------------------------------------------ main


def _percent(share) -> str:
    return "n/a" if share is None else f"{100 * share:.0f} %"


def main() -> None:
    quiet = wait_for_quiet()
    compile_s = warm_up()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    echo(f"warm-up (compilation or cache load) {compile_s:.1f} s")

    # The reference's rate moves with the host's state (benchmarks/README.md): it is taken
    # before and after the cases and the fastest kept, so that the ratios are not
    # flattered by a slow moment of the reference.
    references = [stencil19_rate(2, per_cell=True)]
    cases = []
    for case, flow in flows().items():
        material = material_cells(flow, CELLS)
        windows = [(scheme, "short", None) for scheme in bx.SCHEMES]
        windows += [(scheme, "steady", STEADY_OUTPUT_EVERY) for scheme in RATIO_TARGET]
        for scheme, window, output_every in windows:
            if window == "steady":
                revolutions = STEADY_REVOLUTIONS
            else:
                revolutions = TOTE_REVOLUTIONS if case == "tote-40pct" else REVOLUTIONS
            while True:
                timed = run(flow, scheme, revolutions, output_every)
                mixed, wall = timed["result"], timed["wall_s"]
                steps = int(mixed.attrs["steps"])
                if steps >= MIN_STEPS:
                    break
                revolutions *= max(2.0, math.ceil(MIN_STEPS / max(steps, 1)))
            a = mixed.attrs
            row = {
                "case": case,
                "scheme": scheme,
                "window": window,
                "revolutions": revolutions,
                "output_every": output_every or revolutions,
                "steps": steps,
                "dt_max_s": float(a["dt_max"]),
                "grid_cells": [int(x) for x in a["grid_cells"]],
                "material_cells": material,
                "counted_updates_per_step": a["cell_updates"] / steps,
                "wall_s": wall,
                "wall_s_all_repeats": timed["walls"],
                "contention": timed["contention"],
                "contention_all_repeats": timed["contentions"],
                "wall_time_s_attr": float(a["wall_time_s"]),
                "s_per_step": wall / steps,
                # the figure that compares schemes taking steps of different length
                "s_per_revolution": wall / revolutions,
                "cell_updates_per_s_attr": float(a["cell_updates_per_s"]),
                "cell_updates_per_s_own": steps * material / wall,
                "phases_read": int(a["phases_read"]),
                "diffusion_substeps_max": int(a["diffusion_substeps_max"]),
            }
            row["profile"] = profile_split(flow, scheme, revolutions, material, output_every)
            cases.append(row)
            extra = f", step kernels {100 * row['profile']['kernel_share']:.0f} % of wall"
            echo(
                f"{case:13s} {scheme:14s} {window:6s} {steps:5d} steps  {wall:7.2f} s  "
                f"{row['cell_updates_per_s_own'] / 1e6:7.2f} M/s{extra}"
            )

    # each measurement is retried (up to 3 times) if other work stalled it
    triads = [best_of(lambda t=t: triad_bandwidth(t), max_runs=3)["result"] for t in (2, 1)]
    bandwidth = triads[0]["gb_per_s"]
    stencils = [best_of(lambda t=t: stencil19_rate(t), max_runs=3)["result"] for t in (2, 1)]
    references += [stencil19_rate(2, per_cell=True) for _ in range(3)]
    reference = max(references, key=lambda r: r["cell_updates_per_s"])
    reference["rates_taken_per_s"] = [r["cell_updates_per_s"] for r in references]
    reference_rate = reference["cell_updates_per_s"]
    for r in cases:
        r["ratio_to_reference_stencil"] = r["cell_updates_per_s_own"] / reference_rate
    bound = bandwidth * 1e9 / BYTES_C_ONLY

    echo()
    echo(f"## ADE throughput, {CELLS}^3 cells, k1 = {PHYSICS['k1']}, d = {PHYSICS['d']} m")
    echo()
    rows = []
    for r in cases:
        rows.append(
            [
                r["case"],
                r["scheme"],
                f"{r['window']} ({r['revolutions']:g} rev)",
                r["steps"],
                r["s_per_step"],
                f"{r['material_cells'] / 1e6:.3f}",
                f"{r['cell_updates_per_s_attr'] / 1e6:.2f}",
                f"{r['cell_updates_per_s_own'] / 1e6:.2f}",
                (
                    f"{r['profile']['kernel_only_cell_updates_per_s'] / 1e6:.2f}"
                    if "profile" in r
                    else "-"
                ),
                f"{100 * r['profile']['kernel_share']:.0f} %" if "profile" in r else "-",
                _percent(r["contention"]["other_cpu_share"]),
                f"{r['ratio_to_reference_stencil']:.3f}",
                f"{r['s_per_revolution']:.1f}",
                f">= {RATIO_TARGET[r['scheme']]}" if r["scheme"] in RATIO_TARGET else "-",
            ]
        )
    echo(
        table(
            [
                "case",
                "scheme",
                "window",
                "steps",
                "s/step",
                "material cells (M)",
                "attr M upd/s",
                "own M upd/s",
                "kernel-only M upd/s",
                "kernel share",
                "others' CPU",
                "ratio to reference stencil",
                "wall s / rev",
                "target",
            ],
            rows,
            align="lllrrrrrrrrrrr",
        )
    )
    echo()
    echo("## Where the wall time goes (cProfile, a second run of each case)")
    echo()
    rows = []
    for r in cases:
        if "profile" not in r:
            continue
        p = r["profile"]
        rows.append(
            [r["case"], r["scheme"], r["window"], p["wall_s"], p["steps"]]
            + [f"{100 * p['share'][k]:.0f} %" for k in p["seconds"]]
            + [_percent(p["contention"]["other_cpu_share"])]
        )
    echo(
        table(
            [
                "case",
                "scheme",
                "window",
                "wall s",
                "steps",
                "step kernels",
                "prepare (blend)",
                "interval set-up",
                "stability limits",
                "records/checks",
                "other (set-up, phase prep)",
                "others' CPU",
            ],
            rows,
            align="lllrrrrrrrrr",
        )
    )
    echo()
    echo("## Memory bandwidth and bounds")
    echo()
    lw = next(
        r
        for r in cases
        if r["scheme"] == "lax-wendroff" and r["case"] == "swirl-3d" and r["window"] == "steady"
    )
    rows = [
        [
            f"triad a = b + s c, {t['threads']} thread(s), 3 x {t['array_mb']:.0f} MB",
            f"{t['gb_per_s']:.2f} GB/s",
            "",
        ]
        for t in triads
    ]
    rows += [["bound, read + write c only (16 B/update)", f"{bound / 1e6:.0f} M upd/s", ""]]
    rows += [
        [
            f"plain 19-point stencil, measured here, {t['threads']} thread(s)",
            f"{t['cell_updates_per_s'] / 1e6:.0f} M upd/s",
            "",
        ]
        for t in stencils
    ]
    rows += [
        [
            "reference: 19-point stencil, six per-cell coefficients, 2 threads "
            "(fastest of "
            + " / ".join(f"{r / 1e6:.0f}" for r in reference["rates_taken_per_s"])
            + " M, before and after the cases)",
            f"{reference_rate / 1e6:.0f} M upd/s",
            f"Lax-Wendroff whole run (steady) {lw['ratio_to_reference_stencil']:.3f} of it "
            f"(target {RATIO_TARGET['lax-wendroff']})",
        ],
    ]
    echo(table(["quantity", "value", "comparison"], rows, align="lrl"))

    payload = {
        "benchmark": "throughput",
        "machine": info,
        "settings": {
            "cells": CELLS,
            "min_steps": MIN_STEPS,
            **PHYSICS,
            "flows": {
                "swirl-3d": "swirl(ndim=3, cells=50, n_phases=72, rpm=10.0, size=0.2)",
                "sbr-3d-40pct": "solid_body_rotation(ndim=3, radius=0.1, cells=50, "
                "fill_fraction=0.4, n_phases=72)",
                "tote-40pct": f"the solver's flow of {TOTE_SCENE} (cached), "
                f"{TOTE_REVOLUTIONS} revolution",
            },
            "warm_up_s": compile_s,
            "definitions": {
                "cell_updates_per_s_attr": "attribute of the mix result: cells counted by "
                "the driver per step, summed, over the wall time of the whole mix call",
                "cell_updates_per_s_own": "steps x material cells (material volume of the "
                "flow / ADE cell volume) / wall time of the mix call timed here",
                "s_per_step": "wall time of the mix call / steps (set-up included)",
                "kernel_only_cell_updates_per_s": "steps x material cells / time inside "
                "the step kernels (profiled run)",
            },
        },
        "runs": cases,
        "bandwidth": {
            "triad": triads,
            "gb_per_s": bandwidth,
            "c_only_bound_cell_updates_per_s": bound,
            "bytes_per_cell_update": BYTES_C_ONLY,
        },
        "stencil19_measured": stencils,
        "reference_stencil": reference,
        "targets": {"ratio_to_reference_stencil": RATIO_TARGET},
        "load_average_at_end": load_average(),
        "cpu_pressure_at_end": cpu_pressure(),
    }
    path = write_json("throughput", payload)
    echo()
    echo(f"wrote {path.relative_to(path.parents[2])}")


if __name__ == "__main__":
    main()
