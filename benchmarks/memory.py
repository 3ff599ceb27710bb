"""Peak memory of a 100^3 ADE run whose 72-phase 3-D flow is read from disk.

The flow ``bx.flows.swirl(ndim=3, cells=50, n_phases=72, size=0.2)`` is written with
``bx.write_dataset`` to a temporary netCDF file; then, for each scheme, a fresh Python
process runs

    bx.mix(path, scheme=..., cells=100, revolutions=1.0, k1=0.01, d=0.002, progress=False)

(one revolution: every one of the 72 phases is read from the file, through the driver's
cyclic reader). Reported per scheme: the child's peak resident set size as the kernel
accounts it (``ru_maxrss`` from ``wait4`` on that child), the child's resident size
after ``import blendxr`` (the interpreter and libraries), a trace of its resident size
sampled every 0.25 s (to show whether memory grows as phases pass), the ``phases_read``
and ``steps`` attributes, and the on-disk size of the flow file; the target is a peak
below 2 GB (taken as 2 GiB).

Run: ``python benchmarks/memory.py`` (every scheme, 1-6 minutes on 2 cores), or
``python benchmarks/memory.py --schemes lax-wendroff --revolutions 0.3``. Writes
``benchmarks/results/memory.json``.
"""

from __future__ import annotations

import os

os.environ["NUMBA_NUM_THREADS"] = "2"

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

CELLS = 100
REVOLUTIONS = 1.0
PHYSICS = {"k1": 0.01, "d": 0.002}
TARGET_MIB = 2048.0
FLOW = {"ndim": 3, "cells": 50, "n_phases": 72, "size": 0.2}


def _vm(field: str) -> float | None:
    """A /proc/self/status field (VmRSS, VmHWM) in MiB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return None


def child(path: str, scheme: str, revolutions: float) -> None:
    """Run one mix in this (fresh) process and print a JSON line about it."""
    import blendxr as bx

    rss_after_import = _vm("VmRSS")
    trace: list[tuple[float, float]] = []
    peak = [0.0]
    done = threading.Event()
    started = time.perf_counter()

    def sample():
        last = -1e9
        while not done.is_set():
            rss = _vm("VmRSS") or 0.0
            peak[0] = max(peak[0], rss)
            now = time.perf_counter() - started
            if now - last >= 2.0:
                trace.append((round(now, 1), round(rss, 1)))
                last = now
            done.wait(0.25)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    mixed = bx.mix(
        path, scheme=scheme, cells=CELLS, revolutions=revolutions, progress=False, **PHYSICS
    )
    wall = time.perf_counter() - started
    done.set()
    sampler.join()
    trace.append((round(wall, 1), round(_vm("VmRSS") or 0.0, 1)))
    a = mixed.attrs
    import numba

    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = None
    report = {
        "numba_num_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "scheme": scheme,
        "revolutions": float(a["revolutions"]),
        "steps": int(a["steps"]),
        "phases_read": int(a["phases_read"]),
        "grid_cells": [int(x) for x in a["grid_cells"]],
        "wall_s": wall,
        "stopped_by": a["stopped_by"],
        "rss_after_import_mib": rss_after_import,
        "rss_sampled_peak_mib": peak[0],
        "vm_hwm_mib": _vm("VmHWM"),
        "ru_maxrss_self_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "rss_trace_s_mib": trace,
    }
    print("RESULT " + json.dumps(report), flush=True)


def run_child(path: Path, scheme: str, revolutions: float) -> dict:
    """Start a fresh interpreter for one run; its own peak RSS comes from wait4."""
    from _common import Contention

    command = [sys.executable, str(Path(__file__).resolve()), "--child", str(path)]
    command += ["--schemes", scheme, "--revolutions", repr(revolutions)]
    started = time.perf_counter()
    meter = Contention().__enter__()
    # stderr goes to a file, so that reading stdout to its end cannot block on a full pipe;
    # the child is reaped with wait4 (not Popen.wait) to get its own resource usage
    with tempfile.TemporaryFile(mode="w+") as errors:
        proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=errors, text=True)
        out = proc.stdout.read()
        proc.stdout.close()
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        errors.seek(0)
        err = errors.read()
    elapsed = time.perf_counter() - started
    meter.__exit__(None, None, None)
    lines = [line for line in out.splitlines() if line.startswith("RESULT ")]
    if proc.returncode != 0 or not lines:
        return {
            "scheme": scheme,
            "error": f"child exited with status {proc.returncode}",
            "stderr_tail": err[-4000:],
            "peak_rss_mib": usage.ru_maxrss / 1024.0,
        }
    report = json.loads(lines[-1][len("RESULT ") :])
    report["peak_rss_mib"] = usage.ru_maxrss / 1024.0  # Linux: KiB
    report["child_elapsed_s"] = elapsed
    report["contention"] = meter.as_dict()
    report["under_target"] = report["peak_rss_mib"] < TARGET_MIB
    return report


def main() -> None:
    import numpy as np
    from _common import (
        cpu_pressure,
        echo,
        load_average,
        machine,
        machine_line,
        table,
        wait_for_quiet,
        write_json,
    )

    import blendxr as bx

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--schemes", default=",".join(bx.SCHEMES))
    parser.add_argument("--revolutions", type=float, default=REVOLUTIONS)
    args = parser.parse_args()
    schemes = [s for s in args.schemes.split(",") if s]

    quiet = wait_for_quiet()
    info = machine()
    info["quiet_wait"] = quiet
    echo(f"machine: {machine_line(info)}")
    results = []
    with tempfile.TemporaryDirectory(prefix="blendxr-memory-") as tmp:
        path = Path(tmp) / "flow.nc"
        flow = bx.flows.swirl(**FLOW)
        in_memory = int(flow.nbytes)
        started = time.perf_counter()
        bx.write_dataset(flow, path)
        write_s = time.perf_counter() - started
        del flow
        disk = path.stat().st_size
        echo(
            f"flow file: {disk / 2**20:.1f} MiB on disk ({in_memory / 2**20:.1f} MiB in memory), "
            f"written in {write_s:.1f} s"
        )
        for scheme in schemes:
            report = run_child(path, scheme, args.revolutions)
            results.append(report)
            if "error" in report:
                echo(f"{scheme}: FAILED: {report['error']}\n{report['stderr_tail']}")
            else:
                echo(
                    f"{scheme:14s} peak RSS {report['peak_rss_mib']:.0f} MiB, "
                    f"{report['steps']} steps, {report['phases_read']} phases read, "
                    f"{report['wall_s']:.0f} s"
                )

    echo()
    echo(
        f"## Peak memory, {CELLS}^3 ADE cells, 72-phase 3-D swirl read from disk "
        f"({args.revolutions:g} revolution)"
    )
    echo()
    rows = []
    for r in results:
        if "error" in r:
            rows.append([r["scheme"], "failed", "", "", "", "", "", ""])
            continue
        rows.append(
            [
                r["scheme"],
                f"{r['peak_rss_mib']:.0f}",
                f"{r['rss_after_import_mib']:.0f}",
                f"{r['peak_rss_mib'] - r['rss_after_import_mib']:.0f}",
                f"{TARGET_MIB:.0f}",
                "yes" if r["under_target"] else "NO",
                r["phases_read"],
                r["steps"],
                f"{r['wall_s']:.0f}",
            ]
        )
    echo(
        table(
            [
                "scheme",
                "peak RSS MiB",
                "after import MiB",
                "run MiB",
                "target MiB",
                "under",
                "phases_read",
                "steps",
                "wall s",
            ],
            rows,
            align="lrrrrlrrr",
        )
    )
    echo()
    echo(
        f"flow file on disk: {disk / 2**20:.1f} MiB ({disk} bytes); "
        f"in memory: {in_memory / 2**20:.1f} MiB"
    )
    for r in results:
        if "rss_trace_s_mib" in r:
            trace = r["rss_trace_s_mib"]
            rss = np.array([x[1] for x in trace])
            half = len(rss) // 2
            echo(
                f"{r['scheme']}: RSS over the run {rss.min():.0f}..{rss.max():.0f} MiB; "
                f"max of first half {rss[: half or 1].max():.0f}, second half "
                f"{rss[half:].max():.0f} MiB"
            )

    payload = {
        "benchmark": "memory",
        "machine": info,
        "settings": {
            "flow": "swirl(ndim=3, cells=50, n_phases=72, size=0.2), rpm default",
            "cells": CELLS,
            "revolutions": args.revolutions,
            **PHYSICS,
            "target_mib": TARGET_MIB,
            "peak_rss_mib": "ru_maxrss of the child process (wait4), KiB / 1024",
        },
        "flow_file_bytes": disk,
        "flow_file_mib": disk / 2**20,
        "flow_in_memory_mib": in_memory / 2**20,
        "flow_write_s": write_s,
        "runs": results,
        "load_average_at_end": load_average(),
        "cpu_pressure_at_end": cpu_pressure(),
    }
    out = write_json("memory", payload)
    echo()
    echo(f"wrote {out.relative_to(out.parents[2])}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        parser = argparse.ArgumentParser()
        parser.add_argument("--child")
        parser.add_argument("--schemes")
        parser.add_argument("--revolutions", type=float)
        ns = parser.parse_args()
        child(ns.child, ns.schemes, ns.revolutions)
    else:
        main()
