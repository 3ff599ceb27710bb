"""Error against wall time of every ADE scheme on two problems with exact answers.

Cases, each on four grids, one revolution:

- ``sbr-3d``: solid-body rotation (10 rpm) of a full cylinder (R = 0.1 m) carrying a
  Gaussian bump (centre (0.045, 0, 0) m, sigma = 18 mm, on a background of 0.2) with an
  isotropic constant diffusivity D = 2e-6 m2/s. After one revolution the exact answer is
  the Gaussian back at its start, its variance grown by 2 D T. Errors are taken in
  r < 0.8 R, |z| < 0.6 R (away from the wall). Grids: 16, 24, 32, 48 cells.
- ``swirl-2d``: LeVeque's time-reversing swirl (unit box, 60 rpm, 72 phases) carrying a
  Gaussian bump (centre (0.5, 0.3), sigma = 0.1) with no diffusion (k1 = 0). After one
  revolution the exact answer is the initial state. Errors over the whole box. Grids:
  32, 64, 128, 256 cells.

A time-step study reruns one grid per case at 0.9, 0.3 and 0.1 of the stable dt
(``safety``), to tell time error from space error.

Per run: L1 error (sum of |c - exact| times the cell volume over the error window, as in
tests/test_mix.py), max error, observed orders from successive grids
(log(e1 / e2) / log(h1 / h2)), wall time of the ``mix`` call (after a warm-up that
compiles the kernels; fastest of repeated runs, see ``_common.best_of``), steps and the
species mass drift (``mass_a_relative_drift``).

Run: ``python benchmarks/work_precision.py`` (1-4 minutes on 2 cores). Writes
``benchmarks/results/work_precision.{json,md,png}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import io  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    RESULTS,
    best_of,
    cpu_pressure,
    echo,
    load_average,
    machine,
    machine_line,
    table,
    wait_for_quiet,
    write_atomic,
    write_json,
)

import blendxr as bx  # noqa: E402

RADIUS, RPM_SBR, DIFFUSION = 0.1, 10.0, 2.0e-6
SBR_CENTRE, SBR_SIGMA2 = (0.045, 0.0, 0.0), 0.018**2
SWIRL_CENTRE, SWIRL_SIGMA2 = (0.5, 0.3), 0.1**2
GRIDS = {"sbr-3d": (16, 24, 32, 48), "swirl-2d": (32, 64, 128, 256)}
DT_STUDY_CELLS = {"sbr-3d": 32, "swirl-2d": 128}  # grid of the time-step study per case
SAFETIES = (0.9, 0.3, 0.1)  # fractions of the stable dt in the time-step study
REPEATS = 3  # timed runs per grid (the answers are identical; the fastest is kept) ...
BUDGET_S = 40.0  # ... while their total stays below this (long runs: fewer)
MAX_REPEATS = 5  # more runs, within the budget, while other work stalled every run so far


def gaussian(centre, sigma2, background=0.2, amplitude=0.6):
    """Initial c: a Gaussian bump on a constant background (inside [0, 1])."""

    def c0(*points):
        r2 = sum((p - c) ** 2 for p, c in zip(points, centre, strict=True))
        return background + amplitude * np.exp(-r2 / (2 * sigma2))

    return c0


def spread_gaussian(points, centre, sigma2, diffusivity, t, background=0.2, amplitude=0.6):
    """Exact solution for a Gaussian at rest under constant diagonal diffusion for time t."""
    value = np.full(points[0].shape, amplitude)
    for p, c, d in zip(points, centre, diffusivity, strict=True):
        s2 = sigma2 + 2 * d * t
        value = value * np.sqrt(sigma2 / s2) * np.exp(-((p - c) ** 2) / (2 * s2))
    return background + value


def final_field(mixed):
    c = mixed["c"].isel(snapshot=-1)
    points = np.meshgrid(*[c[d].values for d in c.dims], indexing="ij")
    return c.values, points


def errors(values, exact, spacing, window):
    inside = window & np.isfinite(values)
    diff = np.abs(values - exact)[inside]
    return float(diff.sum() * np.prod(spacing)), float(diff.max()), int(inside.sum())


def case_sbr(cells):
    # a linear velocity field: interpolation from any flow grid is exact
    flow = bx.flows.solid_body_rotation(ndim=3, radius=RADIUS, cells=32, rpm=RPM_SBR)
    period = 60.0 / RPM_SBR
    kwargs = {"initial": gaussian(SBR_CENTRE, SBR_SIGMA2), "diffusivity": (DIFFUSION,) * 3}

    def exact_and_window(points):
        exact = spread_gaussian(points, SBR_CENTRE, SBR_SIGMA2, (DIFFUSION,) * 3, period)
        r = np.hypot(points[0], points[1])
        return exact, (r < 0.8 * RADIUS) & (np.abs(points[2]) < 0.6 * RADIUS)

    return flow, kwargs, exact_and_window


def case_swirl(cells):
    # the flow refined with the ADE grid, so that its interpolation error shrinks too
    flow = bx.flows.swirl(ndim=2, cells=cells, n_phases=72, rpm=60.0, size=1.0)
    start = gaussian(SWIRL_CENTRE, SWIRL_SIGMA2)
    kwargs = {"initial": start, "k1": 0.0}

    def exact_and_window(points):
        return start(*points), np.ones(points[0].shape, bool)

    return flow, kwargs, exact_and_window


CASES = {"sbr-3d": case_sbr, "swirl-2d": case_swirl}


def run_one(flow, scheme, cells, kwargs, exact_and_window) -> dict:
    """One revolution on one grid; short runs are repeated and the fastest time kept."""

    def once():
        return bx.mix(
            flow,
            scheme=scheme,
            cells=cells,
            revolutions=1.0,
            output_every=0.5,
            snapshots=[1.0],
            progress=False,
            **kwargs,
        )

    timed = best_of(once, min_runs=REPEATS, max_runs=MAX_REPEATS, budget_s=BUDGET_S)
    mixed, wall = timed["result"], timed["wall_s"]
    values, points = final_field(mixed)
    exact, window = exact_and_window(points)
    spacing = mixed.attrs["grid_spacing"]
    l1, emax, n_window = errors(values, exact, spacing, window)
    return {
        "cells": cells,
        "grid_cells": [int(x) for x in mixed.attrs["grid_cells"]],
        "h_m": float(spacing[0]),
        "steps": int(mixed.attrs["steps"]),
        "dt_max_s": float(mixed.attrs["dt_max"]),
        "wall_s": wall,
        "wall_s_all_repeats": timed["walls"],
        "contention": timed["contention"],
        "wall_time_s_attr": float(mixed.attrs["wall_time_s"]),
        "l1_error": l1,
        "max_error": emax,
        "window_cells": n_window,
        "mass_a_relative_drift": float(mixed.attrs["mass_a_relative_drift"]),
        "diffusion_substeps_max": int(mixed.attrs["diffusion_substeps_max"]),
    }


def dt_study(flow, scheme, cells, kwargs, exact_and_window) -> list[dict]:
    """The same grid at several fractions of the stable dt: separates time from space error.

    If the L1 error falls in proportion to dt at a fixed grid, the time error dominates
    and, since the stable dt shrinks with h, the observed order in h is that of time.
    """
    rows = []
    for safety in SAFETIES:
        mixed = bx.mix(
            flow,
            scheme=scheme,
            cells=cells,
            revolutions=1.0,
            output_every=0.5,
            snapshots=[1.0],
            safety=safety,
            progress=False,
            **kwargs,
        )
        values, points = final_field(mixed)
        exact, window = exact_and_window(points)
        l1, emax, _ = errors(values, exact, mixed.attrs["grid_spacing"], window)
        rows.append(
            {
                "cells": cells,
                "safety": safety,
                "steps": int(mixed.attrs["steps"]),
                "dt_max_s": float(mixed.attrs["dt_max"]),
                "l1_error": l1,
                "max_error": emax,
            }
        )
    for row in rows:
        row["l1_relative_to_first"] = row["l1_error"] / rows[0]["l1_error"]
        # mean dt over the revolution (dt_max is capped by the phase interval where the
        # flow is slow, so it does not follow the safety factor)
        row["mean_dt_relative_to_first"] = rows[0]["steps"] / row["steps"]
    return rows


def observed_orders(rows, key):
    orders = [None]
    for a, b in zip(rows[:-1], rows[1:], strict=True):
        if a[key] > 0 and b[key] > 0:
            orders.append(math.log(a[key] / b[key]) / math.log(a["h_m"] / b["h_m"]))
        else:
            orders.append(None)
    return orders


def warm_up() -> float:
    started = time.perf_counter()
    for case in CASES.values():
        flow, kwargs, _ = case(8)
        for scheme in bx.SCHEMES:
            bx.mix(flow, scheme=scheme, cells=8, revolutions=0.05, progress=False, **kwargs)
    return time.perf_counter() - started


def plot(results, path):
    fig, ax = plt.subplots(figsize=(7.5, 5.2), dpi=120)
    styles = {"finite-volume": "-", "lax-wendroff": "--", "semi-lagrangian": ":"}
    markers = {"sbr-3d": "o", "swirl-2d": "s"}
    colours = {
        ("sbr-3d", "finite-volume"): "tab:blue",
        ("sbr-3d", "lax-wendroff"): "tab:cyan",
        ("swirl-2d", "finite-volume"): "tab:red",
        ("swirl-2d", "lax-wendroff"): "tab:orange",
        ("sbr-3d", "semi-lagrangian"): "tab:purple",
        ("swirl-2d", "semi-lagrangian"): "tab:brown",
    }
    for entry in results:
        case, scheme, rows = entry["case"], entry["scheme"], entry["runs"]
        t = [r["wall_s"] for r in rows]
        e = [r["l1_error"] for r in rows]
        ax.loglog(
            t,
            e,
            styles[scheme],
            marker=markers[case],
            color=colours[(case, scheme)],
            label=f"{case}, {scheme}",
        )
        for r in rows:
            ax.annotate(
                str(r["cells"]),
                (r["wall_s"], r["l1_error"]),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=7,
                color=colours[(case, scheme)],
            )
    ax.set_xlabel("wall time of the mix call (s)")
    ax.set_ylabel("L1 error after one revolution")
    ax.set_title("blendxr ADE: work-precision (labels: cells along the longest axis)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")
    plt.close(fig)
    write_atomic(path, buffer.getvalue())


def _percent(share) -> str:
    return "n/a" if share is None else f"{100 * share:.0f} %"


def markdown(results, info) -> str:
    rows = []
    for entry in results:
        l1_orders = observed_orders(entry["runs"], "l1_error")
        max_orders = observed_orders(entry["runs"], "max_error")
        for r, p1, pm in zip(entry["runs"], l1_orders, max_orders, strict=True):
            rows.append(
                [
                    entry["case"],
                    entry["scheme"],
                    r["cells"],
                    r["steps"],
                    r["wall_s"],
                    f"{r['l1_error']:.3e}",
                    "-" if p1 is None else f"{p1:.2f}",
                    f"{r['max_error']:.3e}",
                    "-" if pm is None else f"{pm:.2f}",
                    f"{r['mass_a_relative_drift']:.1e}",
                    _percent(r["contention"]["other_cpu_share"]),
                ]
            )
    head = [
        "case",
        "scheme",
        "cells",
        "steps",
        "wall s",
        "L1 error",
        "order L1",
        "max error",
        "order max",
        "mass drift",
        "others' CPU",
    ]
    return table(head, rows, align="llrrrrrrrrr")


def main() -> None:
    quiet = wait_for_quiet()
    compile_s = warm_up()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    echo(f"warm-up {compile_s:.1f} s")
    results = []
    for case, build in CASES.items():
        for scheme in bx.SCHEMES:
            rows = []
            for cells in GRIDS[case]:
                flow, kwargs, exact_and_window = build(cells)
                row = run_one(flow, scheme, cells, kwargs, exact_and_window)
                rows.append(row)
                echo(
                    f"{case:9s} {scheme:14s} cells {cells:4d}  {row['steps']:5d} steps  "
                    f"{row['wall_s']:7.2f} s  L1 {row['l1_error']:.3e}  "
                    f"max {row['max_error']:.3e}  drift {row['mass_a_relative_drift']:.1e}"
                )
            l1_orders = observed_orders(rows, "l1_error")
            max_orders = observed_orders(rows, "max_error")
            for r, p1, pm in zip(rows, l1_orders, max_orders, strict=True):
                r["order_l1"], r["order_max"] = p1, pm
            flow, kwargs, exact_and_window = build(DT_STUDY_CELLS[case])
            study = dt_study(flow, scheme, DT_STUDY_CELLS[case], kwargs, exact_and_window)
            results.append({"case": case, "scheme": scheme, "runs": rows, "dt_study": study})

    text = markdown(results, info)
    echo()
    echo(text)
    study_rows = [
        [
            entry["case"],
            entry["scheme"],
            r["cells"],
            r["safety"],
            r["steps"],
            f"{r['l1_error']:.3e}",
            f"{r['mean_dt_relative_to_first']:.3f}",
            f"{r['l1_relative_to_first']:.3f}",
        ]
        for entry in results
        for r in entry["dt_study"]
    ]
    study_text = table(
        ["case", "scheme", "cells", "safety", "steps", "L1 error", "mean dt ratio", "L1 ratio"],
        study_rows,
        align="llrrrrrr",
    )
    echo()
    echo("Time-step study (one grid per case, dt = safety x stable limit):")
    echo()
    echo(study_text)
    md = (
        "<!-- written by benchmarks/work_precision.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        "One revolution; `sbr-3d`: solid-body rotation of a Gaussian with D = "
        f"{DIFFUSION:g} m2/s (exact: the Gaussian spread by 2DT); `swirl-2d`: LeVeque's swirl, "
        "k1 = 0 (exact: the initial state). Orders from successive grids, "
        "log(e1/e2)/log(h1/h2); mass drift = `mass_a_relative_drift`; others' CPU = CPU time "
        "other processes used during the timed run, as a share of the machine (high values "
        "mean a pessimistic wall time).\n\n" + text + "\n\n"
        "Time-step study: the same grid run at several fractions (`safety`) of the stable dt; "
        "ratios are to the run at safety 0.9 (mean dt = period / steps). An L1 error falling "
        "in proportion to dt means the time error dominates at that grid.\n\n" + study_text + "\n"
    )
    write_atomic(RESULTS / "work_precision.md", md)
    plot(results, RESULTS / "work_precision.png")
    payload = {
        "benchmark": "work_precision",
        "machine": info,
        "settings": {
            "warm_up_s": compile_s,
            "grids": GRIDS,
            "sbr-3d": {
                "flow": f"solid_body_rotation(ndim=3, radius={RADIUS}, cells=32, rpm={RPM_SBR})",
                "diffusivity_m2_s": DIFFUSION,
                "centre_m": SBR_CENTRE,
                "sigma_m": math.sqrt(SBR_SIGMA2),
                "window": "r < 0.8 R and |z| < 0.6 R",
                "exact": "Gaussian at its start, variance + 2 D T",
            },
            "swirl-2d": {
                "flow": "swirl(ndim=2, cells=<the ADE cells>, n_phases=72, rpm=60.0, size=1.0)",
                "k1": 0.0,
                "centre_m": SWIRL_CENTRE,
                "sigma_m": math.sqrt(SWIRL_SIGMA2),
                "window": "whole box",
                "exact": "initial state",
            },
            "l1_error": "sum |c - exact| x cell volume over the window",
            "dt_study": {"cells": DT_STUDY_CELLS, "safety": SAFETIES},
            "wall_s": f"wall time of the mix call after warm-up, fastest of {REPEATS} runs "
            f"(fewer if their total would exceed {BUDGET_S} s; up to {MAX_REPEATS} while "
            "other work on the machine slowed every run so far)",
        },
        "results": results,
        "load_average_at_end": load_average(),
        "cpu_pressure_at_end": cpu_pressure(),
    }
    path = write_json("work_precision", payload)
    echo()
    echo(f"wrote {path.relative_to(path.parents[2])}, work_precision.md, work_precision.png")


if __name__ == "__main__":
    main()
