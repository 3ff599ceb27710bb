"""Collapse of a granular column onto a horizontal floor: a canonical benchmark with
published measurements, at three cells.

A 2-D column of width L0 = 0.1 m and height H0 = a L0 stands against the left wall of a
box and is released at t = 0 (gravity switched on at once, ``solver.settle_time = 0``,
the sudden removal of a gate); it spreads along the floor until it stops. Measured, for
plane flows in a channel (quasi-2-D, many materials: sand, glass beads, rice, sugar):
the runout (L∞ − L0) / L0 ≈ 1.2 a for a ≲ 1.8 and the final height H∞ = H0 for
a ≲ 1.15, the top of the column staying in place (Lube, Huppert, Sparks and Freundt 2005,
Phys. Rev. E 72, 041301). The constant of the runout depends on the material by some
tens of percent in other channels (Balmforth and Kerswell 2005, J. Fluid Mech. 538,
399: (l∞ − L)/L ∝ a^(0.9 ± 0.1) in wide channels).

The solver runs with the scene defaults (Table 1's glass beads with c = 0, E unscaled,
the floor's and the back wall's Coulomb friction ``material.wall_friction``, the density
projection every 10 steps, ψ = 0), for 1 s, by which time every case has stopped (the
largest speed at the end is reported). Variants: ``mu_i``, the μ(I) friction
(``material.friction_angle_limit_deg = 37.7``, 1 mm grains, as flow_work_precision.py's
runs); ``no_projection``, the flow before the projection and ψ = 0 were the defaults
(no projection, Table 1's ψ = 0.1°); ``rough_floor``, the floor's friction coefficient
tan 27.1° (as rough as the bed's internal friction) instead of Table 1's 0.324;
``sticky_floor``, friction 1, on which the bed cannot slide (the no-slip base of
continuum studies of the collapse), and ``mu_i_sticky_floor``, that floor with μ(I);
``gate``, the experiment's start: the column settled under gravity behind a gate (the
right wall of a box as wide as the column) and released at rest into the long box;
``no_lost_contact`` and ``poisson_0.3`` (ν = 0.3 instead of Table 1's 0.065), which
test two suspected causes of the a = 1 column's long runout. Cells
5, 2.5 and 1.25 mm (20, 40 and 80 cells across the column). The front is the 99.9th
percentile of the particles' x (a few particles thrown ahead of the deposit do not
count); the height the largest y at the back wall.

Run: ``python benchmarks/flow_column.py [--case NAME ...]`` (2-D beds run on one
thread, so two invocations with different cases share 2 cores). Writes
``benchmarks/results/flow_column.{json,md,png}``; ``--report`` rewrites them from the
JSON.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import copy  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, machine_line, run_cases, table, three_cell_order  # noqa: E402

import blendxr as bx  # noqa: E402
from blendxr.plot import save_figure  # noqa: E402

NAME = "flow_column"
WIDTH = 0.1  # L0 [m]
DURATION = 1.0  # [s]
#: Lube et al. (2005): (L - L0) / L0 = RUNOUT_SLOPE a for a below RUNOUT_RANGE
RUNOUT_SLOPE = 1.2
RUNOUT_RANGE = 1.8
HEIGHT_RANGE = 1.15  # H = H0 below this aspect ratio
ASPECTS = (0.5, 1.0)
CELLS = (0.005, 0.0025, 0.00125)
VARIANTS = {
    "default": {},
    "mu_i": {"material": {"friction_angle_limit_deg": 37.7, "particle_diameter": 0.001}},
    "no_projection": {
        "material": {"dilation_angle_deg": 0.1},
        "solver": {"density_projection": 0},
    },
    # a floor as rough as the bed is frictional (tan 27.1 deg), as a base of glued grains
    "rough_floor": {"material": {"wall_friction": 0.512}},
    # a floor the bed cannot slide on (Coulomb friction 1, twice the bed's tan 27.1 deg):
    # the no-slip base of continuum collapse studies
    "sticky_floor": {"material": {"wall_friction": 1.0}},
    "mu_i_sticky_floor": {
        "material": {
            "wall_friction": 1.0,
            "friction_angle_limit_deg": 37.7,
            "particle_diameter": 0.001,
        },
    },
    # the experiment's start: the column settled under gravity behind a gate, then the
    # gate removed (the other variants switch gravity on at once on a stress-free column)
    "gate": {},
    "no_lost_contact": {"solver": {"lost_contact": False}},
    # a stiffer lateral response than Table 1's loose bed (nu = 0.065): K0 = nu / (1 - nu)
    # = 0.43 above the active Rankine ratio 0.37 instead of 0.07 below it
    "poisson_0.3": {"material": {"poisson_ratio": 0.3}},
}
#: variants that start from a column settled behind a gate, and the settling time [s]
GATED = {"gate"}
GATE_SETTLE = 0.3
#: the thickness at which the deposit's front is read on every grid: one cell of the
#: coarsest (a layer thinner than a cell is below that grid's resolution)
RESOLVED_THICKNESS = max(CELLS)
CASES = {
    f"{variant}_a{a:g}_{cell * 1000:g}mm": (variant, a, cell)
    for variant in VARIANTS
    for a in ASPECTS
    for cell in CELLS
}


def scene(a: float, cell: float, variant: str) -> dict:
    """The column of aspect ratio ``a`` against the left wall of a box long enough for
    twice the published runout."""
    height = a * WIDTH
    length = WIDTH * (1.0 + 2.0 * max(RUNOUT_SLOPE * a, 1.0)) + 0.1
    box = [length, height + 0.03]
    out = {
        "name": f"column-a{a:g}",
        "vessel": {"kind": "box", "ndim": 2, "size": box, "center": [b / 2 for b in box]},
        "operation": {"rpm": 0.0, "duration": DURATION},
        "material": {"cohesion": 0.0},
        "fill": {"box": [[0.0, WIDTH], [0.0, height]]},
        "flow": {"cell": cell},
        "solver": {"settle_time": 0.0},
    }
    for section, values in VARIANTS[variant].items():
        out.setdefault(section, {}).update(values)
    return out


def deposit_profile(x: np.ndarray, bin_width: float) -> tuple[np.ndarray, np.ndarray]:
    """(bin centres, largest particle height per bin) of the deposit, empty bins left out."""
    edges = np.arange(0.0, x[:, 0].max() + bin_width, bin_width)
    index = np.digitize(x[:, 0], edges) - 1
    tops = np.full(len(edges), -np.inf)
    np.maximum.at(tops, index, x[:, 1])
    keep = np.isfinite(tops)
    return (edges + 0.5 * bin_width)[keep], tops[keep]


def gated_release(spec: dict) -> tuple[np.ndarray, np.ndarray, int]:
    """Settle the column in a box as wide as itself (the gate its right wall) with
    gravity ramped over ``GATE_SETTLE``, then release it into the long box at rest.

    Returns the final positions, velocities and the steps of the release."""
    from blendxr.flow.solver import FlowSimulation

    gate = copy.deepcopy(spec)
    box = [WIDTH, spec["vessel"]["size"][1]]
    gate["vessel"].update(size=box, center=[b / 2 for b in box])
    gate["solver"]["settle_time"] = GATE_SETTLE
    behind = FlowSimulation(gate)
    behind.run(until=GATE_SETTLE, progress=False)
    released = FlowSimulation(spec)
    state = behind.particles.arrays()
    if state["x"].shape != released.particles.x.shape:
        raise RuntimeError("the gated and the released column were seeded differently")
    state["v"] = np.zeros_like(state["v"])
    state["C"] = np.zeros_like(state["C"])
    released.particles.load(state)
    released.run(progress=False)
    return released.particles.x, released.particles.v, released.steps


def run_case(name: str) -> dict:
    variant, a, cell = CASES[name]
    started = time.perf_counter()
    spec = scene(a, cell, variant)
    if variant in GATED:
        x, v, steps = gated_release(spec)
    else:
        flow, particles = bx.solve_flow(spec, particles=True, progress=False)
        x, v = particles["position"].values, particles["velocity"].values
        steps = int(flow.attrs["steps"])
    wall = time.perf_counter() - started
    front = float(np.quantile(x[:, 0], 0.999))
    back = x[:, 0] < 0.1 * WIDTH
    centres, tops = deposit_profile(x, cell)
    return {
        "case": name,
        "variant": variant,
        "aspect": a,
        "cell_m": cell,
        "runout": (front - WIDTH) / WIDTH,
        "runout_max": (float(x[:, 0].max()) - WIDTH) / WIDTH,
        "height": float(x[back, 1].max()) / (a * WIDTH),
        "speed_max_end_m_s": float(np.abs(v).max()),
        "particles": int(len(x)),
        "steps": steps,
        "wall_s": wall,
        "profile_x_m": centres.tolist(),
        "profile_top_m": tops.tolist(),
    }


def resolved_runout(r: dict) -> float:
    """(front - L0) / L0 with the front the last place where the deposit is at least
    RESOLVED_THICKNESS thick (the particle tops plus half a particle spacing)."""
    x = np.asarray(r["profile_x_m"])
    top = np.asarray(r["profile_top_m"]) + 0.25 * r["cell_m"]
    return float((x[top >= RESOLVED_THICKNESS].max() - WIDTH) / WIDTH)


def published(a: float) -> tuple[float | None, float | None]:
    """Lube et al.'s runout and height at aspect ratio ``a`` (None outside their fits)."""
    runout = RUNOUT_SLOPE * a if a <= RUNOUT_RANGE else None
    height = 1.0 if a <= HEIGHT_RANGE else None
    return runout, height


def summary(name: str, r: dict) -> str:
    want, _ = published(r["aspect"])
    return (
        f"{name}: runout {r['runout']:.2f} (published {want}), height {r['height']:.3f}, "
        f"{r['wall_s']:.0f} s"
    )


def report(results: dict, info: dict) -> str:
    rows, trend = [], []
    for name, (variant, a, cell) in CASES.items():
        if name not in results:
            continue
        r = results[name]
        runout, height = published(a)
        resolved = resolved_runout(r)
        rows.append([
            name, variant, f"{a:g}", f"{cell * 1000:g}", f"{r['runout']:.2f}",
            f"{resolved:.2f}", f"{runout:.2f}", f"{resolved / runout - 1:+.0%}",
            f"{r['height']:.3f}",
            f"{height:g}", f"{r['speed_max_end_m_s'] * 1000:.2f}", r["particles"],
            f"{r['wall_s']:.0f}",
        ])  # fmt: skip
    for variant in VARIANTS:
        for a in ASPECTS:
            names = [f"{variant}_a{a:g}_{c * 1000:g}mm" for c in CELLS]
            if all(n in results for n in names):
                runs = [results[n]["runout"] for n in names]
                resolved = [resolved_runout(results[n]) for n in names]
                trend.append([variant, f"{a:g}", " → ".join(f"{v:.2f}" for v in runs),
                              three_cell_order(runs), " → ".join(f"{v:.2f}" for v in resolved),
                              three_cell_order(resolved), f"{published(a)[0]:.2f}"])  # fmt: skip
    return (
        f"<!-- written by benchmarks/{NAME}.py -->\n"
        "# Collapse of a granular column (2-D, against a wall)\n\n"
        f"Machine: {machine_line(info)}.\n\n"
        "Published: (L∞ − L0)/L0 ≈ 1.2 a for a ≲ 1.8 and H∞ = H0 for a ≲ 1.15 (Lube et "
        "al. 2005, Phys. Rev. E 72, 041301, quasi-2-D channel, several materials). "
        "runout (particles): (front − L0)/L0, the front the 99.9th percentile of the "
        "particles' x, which follows a thinning tail as the cell shrinks; runout "
        f"(resolved): the front where the deposit is {RESOLVED_THICKNESS * 1000:g} mm "
        "thick, one cell of the coarsest grid, read alike on every grid (the published "
        "front is where the grains run out, so this one falls short of it by the tail); "
        "height: the deposit's largest height at the back wall over H0; speed: the "
        "largest particle speed at t = 1 s (the deposit has stopped when it is small). "
        "default: the scene defaults (rate-independent Mohr–Coulomb, Table 1 with c = 0, "
        "the density projection every 10 steps, ψ = 0); mu_i: the same with μ(I), μ2 = "
        "tan 37.7°, 1 mm grains; no_projection: no projection and Table 1's ψ = 0.1°, "
        "the defaults before; rough_floor: wall friction tan 27.1° = 0.512; sticky_floor: "
        "wall friction 1 (the bed cannot slide on the floor); mu_i_sticky_floor: both; "
        "gate: the experiment's start, the column settled behind a gate "
        f"({GATE_SETTLE:g} s, gravity ramped) and released at rest (the others switch "
        "gravity on at once on a stress-free column); no_lost_contact: "
        "`solver.lost_contact = false`; poisson_0.3: ν = 0.3 instead of Table 1's 0.065.\n\n"
        + table(
            [
                "case",
                "variant",
                "a",
                "cell mm",
                "runout (particles)",
                "runout (resolved)",
                "published",
                "error (resolved)",
                "height",
                "published",
                "speed mm/s",
                "particles",
                "wall s",
            ],
            rows,
        )  # fmt: skip
        + "\n\n## The runout against the cell (5 → 2.5 → 1.25 mm)\n\n"
        + table(
            [
                "variant",
                "a",
                "runout (particles)",
                "observed order",
                "runout (resolved)",
                "observed order",
                "published",
            ],
            trend,
        )  # fmt: skip
        + f"\n\n![deposits]({NAME}.png)\n"
    )


def plot(results: dict) -> None:
    """One panel per aspect ratio: every variant's deposit at its finest cell, and the
    default's at every cell (dashed)."""
    fig, axes = plt.subplots(1, len(ASPECTS), figsize=(12, 4.2), squeeze=False)
    for col, a in enumerate(ASPECTS):
        ax = axes[0, col]
        ax.plot([0, WIDTH, WIDTH], [a * WIDTH] * 2 + [0], "k:", lw=1, label="column")
        runout, _ = published(a)
        ax.axvline(WIDTH * (1 + runout), color="k", lw=1, label="published front")
        for cell in CELLS[:-1]:
            r = results.get(f"default_a{a:g}_{cell * 1000:g}mm")
            if r:
                ax.plot(r["profile_x_m"], r["profile_top_m"], "--", lw=0.8, color="0.5",
                        label=f"default, {cell * 1000:g} mm")  # fmt: skip
        for variant in VARIANTS:
            runs = [(c, results.get(f"{variant}_a{a:g}_{c * 1000:g}mm")) for c in CELLS]
            runs = [(c, r) for c, r in runs if r]
            if runs:
                cell, r = runs[-1]
                ax.plot(r["profile_x_m"], r["profile_top_m"], lw=1.2,
                        label=f"{variant}, {cell * 1000:g} mm")  # fmt: skip
        ax.set_title(f"a = {a:g}", fontsize=10)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("deposit top (m)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, RESULTS / f"{NAME}.png")


def main() -> None:
    payload = run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, summary)
    plot(payload["cases"])


if __name__ == "__main__":
    sys.exit(main())
