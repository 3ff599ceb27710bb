"""What the Tote's change between revolutions depends on: E, particles per cell, scale.

The 40 % Tote at 10 rpm and a 12.5 mm cell (12 phase bins) is turned three
revolutions in each of these cases, and eq. (30) between revolutions 2 and 3 (the
issue's figure) is reported with each thing that might drive it changed in turn:

- ``default``: the benchmark flow_tote's case, E/10, 2 particles per cell and axis;
- ``unscaled``: E unscaled (a third as large a time step): is the change the stiffness
  scaling's?
- ``ppc1``, ``ppc3``, ``ppc4``: 1, 3 and 4 particles per cell and axis (1/8, 27/8 and 8
  times the particles): is it the particle discretisation (quadrature of the stress,
  the particles' arrangement)?

Each case also gives eq. (30) in the vessel frame (no rigid rotation in the velocities)
on the output cells and on blocks of 2³ and 3³ of them
(:func:`blendxr.flow.averaging.coarsen_fields`, fill-weighted): how much of the change
lies within a block, at the scale of the cell, and how much is a change of the flow at
larger scales; the noise part (eq. (30) between the averages of the even- and
odd-numbered particles, over sqrt 2); the bed's current volume over its seeded one.

Run: ``python benchmarks/flow_tote_periodicity.py [--case NAME ...]`` (all cases: about
an hour on 2 cores; ``--case`` runs some and merges them into the results file, so two
invocations can share the machine: the figures do not depend on the load, the wall
times do). Writes ``benchmarks/results/flow_tote_periodicity.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import time  # noqa: E402

import flow_tote  # noqa: E402
from _common import (  # noqa: E402
    machine_line,
    percent_xyz,
    run_cases,
    table,
)

from blendxr.flow.averaging import coarsen_fields, periodicity  # noqa: E402
from blendxr.flow.output import sampling_noise  # noqa: E402
from blendxr.flow.solver import FlowSimulation  # noqa: E402

NAME = "flow_tote_periodicity"
FILL = 0.4
CELL = 0.0125
PHASES = 12
REVOLUTIONS = 3
SCALES = (1, 2, 3)
COMPONENTS = ("vx", "vy", "vz")
#: case -> (stiffness scaling, particles per cell and axis)
CASES = {
    "default": (10.0, 2),
    "unscaled": (1.0, 2),
    "ppc1": (10.0, 1),
    "ppc3": (10.0, 3),
    "ppc4": (10.0, 4),
}


def scene(scaling: float, per_cell: int) -> dict:
    """flow_tote's Tote scene (its solver defaults) with ``per_cell`` particles per
    cell and axis."""
    out = flow_tote.tote(FILL, CELL, scaling, REVOLUTIONS, phases=PHASES)
    out["solver"]["particles_per_cell"] = per_cell
    return out


def _pick(change: dict, suffix: str = "") -> dict:
    return {c: change[f"{c}{suffix}"] for c in COMPONENTS}


def run_case(name: str) -> dict:
    scaling, per_cell = CASES[name]
    sim = FlowSimulation(scene(scaling, per_cell))
    started = time.perf_counter()
    sim.run(progress=False)
    wall = time.perf_counter() - started
    history = sim.periodicity_history()
    fill_b, vel_b, _ = sim.previous.fields()
    fill_a, vel_a, _ = sim.last.fields()
    vessel = {}
    for factor in SCALES:
        fb, vb = coarsen_fields(fill_b, vel_b, factor)
        fa, va = coarsen_fields(fill_a, vel_a, factor)
        coarse = periodicity(vb, va, fb, fa)
        vessel[str(factor)] = {"eq30": _pick(coarse), "norm": _pick(coarse, "_norm")}
    last = history[-1]
    return {
        "case": name,
        "stiffness_scaling": scaling,
        "particles_per_cell": per_cell,
        "particles": sim.particles.count * sim.copies,
        "particles_solved": sim.particles.count,
        "steps": sim.steps,
        "wall_s": wall,
        "threads": sim.grid.threads,
        "eq30_lab_2_3": dict(zip(COMPONENTS, last[1:], strict=True)),
        "eq30_lab_history": [list(row) for row in history],
        "eq30_vessel_by_block": vessel,
        "noise_part_vessel": _pick(sampling_noise(sim, vessel_frame=True)),
        "current_volume_over_seeded": sim.particles.volume_over_seeded,
    }


def report(results: dict, info: dict) -> str:
    order = [c for c in CASES if c in results]
    rows = []
    for name in order:
        r = results[name]
        by = r["eq30_vessel_by_block"]
        rows.append([
            name, f"1/{r['stiffness_scaling']:g}", r["particles_per_cell"],
            r["particles_solved"], f"{r['wall_s']:.0f}", r["threads"],
            percent_xyz(r["eq30_lab_2_3"]), *(percent_xyz(by[str(f)]["eq30"]) for f in SCALES),
            percent_xyz(r["noise_part_vessel"]), f"{r['current_volume_over_seeded']:.3f}",
        ])  # fmt: skip
    text = table(
        ["case", "E", "per cell", "solved", "wall s", "threads", "eq. 30 lab x/y/z",
         *(f"vessel frame, {f}³ cells x/y/z" for f in SCALES), "noise part x/y/z",
         "volume / seeded"],
        rows,
    )  # fmt: skip
    return (
        f"<!-- written by benchmarks/{NAME}.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        f"The 40 % Tote, 10 rpm, {CELL * 1000:g} mm cell, {PHASES} phase bins, settled and "
        f"turned {REVOLUTIONS} revolutions (`solver.lost_contact` and `solver.symmetry` at "
        "their defaults); eq. (30) between revolutions 2 and 3. Lab: the issue's figure "
        "(lab-frame velocities, as the paper's fixed mesh). Vessel frame: the stored "
        "velocities, without the rigid rotation, on the output cells (1³) and on blocks "
        "of 2³ and 3³ cells (fill-weighted, `coarsen_fields`): what is left when the "
        "change within a block is averaged out. Noise part: eq. (30) between the even- "
        "and odd-numbered particles' averages of revolution 3, over sqrt 2 (vessel frame, "
        "1³). Wall times are indicative only: cases were run two at a time on the 2 "
        "cores, oversubscribing them, and one was paused while another finished (column "
        "threads: beds under 20 000 solved particles run on one); the eq. (30) figures "
        "do not depend on the load.\n\n" + text + "\n"
    )


def _summary(name: str, r: dict) -> str:
    blocks = ", ".join(percent_xyz(r["eq30_vessel_by_block"][str(f)]["eq30"]) for f in SCALES)
    return (
        f"{name}: {r['particles_solved']} solved particles, {r['wall_s']:.0f} s, "
        f"lab {percent_xyz(r['eq30_lab_2_3'])}, vessel frame by block {blocks}"
    )


def main() -> None:
    run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, _summary)


if __name__ == "__main__":
    main()
