"""The Tote blender through the flow solver: periodicity, validity, cost.

Part 1 (periodicity at a coarse cell): the default Tote (DESIGN §7) at 40 % and 60 %
fill, 10 rpm, turned five revolutions at a 12.5 mm cell with the default stiffness
scaling; reports the periodicity of eq. (30) between every two successive revolutions
as the paper's Table 3 does (lab-frame velocities as the paper's fixed mesh saw them;
the issue's figure is revolutions 2 and 3), the stricter vessel-frame figure and the
part that the sampling noise of the phase averages accounts for (eq. (30) between the
averages of the even- and odd-numbered particles, over sqrt 2) for the last two, the
deepest particle escape over every step, whether the dataset validates, the mixing that
``bx.mix`` computes on the last revolution's flow over five revolutions, and the wall
time. What the flow's change between revolutions does to that answer: the same mixing
on the flow of the revolution before (the largest relative change of the RSD curve).
At 40 % the run is repeated from a start perturbed by 1e-7 m: how far two runs part is
the yardstick for the change between revolutions (a sensitive, chaotic flow would part
as much; a deterministic drift would not).

Part 2 (the paper's case): the 40 % Tote at a 7.5 mm cell with the default scaling and
36 phase bins, run for three revolutions: the wall time of settling plus two
revolutions (the paper's run) is taken when the second revolution ends, and the third
gives eq. (30) between revolutions 2 and 3 at this cell. Escapes are checked every 50
steps here (an exact distance for every particle every step would add a third to the
cost being measured). The unscaled case is extrapolated from the measured time per
turning step (a step costs the same whatever E; the unscaled run needs sqrt(scaling)
times as many) unless ``--unscaled`` runs it too.

``--no-lost-contact`` turns ``solver.lost_contact`` off (docs/flow.md).

Run: ``python benchmarks/flow_tote.py [--unscaled] [--skip-periodicity] [--no-lost-contact]
[--symmetry none]``
(about 40 minutes on 2 cores by halves; ``--unscaled`` adds about 31). Writes
``benchmarks/results/flow_tote.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    RESULTS,
    echo,
    machine,
    machine_line,
    percent_xyz,
    table,
    wait_for_quiet,
    write_atomic,
    write_json,
)

import blendxr as bx  # noqa: E402
from blendxr.flow.averaging import lab_velocities, periodicity  # noqa: E402
from blendxr.flow.solver import FlowSimulation  # noqa: E402

DEFAULT_SCALING = bx.load_scene("tote-40-top-bottom")["solver"]["stiffness_scaling"]
PERIODICITY_CELL = 0.0125
MIX_REVOLUTIONS = 5.0
REVOLUTIONS = 5  # part 1: eq. (30) between every two successive ones, as Table 3
TWIN_PERTURBATION = 1e-7  # m
PAPER_CELL = 0.0075


LOST_CONTACT = [True]  # --no-lost-contact: False
SYMMETRY = ["auto"]  # set by --symmetry


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
            "lost_contact": LOST_CONTACT[0],
            "symmetry": SYMMETRY[0],
        },
    }


def _escape_tracker(every: int):
    """Callback keeping the deepest particle escape (max signed distance) seen."""
    deepest = [-math.inf]

    def check(sim):
        if sim.steps % every == 0:
            deepest[0] = max(deepest[0], float(sim.vessel.sdf(sim.particles.x).max()))

    return check, deepest


def _attrs(flow) -> dict:
    a = flow.attrs
    out = {}
    for key, prefix in (
        ("periodicity_lab", "periodicity_"),
        ("periodicity_lab_norm", "periodicity_"),
        ("periodicity_vessel_frame", "periodicity_vessel_frame_"),
        ("periodicity_noise", "periodicity_noise_"),
        ("periodicity_noise_norm", "periodicity_noise_"),
    ):
        suffix = "_norm" if key.endswith("_norm") else ""
        out[key] = {c: a[f"{prefix}{c}{suffix}"] for c in ("vx", "vy", "vz")}
    return out


def _last_revolution(sim) -> tuple[np.ndarray, np.ndarray]:
    """(fill, lab-frame velocities) of the last recorded revolution."""
    fill, vel, _ = sim.last.fields()
    return fill, lab_velocities(sim.output, vel)


def twin_case(fraction, reference: tuple[np.ndarray, np.ndarray]) -> dict:
    """The same run from a start perturbed by up to TWIN_PERTURBATION in x and y: how far
    apart the last revolutions' flows end (sensitivity to the initial state, against
    which the change between revolutions is to be read)."""
    sim = FlowSimulation(tote(fraction, PERIODICITY_CELL, DEFAULT_SCALING, REVOLUTIONS))
    rng = np.random.default_rng(1)
    sim.particles.x[:, :2] += TWIN_PERTURBATION * rng.uniform(-1.0, 1.0, (sim.particles.count, 2))
    sim.run(progress=False)
    fill, twin = _last_revolution(sim)
    fill_ref, ref = reference
    change = periodicity(ref, twin, fill_ref, fill)
    material = (fill_ref > 0.5) & (fill > 0.5)  # eq. (30)'s cells
    return {
        "perturbation_m": TWIN_PERTURBATION,
        "eq30_lab": {c: change[c] for c in ("vx", "vy", "vz")},
        "eq30_lab_norm": {c: change[f"{c}_norm"] for c in ("vx", "vy", "vz")},
        # over the cells holding material in both; the bed's edge cells, a few samples
        # each, are left out as eq. (30) leaves them out
        "largest_difference_over_largest_speed": float(
            np.abs(twin - ref)[material].max() / np.abs(ref)[material].max()
        ),
    }


def periodicity_case(fraction, twin=False) -> dict:
    sim = FlowSimulation(tote(fraction, PERIODICITY_CELL, DEFAULT_SCALING, REVOLUTIONS))
    check, deepest = _escape_tracker(1)
    started = time.perf_counter()
    sim.run(progress=False, callback=check)
    wall = time.perf_counter() - started
    flow = bx.validate(sim.dataset(wall=wall))
    before = bx.validate(sim.dataset("previous", wall=wall))
    mixed, mixed_before = (
        bx.mix(f, revolutions=MIX_REVOLUTIONS, cells=50, output_every=0.5, progress=False)
        for f in (flow, before)
    )
    rsd, rsd_before = (m["rsd"].values for m in (mixed, mixed_before))
    a = flow.attrs
    history = {
        "revolution": [int(r) for r in a["periodicity_history_revolution"]],
        **{c: [float(x) for x in a[f"periodicity_history_{c}"]] for c in ("vx", "vy", "vz")},
    }
    at = history["revolution"].index(3)
    out = {
        "fill": fraction,
        "cell_m": PERIODICITY_CELL,
        "stiffness_scaling": DEFAULT_SCALING,
        "revolutions": REVOLUTIONS,
        "particles": a["particles"],
        "particles_solved": a["particles_solved"],
        "steps": a["steps"],
        "wall_s": wall,
        "particle_updates_per_s": a["particle_updates_per_s"],
        "deepest_escape_m": deepest[0],
        "valid": True,
        # the figure: revolutions 2 and 3
        "periodicity_2_3_lab": {c: history[c][at] for c in ("vx", "vy", "vz")},
        "periodicity_history_lab": history,
        **_attrs(flow),
        "current_volume_over_seeded": a["current_volume_over_seeded"],
        "fill_clipped_max": a["fill_clipped_max"],
        "mix_rsd_start_end": [float(rsd[0]), float(rsd[-1])],
        "mix_mass_drift": float(mixed.attrs["mass_a_relative_drift"]),
        # what the flow's change between revolutions does to the answer: the same mixing
        # on the flow of the revolution before the last
        "mix_revolutions": mixed["revolution"].values.tolist(),
        "mix_rsd": rsd.tolist(),
        "mix_rsd_from_revolution_before": rsd_before.tolist(),
        "mix_rsd_largest_relative_change": float(np.max(np.abs(rsd_before - rsd) / rsd)),
    }
    if twin:
        out["twin"] = twin_case(fraction, _last_revolution(sim))
    return out


def memory(sim) -> dict:
    """MiB held by the particles (every per-particle array, return codes included), the
    background grid (per-thread grids, node fields, wall distances and normals) and the
    phase accumulators of the last two revolutions."""
    p, g = sim.particles, sim.grid
    grid = g.nbytes + g.node_sdf.nbytes + g.node_normal.nbytes
    mib = 2.0**20
    return {
        "particles_mib": p.nbytes / mib,
        "bytes_per_particle": p.nbytes / p.count,
        "grid_mib": grid / mib,
        "phase_accumulators_mib": (sim.last.nbytes + sim.previous.nbytes) / mib,
    }


def paper_case(scaling, revolutions=3) -> dict:
    """The 40 % Tote at 7.5 mm: wall time at the end of revolution 2, eq. (30) of 2 vs 3."""
    sim = FlowSimulation(tote(0.4, PAPER_CELL, scaling, revolutions, phases=36))
    settle, period = sim.settings.settle_time, sim.period
    marks = {}
    check, deepest = _escape_tracker(50)

    def watch(s):
        check(s)
        now = time.perf_counter() - started
        for name, when in (("turning", settle), ("rev1", settle + period),
                           ("rev2", settle + 2 * period)):  # fmt: skip
            if name not in marks and s.t >= when - 1e-12:
                marks[name] = (now, s.steps)

    started = time.perf_counter()
    sim.run(progress=False, callback=watch)
    wall = time.perf_counter() - started
    flow = bx.validate(sim.dataset(wall=wall))
    (w1, n1), (w2, n2) = marks["rev1"], marks["rev2"]
    per_step = (w2 - w1) / (n2 - n1)  # revolution 2: turning, the bed in its periodic flow
    return {
        "fill": 0.4,
        "cell_m": PAPER_CELL,
        "stiffness_scaling": scaling,
        "particles": sim.particles.count * sim.copies,
        "particles_solved": sim.particles.count,
        "dt_s": sim.stable_dt(),
        "steps_two_revolutions": n2,
        "wall_two_revolutions_s": w2,
        "wall_settle_s": marks["turning"][0],
        "steps": sim.steps,
        "wall_s": wall,
        "ms_per_step": per_step * 1e3,
        "particle_updates_per_s": sim.particles.count / per_step,
        "deepest_escape_m": deepest[0],
        "valid": True,
        **_attrs(flow),
        "memory": memory(sim),
        "extrapolated": False,
    }


def unscaled_estimate(scaled: dict) -> dict:
    """Unscaled E: the same step cost, sqrt(scaling) times as many steps (dt ~ 1/c_p)."""
    factor = math.sqrt(scaled["stiffness_scaling"])
    steps = math.ceil(scaled["steps_two_revolutions"] * factor)
    return {
        "stiffness_scaling": 1.0,
        "particles": scaled["particles"],
        "particles_solved": scaled["particles_solved"],
        "steps_two_revolutions": steps,
        "ms_per_step": scaled["ms_per_step"],
        "wall_two_revolutions_s": steps * scaled["ms_per_step"] / 1e3,
        "extrapolated": True,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--unscaled", action="store_true", help="also run the unscaled case")
    parser.add_argument("--skip-periodicity", action="store_true", help="skip part 1")
    parser.add_argument(
        "--no-lost-contact", dest="lost_contact", action="store_false",
        help="solver.lost_contact off: the paper's model as it stands (docs/flow.md)",
    )  # fmt: skip
    parser.add_argument(
        "--symmetry", default="auto", choices=["auto", "none"],
        help="solver.symmetry (auto: the half z >= 0 with a mirror plane; none: whole bed)",
    )  # fmt: skip
    args = parser.parse_args()
    LOST_CONTACT[0] = args.lost_contact
    SYMMETRY[0] = args.symmetry
    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    FlowSimulation(tote(0.4, 0.03, 100.0, 2)).run(max_steps=20, progress=False)  # compile
    periodic = []
    for fraction in () if args.skip_periodicity else (0.4, 0.6):
        r = periodicity_case(fraction, twin=fraction == 0.4)
        periodic.append(r)
        lab, noise = percent_xyz(r["periodicity_2_3_lab"]), percent_xyz(r["periodicity_noise"])
        echo(
            f"fill {fraction}: {r['particles']} particles, {r['wall_s']:.0f} s, "
            f"lab {lab}, noise {noise}"
        )
    paper = [paper_case(DEFAULT_SCALING)]
    if args.unscaled:
        paper.append(paper_case(1.0, revolutions=2))
    else:
        paper.append(unscaled_estimate(paper[0]))
    for r in paper:
        echo(f"7.5 mm, E/{r['stiffness_scaling']:g}: two revolutions "
             f"{r['wall_two_revolutions_s'] / 60:.1f} min")  # fmt: skip

    text1 = table(
        ["fill", "cell mm", "particles", "solved", "wall s", "eq. 30 lab, revs 2-3 x/y/z",
         "noise part x/y/z", "vessel frame, last two x/y/z", "max sdf m",
         f"RSD, {MIX_REVOLUTIONS:g} rev", "RSD on the revolution before: largest change"],
        [
            [
                f"{r['fill']:.0%}", f"{r['cell_m'] * 1000:g}", r["particles"],
                r["particles_solved"], f"{r['wall_s']:.0f}",
                percent_xyz(r.get("periodicity_2_3_lab", r["periodicity_lab"])),
                percent_xyz(r["periodicity_noise"]), percent_xyz(r["periodicity_vessel_frame"]),
                f"{r['deepest_escape_m']:.1e}",
                f"{r['mix_rsd_start_end'][0]:.3f} -> {r['mix_rsd_start_end'][1]:.3f}"
                if "mix_rsd_start_end" in r else "",
                f"{r['mix_rsd_largest_relative_change']:.1%}"
                if "mix_rsd_largest_relative_change" in r else "",
            ]
            for r in periodic + [p for p in paper if "periodicity_lab" in p and p["steps"] >
                                 p["steps_two_revolutions"]]
        ],
    )  # fmt: skip
    turned = periodic[0]["periodicity_history_lab"]["revolution"] if periodic else []
    pairs = [f"{j - 1}-{j}" for j in turned]
    text4 = table(
        ["fill"] + [f"revs {pair} x/y/z" for pair in pairs] + ["current volume / seeded"],
        [
            [f"{r['fill']:.0%}"]
            + [
                percent_xyz({c: r["periodicity_history_lab"][c][i] for c in ("vx", "vy", "vz")})
                for i in range(len(pairs))
            ]
            + [f"{r['current_volume_over_seeded']:.3f}"]
            for r in periodic
        ],
    )  # fmt: skip
    twins = [r for r in periodic if "twin" in r]
    text5 = "\n".join(
        f"{r['fill']:.0%} fill, start perturbed by up to {r['twin']['perturbation_m']:g} m: "
        "eq. (30) between the two runs' last revolutions "
        + " / ".join(f"{r['twin']['eq30_lab'][c]:.2%}" for c in ("vx", "vy", "vz"))
        + " (lab x/y/z), largest velocity difference "
        + f"{r['twin']['largest_difference_over_largest_speed']:.2%} of the largest speed "
        "(cells with fill > 0.5 in both)."
        for r in twins
    )
    text3 = table(
        ["E scaling", "particles MiB", "B/particle", "grid MiB", "phase accumulators MiB"],
        [
            [
                f"1/{r['stiffness_scaling']:g}", f"{r['memory']['particles_mib']:.1f}",
                f"{r['memory']['bytes_per_particle']:.0f}", f"{r['memory']['grid_mib']:.1f}",
                f"{r['memory']['phase_accumulators_mib']:.0f}",
            ]
            for r in paper if "memory" in r
        ],
    )  # fmt: skip
    text2 = table(
        ["E scaling", "particles", "solved", "steps", "ms/step", "M updates/s",
         "two revolutions min",
         "how"],
        [
            [
                f"1/{r['stiffness_scaling']:g}", r["particles"], r["particles_solved"],
                r["steps_two_revolutions"], f"{r['ms_per_step']:.1f}",
                f"{r['particles_solved'] / r['ms_per_step'] / 1e3:.2f}",
                f"{r['wall_two_revolutions_s'] / 60:.1f}",
                "extrapolated: measured ms/step times the steps E/1 needs"
                if r["extrapolated"] else "run (settling included)",
            ]
            for r in paper
        ],
    )  # fmt: skip
    echo()
    echo(text1)
    echo()
    echo(text4)
    echo(text5)
    echo()
    echo(text2)
    echo()
    echo(text3)
    md = (
        "<!-- written by benchmarks/flow_tote.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        f"`solver.lost_contact = {str(args.lost_contact).lower()}`, "
        f'`solver.symmetry = "{args.symmetry}"` (particles: the whole bed; solved: '
        "those the solver computed, the half z >= 0 with a mirror plane when symmetric; "
        "M updates/s counts solved particles).\n\n"
        "Periodicity (eq. 30) between revolutions 2 and 3, Tote at 10 rpm, "
        f"E/{DEFAULT_SCALING:g}; 12 phase bins at 12.5 mm (five revolutions turned), 36 at "
        "7.5 mm (three). Noise part: eq. (30) between the phase averages of the even- and "
        "odd-numbered particles of the last revolution, over sqrt 2: what the sampling "
        "noise of the averages alone puts into eq. (30). Max sdf: the deepest particle "
        "escape (every step at 12.5 mm, every 50 at 7.5 mm; negative: none left the "
        "vessel); RSD from `bx.mix` "
        f"on the flow over {MIX_REVOLUTIONS:g} revolutions (top-bottom loading, 50 cells, "
        "output every half revolution), and the largest relative change of that RSD "
        "curve when the flow of the revolution before the last is repeated instead of "
        "the last's. Noise part and vessel frame: between the last two revolutions.\n\n"
        + text1
        + "\n\nEq. (30) between every two successive revolutions (lab frame, as the "
        "paper's Table 3: 3.95 / 2.30 / 2.91 %, 0.56 / 0.38 / 1.18 %, 1.85 / 3.03 / 2.53 % "
        "for revolutions 1-2, 2-3, 3-4), and the bed's current volume (J times the seeded "
        "volumes) at the end.\n\n"
        + text4
        + ("\n\nSensitivity to the initial state: " + text5 if text5 else "")
        + f"\n\nCost of the paper's case: 40 % fill, {PAPER_CELL * 1000:g} mm cell, settling "
        "plus two revolutions; ms/step over revolution 2.\n\n" + text2 + "\n\n"
        "Memory of the paper's case (the solved particles; the grid with the mirror "
        "plane's padding; 36 phase bins, two revolutions, the last in two halves for the "
        "noise part).\n\n" + text3 + "\n"
    )
    write_atomic(RESULTS / "flow_tote.md", md)
    payload = {"machine": info, "lost_contact": args.lost_contact, "symmetry": args.symmetry}
    write_json("flow_tote", {**payload, "periodicity": periodic, "paper": paper})


if __name__ == "__main__":
    main()
