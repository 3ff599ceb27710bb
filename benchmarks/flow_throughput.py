"""Flow solver speed: particle updates per second of the full MPM step, and memory.

A full step is what ``FlowSimulation.step`` does: P2G into per-thread grids (with the
bulk viscosity) and their sum, grid update (gravity, centrifugal, Coriolis, walls with
friction), G2P with advection and the Mohr-Coulomb stress update, exact wall
projection, plus the re-sort every 20 steps. Cases: the default Tote at 40 % fill in 3-D
at three cell sizes (about 1e4 to 4e5 particles, 8 per cell) and the 2-D calibration
drum, each measured in a representative state: settled under gravity for 0.3 s and
turned for 1 s (60 degrees: gravity rotating, Coriolis on, the bed avalanching, so
much of the stress update takes its plastic branches; the shares of each return are
reported). E is scaled down by 100 to reach that state quickly; the cost of a step does
not depend on E. Each kernel is also timed alone, and so is the density projection
(``solver.density_projection``, once every 10 steps by default, not in the step's time)
and one sample of the phase averages (the deposit, every ``sample_every`` steps, not in
the step's time either).
The whole bed is solved (``solver.symmetry = "none"``): by default a symmetric Tote is
solved as its half z >= 0, the same work per particle on half the particles plus a fold
of the grid.

Memory per particle is the particle arrays' bytes (positions, velocities, affine
matrices, which are also the velocity gradients, stress, volumes, masses, Jacobians,
colour, return codes) divided by the count; the
background grid (per-thread copies included) is reported beside it.

Run: ``python benchmarks/flow_throughput.py`` (about 6 minutes on 2 cores). Writes
``benchmarks/results/flow_throughput.{json,md}``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import time  # noqa: E402

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    RESULTS,
    best_of,
    echo,
    machine,
    machine_line,
    table,
    wait_for_quiet,
    write_atomic,
    write_json,
)

from blendxr.flow import kernels as mpm  # noqa: E402
from blendxr.flow.solver import FlowSimulation  # noqa: E402
from blendxr.flow.walls import project_into_vessel  # noqa: E402

STEPS = 40  # steps per timed run
SETTLE = 0.3  # s of settling before the vessel turns
TURNED = 1.0  # s of turning (60 degrees: the bed is avalanching) before the timed steps
RETURNS = ("elastic", "plane", "edge-compression", "edge-extension", "apex", "tension-cap")


def tote(cell):
    return {
        "name": f"tote-40-{cell * 1000:g}mm",
        "vessel": {"kind": "tote", "ndim": 3},
        "operation": {"rpm": 10.0},
        "fill": {"fraction": 0.4},
        "flow": {"cell": cell, "phases": 12},
        "solver": {
            "settle_time": SETTLE,
            "revolutions": 2,
            "stiffness_scaling": 100.0,
            "symmetry": "none",
        },
    }


def drum(cell):
    return {
        "name": f"drum-2d-{cell * 1000:g}mm",
        "vessel": {"kind": "drum", "ndim": 2, "diameter": 0.15},
        "operation": {"rpm": 3.26},
        "fill": {"fraction": 0.32},
        "flow": {"cell": cell},
        "solver": {
            "settle_time": SETTLE,
            "revolutions": 2,
            "stiffness_scaling": 100.0,
            "symmetry": "none",
        },
    }


CASES = [("tote-3d", tote, c) for c in (0.015, 0.0075, 0.005)] + [
    ("drum-2d", drum, c) for c in (0.0025, 0.001)
]


def kernel_times(sim, dt) -> dict:
    """Milliseconds per call of each part of the step (fastest of 5)."""
    p, g = sim.particles, sim.grid
    three = sim.ndim == 3
    inv_h = 1.0 / g.h
    gravity, omega, damping = sim._body(sim.t)
    shape = np.asarray(g.shape, np.int64)
    state = {name: getattr(p, name).copy() for name in ("x", "v", "C", "vol", "J", "gap", "stress")}

    def restore():  # the same particles for every G2P call (not timed)
        for name, value in state.items():
            getattr(p, name)[...] = value

    def g2p():
        (mpm.g2p_3d if three else mpm.g2p_2d)(
            p.x, p.v, p.C, p.vol, p.J, p.gap, p.stress, p.codes, g.velocity, g.mass, g.origin,
            inv_h, dt, sim.stress_arguments, sim.starts, g.g2p_work,
        )  # fmt: skip

    parts = {
        "sort": lambda: mpm.sort_by_cell(p.x, g.origin, inv_h, shape),
        "p2g": lambda: (mpm.p2g_3d if three else mpm.p2g_2d)(
            p.x, p.v, p.C, p.mass, p.vol, p.stress, g.origin, inv_h, dt, sim.bulk,
            g.thread_grids, sim.starts,
        ),
        "reduce": lambda: (mpm.reduce_grids_3d if three else mpm.reduce_grids_2d)(
            g.thread_grids, g.mass, g.momentum
        ),
        "grid": lambda: (mpm.grid_update_3d if three else mpm.grid_update_2d)(
            g.mass, g.momentum, g.velocity, g.origin, g.h, dt, gravity, omega, damping,
            g.node_sdf, g.node_normal, 0.324, g.h,
        ),
        "g2p+stress": g2p,
        "project": lambda: project_into_vessel(
            sim.vessel.kind, sim.vessel.params, p.x, p.v, 1e-6, sim.starts, g.scratch,
            g.node_sdf.reshape(-1), g.origin, g.h, g.shape_array,
        ),
        # the density projection (solver.density_projection, every 10 steps by default,
        # so not in the step's time): scatter, Poisson solve and displacement
        "projection": lambda: sim.projection(p.x, p.vol, g.origin, sim.starts),
        # one sample of the phase averages (every ``sim.sample_every`` steps, not in the
        # step's time): both halves of the particles deposited onto the output cells
        "deposit": lambda: sim.last.add(0, p.x, p.v, p.vol0),
    }  # fmt: skip
    out = {}
    for name, fn in parts.items():
        best = np.inf
        for _ in range(5):
            restore()
            started = time.perf_counter()
            fn()
            best = min(best, time.perf_counter() - started)
        out[name] = best * 1e3
    return out


def measure(label, build, cell) -> dict:
    sim = FlowSimulation(build(cell))
    sim.run(until=SETTLE + TURNED, progress=False)  # settled, then turning
    dt = sim.stable_dt()

    def run():
        for _ in range(STEPS):
            sim.step(dt)

    timed = best_of(run, min_runs=2, max_runs=4, budget_s=60.0)
    n = sim.particles.count
    rate = n * STEPS / timed["wall_s"]
    counts = np.bincount(sim.particles.codes, minlength=len(RETURNS))
    return {
        "case": label,
        "cell_m": cell,
        "particles": n,
        "grid_nodes": int(np.prod(sim.grid.shape)),
        "steps": STEPS,
        "wall_s": timed["wall_s"],
        "particle_updates_per_s": rate,
        "ms_per_step": timed["wall_s"] / STEPS * 1e3,
        "kernels_ms": kernel_times(sim, dt),
        "returns": {name: float(k) / n for name, k in zip(RETURNS, counts, strict=True)},
        "bytes_per_particle": sim.particles.nbytes / n,
        "grid_mib": sim.grid.nbytes / 2**20,
        "dt_s": dt,
        "sample_every": sim.sample_every,
        "contention": timed["contention"],
    }


def main() -> None:
    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    started = time.perf_counter()
    FlowSimulation(tote(0.03)).run(max_steps=25, progress=False)  # compile
    FlowSimulation(drum(0.01)).run(max_steps=25, progress=False)
    echo(f"compile {time.perf_counter() - started:.1f} s")
    rows = []
    for label, build, cell in CASES:
        r = measure(label, build, cell)
        rows.append(r)
        echo(
            f"{label} cell {cell * 1000:g} mm: {r['particles']} particles, "
            f"{r['particle_updates_per_s'] / 1e6:.2f} M/s, {r['ms_per_step']:.2f} ms/step"
        )
    headers = ["case", "cell mm", "particles", "M updates/s", "ms/step", "B/particle", "grid MiB"]
    headers += ["plastic %"]
    headers += [f"{k} ms" for k in rows[0]["kernels_ms"]]
    body = [
        [
            r["case"],
            f"{r['cell_m'] * 1000:g}",
            r["particles"],
            f"{r['particle_updates_per_s'] / 1e6:.2f}",
            f"{r['ms_per_step']:.2f}",
            f"{r['bytes_per_particle']:.0f}",
            f"{r['grid_mib']:.1f}",
            f"{100 * (1 - r['returns']['elastic']):.0f}",
        ]
        + [f"{v:.2f}" for v in r["kernels_ms"].values()]
        for r in rows
    ]
    text = table(headers, body)
    echo()
    echo(text)
    md = (
        "<!-- written by benchmarks/flow_throughput.py -->\n"
        f"Machine: {machine_line(info)}.\n\n"
        "Full MPM step (P2G with bulk viscosity, grid update, G2P with the Mohr-Coulomb "
        f"update, wall projection, re-sort every 20 steps) timed over {STEPS} steps of a bed "
        f"settled for {SETTLE} s and turned for {TURNED} s (E/100 to get there; a step's "
        "cost does not depend on E); plastic % is the share of particles whose last stress "
        "update returned to the yield surface. Kernel columns are single calls (fastest of "
        "5); projection and deposit run every 10 and every `sample_every` steps and are not "
        "in the step's time. Target: >= 8 M particle updates/s on 2 cores.\n\n" + text + "\n"
    )
    write_atomic(RESULTS / "flow_throughput.md", md)
    write_json("flow_throughput", {"machine": info, "steps": STEPS, "results": rows})


if __name__ == "__main__":
    main()
