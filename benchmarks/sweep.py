"""Sweeps on a LocalCluster against the same cases one after another.

Cases: the 2-D drum of ``drum-2d-mpm`` with a coarse solver flow (20 mm cell), swept over
``mixing.k1`` x ``operation.rpm``. ``small``: 10 x 5 = 50 cases sharing 5 flows, each
mixed for half a revolution on 24 cells (a tenth of a second each: the sweep's own cost
shows); ``medium``: 5 x 2 = 10 cases sharing 2 flows, four revolutions on 320 cells (a few
seconds each). The sweep runs on a
``LocalCluster`` of 2 worker processes with one thread each (numba at one thread); the
serial run solves the same 5 flows and mixes the 50 cases one after another in this
process with numba at 2 threads. Both start with an empty flow cache, so both solve the
flows. Reported: wall time of each, cases accounted for (ok or failed with their error),
flows solved, and whether the answers agree (revolutions to RSD 0.2 and the RSD curve).

Run: ``python benchmarks/sweep.py`` (1-3 minutes on 2 cores). Writes
``benchmarks/results/sweep.{json,md}``.
"""

from __future__ import annotations

import os

os.environ.setdefault("NUMBA_NUM_THREADS", "2")

import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from _common import RESULTS, echo, machine, machine_line, table, write_atomic, write_json  # noqa: E402

import blendxr as bx  # noqa: E402

TINY = {
    "flow.cell": 0.02,
    "solver.settle_time": 0.1,
    "mixing.revolutions": 0.5,
    "numerics.cells": 24,
}
CONFIGS = {
    "small": (
        TINY,
        {
            "mixing.k1": [0.0, 0.002, 0.004, 0.006, 0.008, 0.01, 0.012, 0.015, 0.02, 0.03],
            "operation.rpm": [10.0, 15.0, 20.0, 25.0, 30.0],
        },
    ),
    "medium": (
        {**TINY, "mixing.revolutions": 4.0, "numerics.cells": 320},
        {"mixing.k1": [0.0, 0.005, 0.01, 0.02, 0.03], "operation.rpm": [20.0, 30.0]},
    ),
}
WORKERS = 2


def serial(base, vary, cache: Path) -> dict:
    """Every case one after another in this process."""
    started = time.perf_counter()
    answers = {}
    for rpm in vary["operation.rpm"]:
        for k1 in vary["mixing.k1"]:
            scene = bx.load_scene(base, {"mixing.k1": k1, "operation.rpm": rpm})
            flow, _ = bx.scene_flow(scene, cache=cache)
            mixed = bx.mix(flow, scene, progress=False)
            answers[(k1, rpm)] = mixed["rsd"].values
    return {"wall_s": time.perf_counter() - started, "answers": answers}


def measure(name: str, values: dict, vary: dict) -> dict:
    base = bx.load_scene("drum-2d-mpm", values)
    work = Path(tempfile.mkdtemp(prefix="blendxr-sweep-bench-"))
    try:
        # compile (or load numba's cache) once, outside both timings
        warm = bx.load_scene(base, {"mixing.revolutions": 0.05})
        bx.mix(bx.scene_flow(warm, cache=work / "warm")[0], warm, progress=False)
        started = time.perf_counter()
        result = bx.sweep(
            base, vary, store=work / "store", cache=work / "cache-sweep", workers=WORKERS,
            progress=False,
        )  # fmt: skip
        sweep_wall = time.perf_counter() - started
        alone = serial(base, vary, work / "cache-serial")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    status = result["status"].values
    ok = int((status == "ok").sum())
    failed = int((status == "failed").sum())
    agree = all(
        np.array_equal(
            result["rsd"].sel({"mixing.k1": k1, "operation.rpm": rpm}).values[: len(rsd)], rsd
        )
        for (k1, rpm), rsd in alone["answers"].items()
    )
    return {
        "config": name,
        "values": values,
        "vary": vary,
        "cases": int(status.size),
        "ok": ok,
        "failed": failed,
        "accounted_for": ok + failed == status.size,
        "flows_solved": int(result.attrs["flows_solved"]),
        "sweep_wall_s": sweep_wall,
        "serial_wall_s": alone["wall_s"],
        "speedup": alone["wall_s"] / sweep_wall,
        "answers_identical": agree,
        "workers": WORKERS,
        "numba_threads_serial": int(os.environ["NUMBA_NUM_THREADS"]),
    }


def main() -> None:
    info = machine()
    echo(f"machine: {machine_line(info)}")
    rows = [measure(name, values, vary) for name, (values, vary) in CONFIGS.items()]
    text = "\n".join(
        [
            "# Sweeps on a LocalCluster against one after another",
            "",
            f"Machine: {machine_line(info)}",
            "",
            table(
                [
                    "config",
                    "cases",
                    "ok",
                    "failed",
                    "flows solved",
                    "sweep s",
                    "serial s",
                    "speed-up",
                    "same answers",
                ],  # fmt: skip
                [
                    [
                        r["config"],
                        r["cases"],
                        r["ok"],
                        r["failed"],
                        r["flows_solved"],
                        f"{r['sweep_wall_s']:.1f}",
                        f"{r['serial_wall_s']:.1f}",
                        f"{r['speedup']:.2f}",
                        r["answers_identical"],
                    ]  # fmt: skip
                    for r in rows
                ],
            ),
            "",
            f"Sweep: {WORKERS} worker processes, one thread and one numba thread each, "
            "started by `bx.sweep` (start-up and shut-down included). Serial: the same "
            "cases in one process, numba at 2 threads. Both solve their flows.",
            "",
        ]
    )
    write_json("sweep", {"benchmark": "sweep", "machine": info, "results": rows})
    write_atomic(RESULTS / "sweep.md", text)
    echo(text)


if __name__ == "__main__":
    main()
