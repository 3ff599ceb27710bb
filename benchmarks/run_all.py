"""Run every benchmark in turn: throughput, work-precision, memory.

Run: ``python benchmarks/run_all.py`` (3-15 minutes on 2 cores). Each script writes
its own results under ``benchmarks/results/``; this one stops at nothing and reports each
script's exit status at the end (status 1 if any failed).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPTS = ("throughput.py", "work_precision.py", "memory.py")


def main() -> int:
    env = dict(os.environ, NUMBA_NUM_THREADS="2")
    outcomes = []
    for name in SCRIPTS:
        print(f"==== {name}", flush=True)
        started = time.perf_counter()
        status = subprocess.call([sys.executable, str(HERE / name)], env=env)
        outcomes.append((name, status, time.perf_counter() - started))
    print("\n==== summary")
    for name, status, seconds in outcomes:
        print(f"{name:20s} {'ok' if status == 0 else f'FAILED ({status})':12s} {seconds:7.0f} s")
    return 0 if all(status == 0 for _, status, _ in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
