"""The Tote's flow averaged over several revolutions: how periodic, and what it answers.

The flow between revolutions changes by a fixed amount whatever the lag: eq. (30) between
revolutions r and r + k of the 40 % Tote (12.5 mm, ψ = 0) is 5.3-6.2 / 5.3-6.0 /
14.7-15.4 % for k = 1, 6.0-6.5 / 5.8-6.6 / 15.6-16.6 % for k = 2 and 6.2-6.5 / 6.1-6.8 /
16.6-18.1 % for k = 3 (measured ad hoc with the drift benchmark's scene): each revolution
is a periodic flow plus a departure of its own, not a drift, which an average over n
revolutions should shrink (by up to sqrt n, were the departures independent; this
benchmark measures by how much). ``solver.average_revolutions``
makes the flow the phase average over the last n revolutions, and eq. (30) compares it
with the average over the n before.

Cases: the 40 % Tote at 10 rpm, 12.5 mm cell, 12 phase bins, E/10 (flow_tote's scene),
seven revolutions, the flow averaged over the last three (revolutions 5-7, compared with
2-4; revolution 1, the start from rest, in neither), without dilation (``psi0_n3``) and
with Table 1's ψ = 0.1° (``table1_n3``), through ``bx.solve_flow``; the baseline
``psi0_n1`` records the same ψ = 0 run revolution by revolution; ``psi0_n3_60`` and
``psi0_n1_60`` the same at 60 % fill. Reported: eq. (30)
between the two averages (lab and vessel frame) and its sampling-noise part, and the
mixing answer on the averaged flow (``bx.mix`` over five revolutions, top-bottom
loading, 50 cells, as flow_tote_drift reports it for single revolutions).

Run: ``python benchmarks/flow_tote_average.py [--case NAME ...]`` (each case about 12
minutes at 40 % and 20 at 60 % on one core of this machine; the solver runs beds under
20 000 solved particles on one thread, so two cases, started as two invocations, share
2 cores). Writes
``benchmarks/results/flow_tote_average.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import time  # noqa: E402

import flow_tote  # noqa: E402
from _common import machine_line, percent_xyz, run_cases, table  # noqa: E402

import blendxr as bx  # noqa: E402

NAME = "flow_tote_average"
FILL = 0.4
CELL = 0.0125
PHASES = 12
REVOLUTIONS = 7
AVERAGED = 3
#: case -> (dilation angle [degrees], revolutions averaged, fill); the *_n1 cases are the
#: baselines: the same run with single revolutions, eq. (30) between every two successive
CASES = {
    "psi0_n3": (0.0, AVERAGED, FILL),
    "table1_n3": (0.1, AVERAGED, FILL),
    "psi0_n1": (0.0, 1, FILL),
    "psi0_n3_60": (0.0, AVERAGED, 0.6),
    "psi0_n1_60": (0.0, 1, 0.6),
}
MIX = {"revolutions": 5, "cells": 50, "output_every": 0.5, "progress": False}
COMPONENTS = ("vx", "vy", "vz")


def scene(dilation_deg: float, averaged: int, fill: float) -> dict:
    out = flow_tote.tote(fill, CELL, flow_tote.DEFAULT_SCALING, REVOLUTIONS, phases=PHASES)
    out["material"] = {"dilation_angle_deg": dilation_deg}
    out["solver"]["average_revolutions"] = averaged
    return out


def run_case(name: str) -> dict:
    started = time.perf_counter()
    flow = bx.solve_flow(scene(*CASES[name]), progress=False)
    wall = time.perf_counter() - started
    rsd = bx.mix(flow, **MIX)["rsd"].values
    a = flow.attrs
    return {
        "case": name,
        "dilation_angle_deg": CASES[name][0],
        "fill": CASES[name][2],
        "revolutions": REVOLUTIONS,
        "averaged_revolutions": int(a["averaged_revolutions"]),
        "particles_solved": int(a["particles_solved"]),
        "steps": int(a["steps"]),
        "wall_s": wall,
        "eq30_lab": {c: float(a[f"periodicity_{c}"]) for c in COMPONENTS},
        "eq30_vessel": {c: float(a[f"periodicity_vessel_frame_{c}"]) for c in COMPONENTS},
        "eq30_noise": {c: float(a[f"periodicity_noise_{c}"]) for c in COMPONENTS},
        "eq30_history": {
            "last_revolution": [int(r) for r in a["periodicity_history_revolution"]],
            **{c: [float(v) for v in a[f"periodicity_history_{c}"]] for c in COMPONENTS},
        },
        "mix_rsd": rsd.tolist(),
    }


def report(results: dict, info: dict) -> str:
    rows = [
        [
            name, f"{r.get('fill', FILL):.0%}", r["dilation_angle_deg"],
            f"{r['revolutions']}, last {r['averaged_revolutions']}",
            percent_xyz(r["eq30_lab"]), percent_xyz(r["eq30_vessel"]),
            percent_xyz(r["eq30_noise"]), f"{r['mix_rsd'][0]:.3f} -> {r['mix_rsd'][-1]:.3f}",
            f"{r['wall_s']:.0f}",
        ]
        for name, r in ((c, results[c]) for c in CASES if c in results)
    ]  # fmt: skip
    history = [
        [name, f"{last - 1}-{last}", percent_xyz({c: r["eq30_history"][c][i] for c in COMPONENTS})]
        for name, r in ((c, results[c]) for c in CASES if c in results)
        if r["averaged_revolutions"] == 1
        for i, last in enumerate(r["eq30_history"]["last_revolution"])
    ]  # fmt: skip
    baseline = (
        "\nThe baseline, the same run recorded revolution by revolution "
        "(`average_revolutions = 1`): eq. (30) between every two successive "
        "revolutions.\n\n" + table(["case", "revolutions", "eq. 30 lab x/y/z"], history) + "\n"
        if history
        else ""
    )
    return (
        f"<!-- written by benchmarks/{NAME}.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        f"The Tote at 40 % (and 60 %: *_60), 10 rpm, {CELL * 1000:g} mm cell, "
        f"{PHASES} phase bins, E/10, "
        f"turned {REVOLUTIONS} revolutions with `solver.average_revolutions = {AVERAGED}`: "
        f"the flow is the phase average over revolutions {REVOLUTIONS - AVERAGED + 1}-"
        f"{REVOLUTIONS}, and eq. (30) compares it with the average over revolutions "
        f"{REVOLUTIONS - 2 * AVERAGED + 1}-{REVOLUTIONS - AVERAGED}. Noise part: eq. (30) "
        "between the averages of the even- and odd-numbered particles, over sqrt 2. RSD: "
        "`bx.mix` on the averaged flow, five revolutions, top-bottom loading, 50 cells "
        "(flow_tote_drift.md gives it on single revolutions).\n\n"
        + table(
            [
                "case",
                "fill",
                "ψ °",
                "revolutions, averaged",
                "eq. 30 lab x/y/z",
                "vessel frame x/y/z",
                "noise part x/y/z",
                "RSD, 5 rev",
                "wall s",
            ],
            rows,
        )  # fmt: skip
        + "\n"
        + baseline
    )


def _summary(name: str, r: dict) -> str:
    return (
        f"{name}: {r['wall_s']:.0f} s, lab {percent_xyz(r['eq30_lab'])}, "
        f"RSD after 5 rev {r['mix_rsd'][-1]:.3f}"
    )


def main() -> None:
    run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, _summary)


if __name__ == "__main__":
    main()
