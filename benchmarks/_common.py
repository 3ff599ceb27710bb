"""Helpers shared by the benchmark scripts: machine description, atomic writes, tables.

Each benchmark script sets ``NUMBA_NUM_THREADS`` itself before importing numba or
blendxr; this module imports numba only inside functions, after that has happened.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import hashlib
import json
import math
import os
import platform
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
REPO = HERE.parent


def flow_cache() -> Path:
    """The flow cache the benchmarks share: ``$BLENDXR_CACHE``, else ``runs/cache`` in the
    checkout (solved flows are reused across scripts and runs)."""
    return Path(os.environ.get("BLENDXR_CACHE", REPO / "runs" / "cache"))


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo, else what the platform module reports."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_details() -> dict:
    """Family, model and stepping, clock [MHz], cache size (as /proc/cpuinfo gives it:
    on AMD the L2 of a core) and vector extensions of the first CPU in /proc/cpuinfo ({}
    elsewhere).

    Machines of one model name can differ by a CPU generation and nearly a factor of two
    in speed (the flow solver's step: 8.0 and 4.7 M particle updates/s on two "AMD EPYC"
    machines a day apart); these tell them apart in the results.
    """
    wanted = {"cpu family": "family", "model": "model", "stepping": "stepping",
              "cpu mhz": "mhz", "cache size": "cache"}  # fmt: skip
    out: dict = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the first CPU only
                key, _, value = (part.strip() for part in line.partition(":"))
                key = key.lower()
                if key in wanted:
                    out[wanted[key]] = value
                elif key == "flags":
                    flags = set(value.split())
                    out["vector"] = [f for f in ("avx2", "fma", "avx512f") if f in flags]
    except OSError:
        return {}
    return out


def _memory_total_gb() -> float | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return round(int(line.split()[1]) / 2**20, 1)
    except OSError:
        pass
    return None


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, timeout=10, check=True
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.rstrip()  # keep leading blanks: `status --porcelain` columns


def load_average() -> list[float] | None:
    """1, 5 and 15 minute load averages (other work on the machine skews timings)."""
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def source_digest() -> str:
    """SHA-1 over the package's Python sources: names exactly the code that was measured."""
    digest = hashlib.sha1()
    for path in sorted((REPO / "blendxr").rglob("*.py")):
        digest.update(path.relative_to(REPO).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def cpu_pressure() -> dict | None:
    """Share of time runnable tasks waited for a CPU (Linux PSI), 10 s and 60 s averages."""
    try:
        with open("/proc/pressure/cpu") as f:
            some = f.readline().split()
    except OSError:
        return None
    values = dict(item.split("=") for item in some[1:] if "=" in item)
    return {k: float(values[k]) for k in ("avg10", "avg60") if k in values}


def cpu_stall_us() -> int | None:
    """Cumulative microseconds in which some runnable task waited for a CPU (Linux PSI)."""
    try:
        with open("/proc/pressure/cpu") as f:
            some = f.readline().split()
    except OSError:
        return None
    values = dict(item.split("=") for item in some[1:] if "=" in item)
    return int(values["total"]) if "total" in values else None


def _machine_busy_s() -> float | None:
    """CPU seconds all processes have used since boot (Linux /proc/stat), idle excluded."""
    try:
        with open("/proc/stat") as f:
            fields = [int(x) for x in f.readline().split()[1:9]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + fields[4]  # idle + iowait
    return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK")


def _own_cpu_s() -> float:
    """CPU seconds used by this process and its waited-for children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class Contention:
    """How much other work competed for the CPUs during a timed interval.

    ``other_cpu_share``: CPU time used by other processes over the interval, as a share of
    the machine (wall time x cores); 0 on an idle machine, 0.5 when others kept one of two
    cores busy. ``stall_share``: share of the interval in which some runnable task waited
    for a CPU (Linux PSI; includes this process's own threads competing with each other).
    Either is None where the system does not provide it.
    """

    def __enter__(self):
        self._busy, self._own = _machine_busy_s(), _own_cpu_s()
        self._stall = cpu_stall_us()
        self._wall = time.perf_counter()
        self.other_cpu_share = self.stall_share = None
        return self

    def __exit__(self, *exc):
        wall = time.perf_counter() - self._wall
        busy, own, stall = _machine_busy_s(), _own_cpu_s(), cpu_stall_us()
        if wall > 0 and busy is not None and self._busy is not None:
            other = (busy - self._busy) - (own - self._own)
            self.other_cpu_share = round(min(max(other / (wall * os.cpu_count()), 0.0), 1.0), 3)
        if wall > 0 and stall is not None and self._stall is not None:
            self.stall_share = round((stall - self._stall) / 1e6 / wall, 3)
        return False

    def as_dict(self) -> dict:
        return {"other_cpu_share": self.other_cpu_share, "cpu_stall_share": self.stall_share}


def wait_for_quiet(max_wait_s: float | None = None, threshold: float = 10.0) -> dict:
    """Wait (up to ``max_wait_s``) until CPU pressure over 10 s falls below ``threshold`` %.

    The wait defaults to the environment variable BLENDXR_BENCH_QUIET_WAIT (seconds,
    default 120); 0 disables it. Returns what happened, for the results file.
    """
    if max_wait_s is None:
        max_wait_s = float(os.environ.get("BLENDXR_BENCH_QUIET_WAIT", "120"))
    started = time.perf_counter()
    pressure = cpu_pressure()
    while pressure is not None and pressure.get("avg10", 0.0) >= threshold:
        waited = time.perf_counter() - started
        if waited >= max_wait_s:
            break
        if waited == 0 or int(waited) % 30 < 5:
            echo(f"waiting for a quiet machine: CPU pressure {pressure} ...")
        time.sleep(5.0)
        pressure = cpu_pressure()
    quiet = pressure is None or pressure.get("avg10", 0.0) < threshold
    return {
        "waited_s": round(time.perf_counter() - started, 1),
        "quiet": quiet,
        "cpu_pressure": pressure,
        "threshold_avg10_percent": threshold,
    }


def best_of(
    fn,
    *,
    min_runs: int = 1,
    max_runs: int = 4,
    budget_s: float = 120.0,
    other_ok: float = 0.1,
    quiet_wait_s: float = 30.0,
) -> dict:
    """Time ``fn()`` until one run was free of other work; keep the fastest.

    Runs at least ``min_runs`` times while their total stays within ``budget_s``, and
    more (up to ``max_runs``, within the budget) while other processes used more than
    ``other_ok`` of the machine in every run so far (on a shared machine they stall
    2-thread kernels badly); before such a retry it waits up to ``quiet_wait_s`` for a
    quiet machine.

    Returns a dict: ``result``, ``wall_s``, ``contention`` of the fastest run, and the
    ``walls`` and ``contentions`` of all runs.
    """
    runs = []
    while True:
        with Contention() as meter:
            started = time.perf_counter()
            result = fn()
            wall = time.perf_counter() - started
        runs.append((wall, meter.as_dict(), result))
        walls = [r[0] for r in runs]
        n, total = len(runs), sum(walls)
        clean = any(
            r[1]["other_cpu_share"] is None or r[1]["other_cpu_share"] < other_ok for r in runs
        )
        if n >= max_runs or total + wall > budget_s:
            break
        if n >= min_runs and clean:
            break
        if not clean:
            wait_for_quiet(quiet_wait_s)
    wall, contention, result = min(runs, key=lambda r: r[0])
    return {
        "result": result,
        "wall_s": wall,
        "contention": contention,
        "walls": walls,
        "contentions": [r[1] for r in runs],
    }


def machine() -> dict:
    """Describe the machine and software a measurement ran on."""
    import numba
    import numpy
    import xarray

    import blendxr

    try:
        layer = numba.threading_layer()  # known only once a parallel function has run
    except ValueError:
        layer = None
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:
        affinity = None
    status = _git("status", "--porcelain", "--untracked-files=no")
    # files of the project (not of the benchmarks) that differ from the commit
    modified = sorted(
        line[3:]
        for line in (status or "").splitlines()
        if line[3:] and not line[3:].startswith("benchmarks/")
    )
    return {
        "cpu_model": cpu_model(),
        "cpu": cpu_details(),
        "cores": os.cpu_count(),
        "cores_usable": affinity,
        "memory_gb": _memory_total_gb(),
        "numba_num_threads": numba.get_num_threads(),
        "numba_threading_layer": layer,
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "numba": numba.__version__,
        "xarray": xarray.__version__,
        "blendxr": blendxr.__version__,
        "git_commit": _git("rev-parse", "--short", "HEAD"),
        "git_tree_modified": bool(modified) if status is not None else None,
        "git_modified_files": modified,
        "package_source_sha1": source_digest(),
        "platform": platform.platform(),
        "date": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "load_average_at_start": load_average(),
        "cpu_pressure_at_start": cpu_pressure(),
    }


def machine_line(info: dict) -> str:
    cpu = info.get("cpu") or {}
    detail = ""
    if cpu:
        detail = (
            f" (family {cpu.get('family')} model {cpu.get('model')}, "
            f"{float(cpu.get('mhz', 'nan')):.0f} MHz, {'/'.join(cpu.get('vector', []))})"
        )
    return (
        f"{info['cpu_model']}{detail}, {info['cores']} cores, numba {info['numba']} with "
        f"{info['numba_num_threads']} threads ({info['numba_threading_layer']}), "
        f"Python {info['python']}, NumPy {info['numpy']}, blendxr {info['blendxr']} "
        f"({info['git_commit']}{', modified tree' if info['git_tree_modified'] else ''}), "
        f"{info['date']}, load average {info['load_average_at_start']}, "
        f"CPU pressure {info['cpu_pressure_at_start']}"
    )


def write_atomic(path: Path, data: bytes | str) -> Path:
    """Write a file through a temporary sibling and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    mode = "wb" if isinstance(data, bytes) else "w"
    with open(tmp, mode) as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def portable(text: str) -> str:
    """``text`` with this checkout's and the flow cache's folders written as
    ``$BLENDXR_CACHE`` and ``.``: committed results must not name the machine's paths."""
    cache = str(flow_cache().resolve())
    text = re.sub(r"[^\s\"'(]*/runs/cache", "$BLENDXR_CACHE", text.replace(cache, "$BLENDXR_CACHE"))
    return text.replace(str(REPO.resolve()), ".")


def write_json(name: str, payload: dict, directory: Path | None = None) -> Path:
    """Write ``<directory>/<name>.json`` atomically (default directory: ``results/``),
    with the machine's folders made portable."""
    text = json.dumps(payload, indent=2, sort_keys=False, default=_to_builtin) + "\n"
    return write_atomic(Path(directory or RESULTS) / f"{name}.json", portable(text))


def cpu_label(info: dict | None) -> str:
    """A short name of a machine's processor, such as ``AMD EPYC 25/17``."""
    if not info:
        return ""
    cpu = info.get("cpu") or {}
    model = f" {cpu.get('family')}/{cpu.get('model')}" if cpu.get("family") else ""
    return f"{info.get('cpu_model', '?')}{model}"


def _with_cpu(cases: dict, info: dict | None) -> dict:
    """``cases`` with ``"cpu"`` set (from ``info``) on those that lack it."""
    label = cpu_label(info)
    return {k: v if "cpu" in v or not label else {**v, "cpu": label} for k, v in cases.items()}


def merge_cases(name: str, new: dict, report, directory: Path | None = None) -> dict:
    """Merge ``new["cases"]`` into the results ``name`` under a lock, rewrite its JSON and
    its table (``report(cases, machine)``, a Markdown string) and return the merged payload.

    Benchmarks whose cases run one at a time (``--case``) use it, so that two invocations
    can share the machine and the file.
    """
    directory = RESULTS if directory is None else Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / f".{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        path = directory / f"{name}.json"
        old = json.loads(path.read_text()) if path.exists() else {}
        # the payload's machine is the latest run's; each case keeps the processor it ran
        # on, so that a table merged from several machines says which time is whose
        old_cases = _with_cpu(old.get("cases", {}), old.get("machine"))
        cases = {**old_cases, **_with_cpu(new["cases"], new.get("machine"))}
        payload = {**old, **new, "cases": cases}
        write_json(name, payload, directory)
        write_atomic(directory / f"{name}.md", report(cases, payload["machine"]))
    return payload


def run_cases(name: str, description: str, cases, run_case, report, summary) -> dict:
    """The main of a benchmark whose cases run one at a time: ``--case NAME`` (repeatable,
    default all of ``cases``); each case's result ``run_case(case)`` is echoed as
    ``summary(case, result)`` and merged into the results ``name`` (:func:`merge_cases`),
    then the whole table is printed. Returns the merged payload."""
    import argparse

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--case", action="append", choices=list(cases),
                        help="run this case (repeatable; default: all)")  # fmt: skip
    parser.add_argument("--report", action="store_true",
                        help="only rewrite the table from the JSON, running nothing")  # fmt: skip
    args = parser.parse_args()
    if args.report:
        payload = json.loads((RESULTS / f"{name}.json").read_text())
        write_atomic(RESULTS / f"{name}.md", report(payload["cases"], payload["machine"]))
        echo(report(payload["cases"], payload["machine"]))
        return payload
    info = machine()
    echo(f"machine: {machine_line(info)}")
    for case in args.case or list(cases):
        result = run_case(case)
        echo(summary(case, result))
        payload = merge_cases(name, {"machine": info, "cases": {case: result}}, report)
    echo()
    echo(report(payload["cases"], info))
    return payload


def _to_builtin(value):
    import numpy as np

    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot serialise {type(value).__name__}")


def percent_xyz(d: dict) -> str:
    """``"x% / y% / z%"`` of a dict with the keys vx, vy, vz (eq. (30) figures)."""
    return " / ".join(f"{d[c]:.1%}" for c in ("vx", "vy", "vz"))


def table(headers: list[str], rows: list[list], align: str | None = None) -> str:
    """A Markdown table (also readable as plain text)."""
    cells = [[str(h) for h in headers]] + [[_fmt(v) for v in row] for row in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    align = align or "l" + "r" * (len(headers) - 1)
    lines = []
    for n, row in enumerate(cells):
        padded = [
            c.ljust(w) if a == "l" else c.rjust(w)
            for c, w, a in zip(row, widths, align, strict=True)
        ]
        lines.append("| " + " | ".join(padded) + " |")
        if n == 0:
            rule = [
                ":" + "-" * (w - 1) if a == "l" else "-" * (w - 1) + ":"
                for w, a in zip(widths, align, strict=True)
            ]
            lines.append("| " + " | ".join(rule) + " |")
    return "\n".join(lines)


def _fmt(value) -> str:
    if isinstance(value, float):
        if value != value:  # NaN
            return "n/a"
        if value == 0:
            return "0"
        if abs(value) >= 1e5 or abs(value) < 1e-3:
            return f"{value:.3e}"
        if abs(value) >= 100:
            return f"{value:.1f}"
        return f"{value:.3g}"
    return str(value)


def echo(*args) -> None:
    print(*args, flush=True)
    sys.stdout.flush()


def sweep_report(title: str, info: dict, result, headers: list[str], rows: list[list]) -> str:
    """The Markdown page of a sweep benchmark: title, machine, what the sweep did, table."""
    from blendxr.sweep import summary_line

    return "\n".join(
        [
            f"# {title}",
            "",
            f"Machine: {machine_line(info)}",
            f"Sweep: {summary_line(result)}.",
            "",
            table(headers, rows),
            "",
        ]  # fmt: skip
    )


def _halving_differences(values: list[float]) -> tuple[float, float] | None:
    """The two successive differences of three values on halving cells, or None when
    there are not three values or the sequence is flat or not monotone."""
    if len(values) != 3:
        return None
    d1, d2 = values[1] - values[0], values[2] - values[1]
    if d1 == 0 or d2 == 0 or d1 * d2 < 0:
        return None
    return d1, d2


def three_cell_order(values: list[float]) -> str:
    """Observed order of convergence of three values on cells halving each time, as text:
    "" when it cannot be read, "none (not monotone)" when the values turn back."""
    diffs = _halving_differences(values)
    if diffs is None:
        if len(values) == 3 and (values[1] - values[0]) * (values[2] - values[1]) < 0:
            return "none (not monotone)"
        return ""
    return f"{math.log2(abs(diffs[0] / diffs[1])):.2f}"


def richardson_limit(values: list[float]) -> float:
    """The h → 0 limit of three values on halving cells at their observed order
    (Richardson extrapolation); NaN where the values are not monotone or the observed
    order is not positive (the differences do not shrink), since no limit can be read."""
    diffs = _halving_differences(values)
    if diffs is None:
        return float("nan")
    ratio = diffs[0] / diffs[1]
    if ratio <= 1.0:
        return float("nan")
    return float(values[2] + diffs[1] / (ratio - 1.0))
