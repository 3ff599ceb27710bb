"""The Tote's flow over six revolutions: does it settle into a periodic state?

The 40 % Tote at 10 rpm, 12.5 mm cell, 12 phase bins, E/10 (flow_tote's scene) is
turned six revolutions with the dilation angle of the paper's Table 1 (``table1``,
ψ = 0.1°) and without dilation (``psi0``, ψ = 0; the paper sets 0.1° as "the minimum
value allowed in Abaqus", for a material whose dilation is small). For every
revolution r it reports:

- eq. (30) between revolutions r - 1 and r (lab frame, as the issue's figure; vessel
  frame, without the rigid rotation);
- the bed's volume as the solver carries it (J times the seeded volumes, over the
  seeded volume), the mean contact gap, the mean pressure, and the volume the particles
  really take (``blendxr.flow.output.occupied_volume_over_seeded``: the seeded 8
  particles per cell over the mean count in the cells inside the bed, those whose 26
  neighbours all hold particles), at the revolution's end;
- the mixing answer on that revolution's flow: ``bx.mix`` over five revolutions
  (top-bottom loading, 50 cells, output every half revolution), its RSD at the end, and
  the largest relative change of the RSD curve from the revolution before's;
- eq. (30) between the averages of two successive revolutions and of the next two
  (fill-weighted: volume and momentum kept), non-overlapping, to ask whether averaging
  over revolutions would take the change out (it does when the change is random, not
  when the flow drifts).

Run: ``python benchmarks/flow_tote_drift.py [--case NAME ...]`` (each case about 15
minutes on this machine; the flow solver runs beds under 20 000 solved particles on
one thread, so two cases, started as two invocations, share 2 cores, but for the short
mixing runs). Writes
``benchmarks/results/flow_tote_drift.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import time  # noqa: E402

import flow_tote  # noqa: E402
import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    echo,
    machine_line,
    percent_xyz,
    run_cases,
    table,
)

import blendxr as bx  # noqa: E402
from blendxr.flow.averaging import fields_change  # noqa: E402
from blendxr.flow.output import occupied_volume_over_seeded  # noqa: E402
from blendxr.flow.solver import FlowSimulation  # noqa: E402

NAME = "flow_tote_drift"
FILL = 0.4
CELL = 0.0125
PHASES = 12
REVOLUTIONS = 6
COMPONENTS = ("vx", "vy", "vz")
#: case -> dilation angle [degrees]
CASES = {"table1": 0.1, "psi0": 0.0}
MIX = {"revolutions": 5, "cells": 50, "output_every": 0.5, "progress": False}


def scene(dilation_deg: float) -> dict:
    out = flow_tote.tote(FILL, CELL, flow_tote.DEFAULT_SCALING, REVOLUTIONS, phases=PHASES)
    out["material"] = {"dilation_angle_deg": dilation_deg}
    return out


def _average(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Fill-weighted average of phase-binned fields: material volume and momentum kept."""
    fill = sum(f for f, _ in pairs) / len(pairs)
    momentum = sum(f[..., None] * v for f, v in pairs) / len(pairs)
    with np.errstate(invalid="ignore", divide="ignore"):
        vel = np.where(fill[..., None] > 0, momentum / fill[..., None], 0.0)
    return fill, vel


def _eq30(sim, a, b) -> dict:
    """Eq. (30) from fields a to fields b, lab and vessel frame."""
    change = fields_change(sim.output, a, b, vessel_frame=True)
    return {
        "lab": {c: change[c] for c in COMPONENTS},
        "vessel": {c: change[f"vessel_frame_{c}"] for c in COMPONENTS},
    }


def _mean_pressure(sim) -> float:
    p = sim.particles
    pressure = -np.trace(p.stress, axis1=1, axis2=2) / 3.0
    return float((pressure * p.vol).sum() / p.vol.sum())


def run_case(name: str) -> dict:
    sim = FlowSimulation(scene(CASES[name]))
    started = time.perf_counter()
    fields, rows, rsd = {}, [], {}
    for r in range(1, REVOLUTIONS + 1):
        sim.run(until=sim.settings.settle_time + r * sim.period, progress=False)
        fields[r] = sim.last.fields()[:2]  # revolution r's, as its flow dataset holds them
        row = {
            "revolution": r,
            "volume_over_seeded": sim.particles.volume_over_seeded,
            "real_volume_over_seeded": occupied_volume_over_seeded(sim),
            "mean_gap": float(sim.particles.gap.mean()),
            "mean_pressure_pa": _mean_pressure(sim),
        }
        if r >= 2:
            row["eq30"] = _eq30(sim, fields[r - 1], fields[r])
            flow = sim.dataset(wall=time.perf_counter() - started)
            rsd[r] = bx.mix(flow, **MIX)["rsd"].values
            row["mix_rsd"] = rsd[r].tolist()
            if r - 1 in rsd:
                row["mix_rsd_change_from_previous"] = float(
                    np.max(np.abs(rsd[r] - rsd[r - 1]) / rsd[r - 1])
                )
        rows.append(row)
        echo(f"  {name} revolution {r}: {time.perf_counter() - started:.0f} s")
    averages = {}
    for first in range(2, REVOLUTIONS - 2):
        a = _average([fields[first], fields[first + 1]])
        b = _average([fields[first + 2], fields[first + 3]])
        averages[f"{first}-{first + 1} vs {first + 2}-{first + 3}"] = _eq30(sim, a, b)
    return {
        "case": name,
        "dilation_angle_deg": CASES[name],
        "particles_solved": sim.particles.count,
        "steps": sim.steps,
        "wall_s": time.perf_counter() - started,
        "by_revolution": rows,
        "eq30_two_revolution_averages": averages,
    }


def report(results: dict, info: dict) -> str:
    rows = []
    for name in [c for c in CASES if c in results]:
        for row in results[name]["by_revolution"]:
            if "eq30" not in row:
                continue
            rows.append([
                name, row["revolution"], percent_xyz(row["eq30"]["lab"]),
                percent_xyz(row["eq30"]["vessel"]), f"{row['volume_over_seeded']:.3f}",
                f"{row['real_volume_over_seeded']:.3f}", f"{row['mean_gap']:.4f}",
                f"{row['mean_pressure_pa']:.0f}", f"{row['mix_rsd'][-1]:.3f}",
                f"{row['mix_rsd_change_from_previous']:.1%}"
                if "mix_rsd_change_from_previous" in row else "",
            ])  # fmt: skip
    per_revolution = table(
        ["case", "revolution r", "eq. 30 r-1 to r, lab x/y/z", "vessel frame x/y/z",
         "J volume / seeded", "real volume / seeded", "mean gap", "mean pressure Pa",
         "RSD after 5 rev on rev r", "RSD curve change from rev r-1"],
        rows,
    )  # fmt: skip
    rows = [
        [name, pair, percent_xyz(e["lab"]), percent_xyz(e["vessel"])]
        for name in [c for c in CASES if c in results]
        for pair, e in results[name]["eq30_two_revolution_averages"].items()
    ]
    averaged = table(["case", "revolutions", "lab x/y/z", "vessel frame x/y/z"], rows)
    return (
        f"<!-- written by benchmarks/{NAME}.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        f"The 40 % Tote, 10 rpm, {CELL * 1000:g} mm cell, {PHASES} phase bins, E/10, "
        f"turned {REVOLUTIONS} revolutions; table1: ψ = 0.1° (the paper's Table 1), "
        "psi0: ψ = 0. J volume: the bed's volume as the solver carries it (J times the "
        "seeded volumes); real volume: 8 seeded particles per cell over the mean count in "
        "the cells inside the bed; both over the seeded volume, at the revolution's end. "
        "RSD: `bx.mix` on revolution r's flow, five revolutions, top-bottom loading, "
        "50 cells; its change: the largest relative difference of the RSD curve from "
        "the one on revolution r - 1.\n\n" + per_revolution + "\n\n"
        "Eq. (30) between the fill-weighted averages of two successive revolutions and "
        "of the next two:\n\n" + averaged + "\n"
    )


def _summary(name: str, r: dict) -> str:
    last = r["by_revolution"][-1]
    return (
        f"{name}: {r['wall_s']:.0f} s, revolutions {REVOLUTIONS - 1}-{REVOLUTIONS} lab "
        f"{percent_xyz(last['eq30']['lab'])}, J volume {last['volume_over_seeded']:.3f},"
        f" real {last['real_volume_over_seeded']:.3f}"
    )


def main() -> None:
    run_cases(NAME, __doc__.splitlines()[0], CASES, run_case, report, _summary)


if __name__ == "__main__":
    main()
