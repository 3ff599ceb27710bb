"""The Tote blender through the flow solver: periodicity, validity, cost.

Part 1 (run): the default Tote (DESIGN §7) at 40 % and 60 % fill, 10 rpm, turned three
revolutions at a 12.5 mm cell with the default stiffness scaling; reports the
periodicity of eq. (30) between revolutions 2 and 3 (lab-frame velocities as the
paper's fixed mesh saw them, and the stricter vessel-frame figure), the deepest
particle escape over every step, whether the dataset validates, the mixing that
``bx.mix`` computes on it over one revolution, and the wall time.

Part 2 (cost at the paper's scale): the 40 % Tote at a 7.5 mm cell, two revolutions.
By default it times 60 steps of the turning bed, unscaled and with the default scaling,
and extrapolates the wall time of the whole run (settling plus two revolutions at the
measured step time; labelled as an extrapolation). ``--full`` runs the scaled case to
the end instead.

Run: ``python benchmarks/flow_tote.py [--full]`` (about 15 minutes on 2 cores; --full
adds about half an hour). Writes ``benchmarks/results/flow_tote.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

from _common import (  # noqa: E402
    RESULTS,
    echo,
    machine,
    machine_line,
    table,
    wait_for_quiet,
    write_atomic,
    write_json,
)

import blendxr as bx  # noqa: E402
from blendxr.flow.solver import FlowSimulation, _flow_from  # noqa: E402

DEFAULT_SCALING = bx.load_scene("tote-40-top-bottom")["solver"]["stiffness_scaling"]
PERIODICITY_CELL = 0.0125
PAPER_CELL = 0.0075
TIMED_STEPS = 60


def tote(fraction, cell, scaling, revolutions, phases=12):
    return {
        "name": f"tote-{round(fraction * 100)}",
        "vessel": {"kind": "tote", "ndim": 3},
        "operation": {"rpm": 10.0},
        "fill": {"fraction": fraction},
        "flow": {"cell": cell, "phases": phases},
        "solver": {
            "stiffness_scaling": scaling,
            "settle_time": 0.5,
            "revolutions": revolutions,
            "checkpoint_every": 1e9,
        },
    }


def periodicity_case(fraction) -> dict:
    sim = FlowSimulation(tote(fraction, PERIODICITY_CELL, DEFAULT_SCALING, 3))
    escape = [-math.inf]

    def check(s):
        escape[0] = max(escape[0], float(s.vessel.sdf(s.particles.x).max()))

    started = time.perf_counter()
    sim.run(progress=False, callback=check)
    wall = time.perf_counter() - started
    flow = bx.validate(_flow_from(sim, wall, "time"))
    mixed = bx.mix(flow, revolutions=1.0, cells=50, progress=False)
    a = flow.attrs
    return {
        "fill": fraction,
        "cell_m": PERIODICITY_CELL,
        "stiffness_scaling": DEFAULT_SCALING,
        "particles": a["particles"],
        "steps": a["steps"],
        "wall_s": wall,
        "particle_updates_per_s": a["particle_updates_per_s"],
        "deepest_escape_m": escape[0],
        "valid": True,
        "periodicity_lab": {c: a[f"periodicity_{c}"] for c in ("vx", "vy", "vz")},
        "periodicity_lab_norm": {c: a[f"periodicity_{c}_norm"] for c in ("vx", "vy", "vz")},
        "periodicity_vessel_frame": {
            c: a[f"periodicity_vessel_frame_{c}"] for c in ("vx", "vy", "vz")
        },
        "fill_clipped_max": a["fill_clipped_max"],
        "mix_rsd_start_end": [float(mixed["rsd"][0]), float(mixed["rsd"][-1])],
        "mix_mass_drift": float(mixed.attrs["mass_a_relative_drift"]),
    }


def cost_case(scaling, full=False) -> dict:
    scene = tote(0.4, PAPER_CELL, scaling, 2, phases=36)
    sim = FlowSimulation(scene)
    total_time = sim.end_time()
    if full:
        started = time.perf_counter()
        sim.run(progress=False)
        wall = time.perf_counter() - started
        return {
            "stiffness_scaling": scaling,
            "particles": sim.particles.count,
            "steps": sim.steps,
            "wall_s": wall,
            "extrapolated": False,
        }
    sim.run(until=sim.settings.settle_time, max_steps=20, progress=False)  # warm, seated
    dt = sim.stable_dt()
    started = time.perf_counter()
    for _ in range(TIMED_STEPS):
        sim.step(dt)
    per_step = (time.perf_counter() - started) / TIMED_STEPS
    steps = math.ceil(total_time / dt)
    return {
        "stiffness_scaling": scaling,
        "particles": sim.particles.count,
        "dt_s": dt,
        "steps": steps,
        "ms_per_step": per_step * 1e3,
        "particle_updates_per_s": sim.particles.count / per_step,
        "wall_s": per_step * steps,
        "extrapolated": True,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--full", action="store_true", help="run the 7.5 mm case to the end")
    args = parser.parse_args()
    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    FlowSimulation(tote(0.4, 0.03, 100.0, 2)).run(max_steps=20, progress=False)  # compile
    periodic = []
    for fraction in (0.4, 0.6):
        r = periodicity_case(fraction)
        periodic.append(r)
        lab = r["periodicity_lab"]
        echo(f"fill {fraction}: {r['particles']} particles, {r['wall_s']:.0f} s, {lab}")
    costs = [cost_case(1.0), cost_case(DEFAULT_SCALING, full=args.full)]
    for r in costs:
        echo(f"7.5 mm, E/{r['stiffness_scaling']:g}: {r['wall_s'] / 60:.1f} min ({r})")

    rows = [
        [
            f"{r['fill']:.0%}",
            r["particles"],
            f"{r['wall_s']:.0f}",
            " / ".join(f"{r['periodicity_lab'][c]:.1%}" for c in ("vx", "vy", "vz")),
            " / ".join(f"{r['periodicity_vessel_frame'][c]:.1%}" for c in ("vx", "vy", "vz")),
            f"{r['deepest_escape_m']:.1e}",
            f"{r['mix_rsd_start_end'][0]:.3f} -> {r['mix_rsd_start_end'][1]:.3f}",
        ]
        for r in periodic
    ]
    text1 = table(
        ["fill", "particles", "wall s", "eq. 30 lab x/y/z", "eq. 30 vessel frame x/y/z",
         "max sdf m", "RSD, 1 rev"],
        rows,
    )  # fmt: skip
    text2 = table(
        ["E scaling", "particles", "steps", "ms/step", "wall min", "how"],
        [
            [
                f"1/{r['stiffness_scaling']:g}",
                r["particles"],
                r["steps"],
                f"{r.get('ms_per_step', r['wall_s'] / r['steps'] * 1e3):.1f}",
                f"{r['wall_s'] / 60:.1f}",
                "extrapolated from timed steps" if r["extrapolated"] else "run",
            ]
            for r in costs
        ],
    )
    echo()
    echo(text1)
    echo()
    echo(text2)
    md = (
        "<!-- written by benchmarks/flow_tote.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        f"Periodicity (eq. 30) between revolutions 2 and 3, Tote at 10 rpm, "
        f"{PERIODICITY_CELL * 1000:g} mm cell, E/{DEFAULT_SCALING:g}, 12 phase bins; max sdf "
        "is the deepest particle escape over every step (negative: none left the vessel); "
        "RSD from `bx.mix` on the flow over one revolution (top-bottom loading, 50 cells).\n\n"
        + text1
        + f"\n\nCost of the paper's case: 40 % fill, {PAPER_CELL * 1000:g} mm cell, settling "
        "plus two revolutions.\n\n" + text2 + "\n"
    )
    write_atomic(RESULTS / "flow_tote.md", md)
    write_json("flow_tote", {"machine": info, "periodicity": periodic, "cost": costs})


if __name__ == "__main__":
    main()
