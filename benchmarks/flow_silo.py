"""Discharge of a flat-bottomed 2-D silo through a slot: a canonical benchmark with
published laws, at three cells.

A silo 120 mm wide, filled 180 mm deep, stands on a 10 mm floor with a centred slot of
width D and empties into a bin below (``vessel.kind = "silo"``); gravity is switched on
at t = 0 and the slot is open from the start. Measured over a century for grains through
orifices in flat bottoms (Hagen 1852; Beverloo, Leniger and van de Velde 1961, Chem.
Eng. Sci. 15, 260; in two dimensions Mankoc et al. 2007, Granular Matter 9, 407): the
mass flow rate does not depend on the height of the material above the orifice once
that exceeds about the silo's width, and in 2-D it follows W = C ρ_b √g (D − k d)^(3/2)
per unit thickness, with C of order one and k d an "empty annulus" of one to three
grain diameters d. A continuum has no grain size, so its k d can only be a multiple of
the cell h, which must vanish as the cell shrinks.

Read here: W, the slope of the mass that has passed below the floor against time,
fitted over t = 0.2 s to the end (the start left out is the jet's first fall to the
fit's level); the head's effect, W over the second half of that window against the first
(the bed above the floor falls meanwhile); the 3/2 law, a straight line
W^(2/3) = (C ρ_b √g)^(2/3) (D − k h) through the three slots at each cell, its C, k and
largest relative misfit of W; and how W at each slot moves as the cell halves.

The solver runs with the scene defaults (rate-independent Mohr–Coulomb, Table 1's glass
beads with c = 0, E unscaled, wall friction 0.324 on every wall and in the slot, the
density projection every 10 steps, ψ = 0); ``mu_i`` adds the μ(I) friction (1 mm
grains, μ2 = tan 37.7°). Slots 20, 30 and 40 mm (the silo at least three slots wide);
cells 5, 2.5 and 1.25 mm. ρ_b is Table 1's bulk density, 1500 kg/m³.

Run: ``python benchmarks/flow_silo.py [--case NAME ...]`` (2-D beds run on one thread,
so two invocations with different cases share 2 cores). Writes
``benchmarks/results/flow_silo.{json,md,png}``; ``--report`` rewrites them from the JSON.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import sys  # noqa: E402
import time  # noqa: E402

import matplotlib  # noqa: E402

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    RESULTS,
    machine_line,
    richardson_limit,
    run_cases,
    table,
    three_cell_order,
)

from blendxr.flow.solver import FlowSimulation  # noqa: E402
from blendxr.plot import save_figure  # noqa: E402

NAME = "flow_silo"
SILO_WIDTH = 0.12  # [m]
FILL_DEPTH = 0.18  # [m] above the floor
BIN_HEIGHT = 0.2  # [m] the floor's top above the bin's bottom
FLOOR = 0.01  # [m] thickness of the floor, two cells of the coarsest grid
HEADROOM = 0.03  # [m] above the fill
DURATION = 0.6  # [s]
FIT_FROM = 0.2  # [s]
RECORD_EVERY = 20  # steps
GRAVITY = 9.81
BULK_DENSITY = 1500.0  # Table 1 [kg/m3]
#: the 2-D law's exponent (Beverloo et al. 1961 for circles: 5/2; Mankoc et al. 2007: 3/2
#: per unit thickness in 2-D)
EXPONENT = 1.5
SLOTS = (0.02, 0.03, 0.04)
CELLS = (0.005, 0.0025, 0.00125)
VARIANTS = {
    "default": {},
    "mu_i": {"material": {"friction_angle_limit_deg": 37.7, "particle_diameter": 0.001}},
}
CASES = {
    f"{variant}_D{slot * 1000:g}_{cell * 1000:g}mm": (variant, slot, cell)
    for variant in VARIANTS
    for slot in SLOTS
    for cell in CELLS
}


def scene(slot: float, cell: float, variant: str) -> dict:
    """The silo with a slot ``slot`` wide, over its bin, filled from the floor up."""
    height = BIN_HEIGHT + FILL_DEPTH + HEADROOM
    out = {
        "name": f"silo-D{slot * 1000:g}mm",
        "vessel": {
            "kind": "silo",
            "ndim": 2,
            "size": [SILO_WIDTH, height],
            "center": [SILO_WIDTH / 2, height / 2],
            "orifice": slot,
            "floor_height": BIN_HEIGHT,
            "floor_thickness": FLOOR,
        },
        "operation": {"rpm": 0.0, "duration": DURATION},
        "material": {"cohesion": 0.0},
        "fill": {"box": [[0.0, SILO_WIDTH], [BIN_HEIGHT, BIN_HEIGHT + FILL_DEPTH]]},
        "flow": {"cell": cell},
        "solver": {"settle_time": 0.0},
    }
    for section, values in VARIANTS[variant].items():
        out.setdefault(section, {}).update(values)
    return out


def discharge_rate(t: np.ndarray, mass: np.ndarray, start: float, stop: float) -> float:
    """Least-squares slope of the discharged mass over [start, stop] (kg m-1 s-1)."""
    keep = (t >= start) & (t <= stop)
    return float(np.polyfit(t[keep], mass[keep], 1)[0])


def run_case(name: str) -> dict:
    variant, slot, cell = CASES[name]
    started = time.perf_counter()
    sim = FlowSimulation(scene(slot, cell, variant))
    mass = sim.particles.mass
    below = BIN_HEIGHT - FLOOR  # the floor's bottom face
    times, passed = [], []

    def record(s: FlowSimulation) -> None:
        if s.steps % RECORD_EVERY == 0:
            times.append(s.t)
            passed.append(float(mass[s.particles.x[:, 1] < below].sum()))

    sim.run(progress=False, callback=record)
    wall = time.perf_counter() - started
    t, m = np.array(times), np.array(passed)
    middle = 0.5 * (FIT_FROM + DURATION)
    rate = discharge_rate(t, m, FIT_FROM, DURATION)
    return {
        "case": name,
        "variant": variant,
        "slot_m": slot,
        "cell_m": cell,
        "rate_kg_m_s": rate,
        "rate_first_half": discharge_rate(t, m, FIT_FROM, middle),
        "rate_second_half": discharge_rate(t, m, middle, DURATION),
        "coefficient": rate / (BULK_DENSITY * np.sqrt(GRAVITY) * slot**EXPONENT),
        "discharged_share": float(m[-1] / mass.sum()),
        "particles": int(sim.particles.count),
        "steps": int(sim.steps),
        "wall_s": wall,
        "t_s": t.tolist(),
        "discharged_kg_m": m.tolist(),
    }


def summary(name: str, r: dict) -> str:
    return (
        f"{name}: W {r['rate_kg_m_s']:.2f} kg/m/s, W/(ρ√g D^1.5) {r['coefficient']:.3f}, "
        f"head {r['rate_second_half'] / r['rate_first_half'] - 1:+.1%}, {r['wall_s']:.0f} s"
    )


def beverloo_fit(slots: list[float], rates: list[float], cell: float) -> dict:
    """W^(2/3) = (C ρ_b √g)^(2/3) (D − k h), by least squares over the slots."""
    w23 = np.asarray(rates) ** (1.0 / EXPONENT)
    slope, intercept = np.polyfit(slots, w23, 1)
    c = slope**EXPONENT / (BULK_DENSITY * np.sqrt(GRAVITY))
    k_cells = -intercept / slope / cell
    fitted = (slope * np.asarray(slots) + intercept) ** EXPONENT
    misfit = float(np.max(np.abs(fitted / np.asarray(rates) - 1.0)))
    return {"C": float(c), "k_cells": float(k_cells), "misfit": misfit}


def report(results: dict, info: dict) -> str:
    rows, fits, trends = [], [], []
    for name, (variant, slot, cell) in CASES.items():
        r = results.get(name)
        if r is None:
            continue
        rows.append([
            name, variant, f"{slot * 1000:g}", f"{cell * 1000:g}", f"{r['rate_kg_m_s']:.2f}",
            f"{r['coefficient']:.3f}",
            f"{r['rate_second_half'] / r['rate_first_half'] - 1:+.1%}",
            f"{r['discharged_share']:.0%}", r["particles"], f"{r['wall_s']:.0f}",
        ])  # fmt: skip
    for variant in VARIANTS:
        for cell in CELLS:
            names = [f"{variant}_D{s * 1000:g}_{cell * 1000:g}mm" for s in SLOTS]
            if all(n in results for n in names):
                fit = beverloo_fit(list(SLOTS), [results[n]["rate_kg_m_s"] for n in names], cell)
                fits.append([variant, f"{cell * 1000:g}", f"{fit['C']:.3f}",
                             f"{fit['k_cells']:.2f}", f"{fit['k_cells'] * cell * 1000:.1f}",
                             f"{fit['misfit']:.1%}"])  # fmt: skip
        for slot in SLOTS:
            names = [f"{variant}_D{slot * 1000:g}_{c * 1000:g}mm" for c in CELLS]
            if all(n in results for n in names):
                w = [results[n]["rate_kg_m_s"] for n in names]
                limit = richardson_limit(w)
                if np.isfinite(limit):
                    coefficient = limit / (BULK_DENSITY * np.sqrt(GRAVITY) * slot**EXPONENT)
                    read = [f"{limit:.2f}", f"{coefficient:.3f}", f"{w[-1] / limit - 1:+.1%}"]
                else:
                    read = ["none (differences grow)", "", ""]
                trends.append([variant, f"{slot * 1000:g}", " → ".join(f"{v:.2f}" for v in w),
                               three_cell_order(w), *read])  # fmt: skip
    return (
        f"<!-- written by benchmarks/{NAME}.py -->\n"
        "# Discharge of a flat-bottomed silo through a slot (2-D)\n\n"
        f"Machine: {machine_line(info)}.\n\n"
        "Published: the flow rate does not depend on the head above the orifice (Hagen "
        "1852; Beverloo et al. 1961), and in 2-D W = C ρ_b √g (D − k d)^(3/2) per unit "
        "thickness (Mankoc et al. 2007), C of order one, k d one to three grain diameters. "
        f"Silo {SILO_WIDTH * 1000:g} mm wide, filled {FILL_DEPTH * 1000:g} mm deep, floor "
        f"{FLOOR * 1000:g} mm thick, slot D; W: slope of the mass passed below the floor "
        f"from t = {FIT_FROM:g} to {DURATION:g} s; C_D = W / (ρ_b √g D^(3/2)), ρ_b = "
        f"{BULK_DENSITY:g} kg/m³; head: W over the second half of that window against the "
        "first (the bed falls meanwhile); default: the scene defaults (rate-independent "
        "Mohr–Coulomb, Table 1 with c = 0, projection, ψ = 0); mu_i: with μ(I), 1 mm "
        "grains.\n\n"
        + table(
            [
                "case",
                "variant",
                "D mm",
                "cell mm",
                "W kg/m/s",
                "C_D",
                "head",
                "discharged",
                "particles",
                "wall s",
            ],
            rows,
        )  # fmt: skip
        + "\n\n## The 3/2 law at each cell: W^(2/3) linear in D\n\n"
        "C and k from a straight line through W^(2/3) of the three slots; misfit: the "
        "largest relative difference of W from the fitted law. A continuum's k d can "
        "only be a multiple of the cell.\n\n"
        + table(["variant", "cell mm", "C", "k (cells)", "k h mm", "misfit"], fits)
        + "\n\n## W against the cell (5 → 2.5 → 1.25 mm)\n\n"
        "limit: Richardson's extrapolation to h → 0 at the observed order; C_D of the "
        "limit; finest: the 1.25 mm value against the limit.\n\n"
        + table(
            ["variant", "D mm", "W kg/m/s", "observed order", "limit", "C_D (limit)", "finest"],
            trends,
        )  # fmt: skip
        + f"\n\n![discharge]({NAME}.png)\n"
    )


def plot(results: dict) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name, r in results.items():
        if not name.startswith("default_"):
            continue
        axes[0].plot(r["t_s"], r["discharged_kg_m"], lw=1,
                     label=f"D {r['slot_m'] * 1000:g} mm, {r['cell_m'] * 1000:g} mm")  # fmt: skip
    axes[0].axvline(FIT_FROM, color="0.6", ls="--", lw=0.8)
    axes[0].set_xlabel("t (s)")
    axes[0].set_ylabel("mass below the floor (kg/m)")
    axes[0].legend(fontsize=6, ncol=2)
    for variant, marker in zip(VARIANTS, "os", strict=False):
        for cell in CELLS:
            pts = [(results[n]["slot_m"], results[n]["rate_kg_m_s"])
                   for n in (f"{variant}_D{s * 1000:g}_{cell * 1000:g}mm" for s in SLOTS)
                   if n in results]  # fmt: skip
            if pts:
                d, w = np.array(pts).T
                axes[1].plot(d * 1000, w ** (1 / EXPONENT), marker + "-", ms=4,
                             label=f"{variant}, {cell * 1000:g} mm")  # fmt: skip
    axes[1].set_xlabel("slot D (mm)")
    axes[1].set_ylabel("W^(2/3)  (kg/m/s)^(2/3)")
    axes[1].set_title("the 2-D law: straight lines", fontsize=9)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, RESULTS / f"{NAME}.png")


def main() -> None:
    payload = run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, summary)
    plot(payload["cases"])


if __name__ == "__main__":
    sys.exit(main())
