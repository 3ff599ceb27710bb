"""Parameter studies on dask.distributed: :func:`sweep`.

A sweep is a set of cases, each a scene with some values set by dotted key. Cases whose
flow inputs agree (:func:`blendxr.pipeline.flow_key`) share one flow, solved once by one
task into the flow cache; their mixing tasks wait on it. Every case is written to the
store as it finishes (``case-<id>.nc``, or ``case-<id>.json`` for a case that failed), so
a sweep called again with the same store runs only what is missing. The result is one
Dataset: a dimension per swept key (a grid of values) or a ``case`` dimension (a list of
cases), with the RSD and intensity over revolutions, the revolutions to each RSD level,
wall times, and each case's status and error.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import math
import os
import time
import traceback
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from . import pipeline
from ._version import __version__
from .scene import SceneError, load_scene

__all__ = ["summary_line", "sweep", "sweep_cases"]

#: RSD levels whose revolutions each case reports
LEVELS = pipeline.RSD_LEVELS


# ----------------------------------------------------------------------------- cases


def sweep_cases(vary) -> tuple[list[dict], dict | None]:
    """The cases of a sweep and, for a grid, its axes.

    Parameters
    ----------
    vary : mapping or sequence of mappings
        ``{"mixing.k1": [0, 0.01], "numerics.cells": [40, 60]}``: every combination (a
        grid, in the order given); or ``[{"mixing.k1": 0}, {"mixing.k1": 0.01,
        "numerics.scheme": "lax-wendroff"}]``: these cases only.

    Returns
    -------
    cases : list of dict
        Dotted values of each case.
    grid : dict or None
        For a grid, ``{key: values}`` in order; None for a list of cases.
    """
    if isinstance(vary, Mapping):
        if not vary:
            raise ValueError("sweep: give at least one key to vary")
        grid = {}
        for key, values in vary.items():
            values = [values] if isinstance(values, str) or np.ndim(values) == 0 else list(values)
            if not values:
                raise ValueError(f"sweep: {key} has no values")
            if len({_canonical(v) for v in values}) != len(values):
                raise ValueError(f"sweep: {key} lists a value twice: {values}")
            grid[key] = values
        cases = [dict(zip(grid, combo, strict=True)) for combo in itertools.product(*grid.values())]
        return cases, grid
    if isinstance(vary, Sequence) and not isinstance(vary, str):
        cases = [dict(case) for case in vary]
        if not cases or not all(isinstance(c, Mapping) for c in vary):
            raise ValueError("sweep: a list of cases must hold at least one mapping of values")
        ids = [case_id(c) for c in cases]
        if len(set(ids)) != len(ids):
            raise ValueError("sweep: a case is listed twice")
        return cases, None
    raise TypeError("sweep: vary must be a mapping of keys to values or a list of cases")


def _canonical(value):
    if isinstance(value, bool | str) or value is None:
        return value
    if isinstance(value, int | float | np.number):
        return float(value)
    return json.dumps(value, sort_keys=True, default=str)


def case_id(values: Mapping) -> str:
    """A short, stable name of a case (a hash of its dotted values)."""
    text = json.dumps({k: _canonical(v) for k, v in sorted(values.items())}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------- tasks


def _limit_threads(threads: int) -> None:
    """Numba's threads for this task: a worker runs one case at a time on its share of
    the cores (parallel numba inside parallel dask workers would oversubscribe them)."""
    import numba

    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


@contextlib.contextmanager
def _in_task(threads: int):
    """A case's own reads in its own thread: lazy data a task computes (the flow file's
    phases, its validation) would otherwise go back to the cluster as sub-tasks, and
    cases waiting on their sub-tasks while holding every worker's thread never finish."""
    import dask

    _limit_threads(threads)
    with dask.config.set(scheduler="synchronous"):
        yield


def _flow_task(scene_toml: str, cache: str | None, threads: int) -> dict:
    """Solve (or find in the cache) one flow; what the mixing tasks need to open it."""
    scene = load_scene(scene_toml)
    started = time.perf_counter()
    try:
        with _in_task(threads):
            flow, source = pipeline.scene_flow(scene, cache=cache, progress=False)
    except Exception as exc:  # recorded with every case that needed this flow
        return {"error": f"flow: {type(exc).__name__}: {exc}", "trace": traceback.format_exc()}
    info = {
        "path": source.path,
        "cache": source.cache,
        "key": source.key,
        "kind": source.kind,
        "wall_s": time.perf_counter() - started,
        "solve_wall_s": float(flow.attrs.get("wall_time_s", math.nan)),
    }
    if source.kind != "analytic":
        flow.close()
    return info


def _mix_task(scene_toml: str, values: dict, flow: dict, store: str, threads: int) -> dict:
    """Mix one case through its flow and write it to the store; never raises."""
    name = case_id(values)
    started = time.perf_counter()
    try:
        if "error" in flow:
            raise RuntimeError(flow["error"])
        from . import mix

        scene = load_scene(scene_toml, values)
        with _in_task(threads):
            if flow["kind"] in ("solver", "file"):
                source = flow["path"]
            else:  # an analytic flow: made here, cheaply, not shipped between processes
                source, _ = pipeline.scene_flow(scene, progress=False)
            mixed = mix(source, scene, progress=False)
            result = _case_dataset(mixed, values, flow, time.perf_counter() - started)
            _write_case(result, Path(store) / f"case-{name}.nc", scene)
        return {"id": name, "status": "ok"}
    except Exception as exc:
        record = {
            "id": name,
            "status": "failed",
            "values": {k: _canonical(v) for k, v in values.items()},
            "error": f"{type(exc).__name__}: {exc}",
            "trace": traceback.format_exc(),
            "wall_s": time.perf_counter() - started,
            "blendxr_version": __version__,
        }
        from .io import write_json

        write_json(record, Path(store) / f"case-{name}.json")
        return record


def _case_dataset(mixed: xr.Dataset, values: dict, flow: dict, wall: float) -> xr.Dataset:
    summary = pipeline.mixing_summary(mixed, LEVELS)
    to_level = [summary["revolutions_to_rsd"][f"{lv:g}"] for lv in LEVELS]
    rev = np.asarray(mixed["revolution"].values, float)
    ds = xr.Dataset(
        {
            "rsd": ("revolution", np.asarray(mixed["rsd"].values, float)),
            "intensity": ("revolution", np.asarray(mixed["intensity"].values, float)),
            "revolutions_to_rsd": (
                "rsd_level",
                np.array([math.nan if v is None else v for v in to_level], float),
            ),
            "final_rsd": ((), float(summary["final_rsd"])),
            "mix_wall_time": ((), float(mixed.attrs.get("wall_time_s", math.nan))),
            "case_wall_time": ((), wall),
            "flow_wall_time": ((), float(flow.get("solve_wall_s", math.nan))),
        },
        coords={"revolution": rev, "rsd_level": np.asarray(LEVELS, float)},
        attrs={
            "case_values": json.dumps({k: _canonical(v) for k, v in values.items()}),
            "flow_key": flow.get("key") or "",
            "stopped_by": str(mixed.attrs.get("stopped_by", "")),
            "random_mixture_rsd": float(mixed.attrs.get("random_mixture_rsd", math.nan)),
        },
    )
    return _with_metadata(ds)


def _with_metadata(ds: xr.Dataset) -> xr.Dataset:
    meta = {
        "rsd": ("1", "relative standard deviation of concentration"),
        "intensity": ("1", "segregation intensity"),
        "revolutions_to_rsd": ("1", "revolutions until the RSD falls to the level"),
        "final_rsd": ("1", "RSD at the end of the run"),
        "mix_wall_time": ("s", "wall time of the mixing run"),
        "case_wall_time": ("s", "wall time of the case's task"),
        "flow_wall_time": ("s", "wall time of the flow's solve (when it was solved)"),
        "revolution": ("1", "revolutions of the vessel"),
        "rsd_level": ("1", "RSD level"),
    }
    for name, (units, long_name) in meta.items():
        if name in ds.variables:
            ds[name].attrs.update(units=units, long_name=long_name)
    return ds


def _write_case(ds: xr.Dataset, path: Path, scene) -> None:
    from .io import write_result

    write_result(ds, path, scene=scene, title="blendxr sweep case")


# ----------------------------------------------------------------------------- store


def _stored(store: Path, name: str) -> dict | None:
    """A finished case in the store: its dataset (ok) or its failure record."""
    nc, failed = store / f"case-{name}.nc", store / f"case-{name}.json"
    if nc.is_file():
        with xr.open_dataset(nc) as ds:
            return {"status": "ok", "data": ds.load()}
    if failed.is_file():
        return json.loads(failed.read_text())
    return None


# ----------------------------------------------------------------------------- sweep


@contextlib.contextmanager
def _cluster(client, workers: int | None, threads: int):
    """The given client, or a LocalCluster with one thread per worker (closed after)."""
    if client is not None:
        yield client
        return
    from dask.distributed import Client, LocalCluster

    n = workers or max(1, (os.cpu_count() or 1) // threads)
    env = {"NUMBA_NUM_THREADS": str(threads), "OMP_NUM_THREADS": "1"}
    with (
        LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            env=env,
        ) as cluster,
        Client(cluster) as own,
    ):
        yield own


def sweep(
    scene,
    vary,
    *,
    client=None,
    store: str | os.PathLike | None = None,
    workers: int | None = None,
    threads_per_case: int = 1,
    cache: str | os.PathLike | None = None,
    retry_failed: bool = False,
    progress: bool | None = None,
) -> xr.Dataset:
    """Run every case of a parameter study as dask tasks and gather the answers.

    Parameters
    ----------
    scene : Scene, str or mapping
        The base scene; each case sets some of its values by dotted key.
    vary : mapping or sequence of mappings
        A grid (``{"mixing.k1": [0, 0.01], ...}``, every combination) or a list of cases
        (see :func:`sweep_cases`). Every value is checked against the scene schema before
        anything runs.
    client : dask.distributed.Client, optional
        Where the tasks run. Default: a ``LocalCluster`` started here with ``workers``
        processes of one thread each, numba set to ``threads_per_case`` threads in them
        (and closed at the end).
    store : path, optional
        Folder of finished cases (created). A case found there is not run again; a
        killed sweep called again with the same store runs only what is missing.
        Default: a folder ``sweep-<hash>`` in the flow cache.
    workers : int, optional
        Processes of the LocalCluster (default: cores / threads_per_case).
    threads_per_case : int
        Numba threads of one case (default 1: parallel over cases, not within one).
    cache : path, optional
        Flow cache folder (default :func:`blendxr.pipeline.cache_folder`); shared
        flows are solved once into it.
    retry_failed : bool
        Run cases again whose failure is recorded in the store.
    progress : bool, optional
        A progress bar of cases done (default: when the output is a terminal).

    Returns
    -------
    xarray.Dataset
        A dimension per swept key (grid) or ``case`` (list), and ``revolution`` and
        ``rsd_level``: ``rsd``, ``intensity``, ``revolutions_to_rsd``, ``final_rsd``,
        ``mix_wall_time``, ``case_wall_time``, ``flow_wall_time``, ``status`` ("ok" or
        "failed") and ``error`` per case. Attributes: the cases run and found in the
        store, the flows solved, and the sweep's wall time.
    """
    from .driver import progress_bar

    base = load_scene(scene)
    cases, grid = sweep_cases(vary)
    scenes = {}
    for values in cases:
        try:
            scenes[case_id(values)] = load_scene(base, values)
        except SceneError as err:
            raise SceneError([f"sweep case {values}: {fault}" for fault in err.faults]) from None
    store = Path(store) if store is not None else _default_store(base, cases, cache)
    store.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    done = {}
    for values in cases:
        name = case_id(values)
        found = _stored(store, name)
        if found is not None and not (retry_failed and found["status"] == "failed"):
            done[name] = found
    todo = [v for v in cases if case_id(v) not in done]
    ran, solved = 0, 0
    if todo:
        groups = {case_id(v): _flow_group(scenes[case_id(v)]) for v in todo}
        folder = pipeline.cache_folder(cache) / "flows"
        solver_keys = {
            group for name, group in groups.items() if scenes[name]["flow"]["source"] == "solver"
        }
        missing = {key for key in solver_keys if not (folder / f"{key}.nc").is_file()}
        base_toml = base.to_toml()
        with _cluster(client, workers, threads_per_case) as cl:
            flows, futures = {}, []
            for values in todo:
                name = case_id(values)
                key = groups[name]
                if key not in flows:
                    flows[key] = cl.submit(_flow_task, scenes[name].to_toml(), _str(cache),
                                           threads_per_case, pure=False)  # fmt: skip
                futures.append(
                    cl.submit(
                        _mix_task,
                        base_toml,
                        values,
                        flows[key],
                        str(store),
                        threads_per_case,
                        pure=False,
                    )  # fmt: skip
                )
            bar = progress_bar(progress, len(futures), "cases", precision=0)
            dashboard = getattr(cl, "dashboard_link", None)
            if dashboard and bar.disable is False:
                bar.write(f"dask dashboard: {dashboard}")
            from dask.distributed import as_completed

            for future in as_completed(futures):
                record = future.result()
                ran += 1
                bar.update(1)
                bar.set_postfix_str(f"{record['status']} {record['id']}")
            bar.close()
            # counted from the cache, not from the tasks: a task dask ran twice (a worker
            # lost) finds its own flow the second time
            solved = sum(1 for key in missing if (folder / f"{key}.nc").is_file())
        for values in todo:
            name = case_id(values)
            done[name] = _stored(store, name) or {"status": "failed", "error": "no result"}
    result = _gather(cases, grid, done)
    result.attrs.update(
        {
            "cases": len(cases),
            "cases_run": ran,
            "cases_from_store": len(cases) - len(todo),
            "flows_solved": solved,
            "sweep_wall_time_s": time.perf_counter() - started,
            "store": str(store),
            "scene": base.to_toml(),
        }
    )
    return result


def summary_line(result: xr.Dataset) -> str:
    """One line of what a sweep did: cases run and found, flows solved, wall time."""
    a = result.attrs
    return (
        f"{a['cases']} cases: {a['cases_run']} run, {a['cases_from_store']} from the store, "
        f"{a['flows_solved']} flows solved, {a['sweep_wall_time_s']:.1f} s"
    )


def _str(path) -> str | None:
    return None if path is None else str(path)


def _flow_group(scene) -> str:
    """Cases with equal keys share one flow task: the cache key of a solver's flow, the
    flow section of another (prefixed, so the two never meet)."""
    if scene["flow"]["source"] == "solver":
        return pipeline.flow_key(scene)
    return "other:" + json.dumps(scene["flow"], sort_keys=True, default=str)


def _default_store(base, cases, cache) -> Path:
    text = json.dumps([base.to_toml(), sorted(case_id(c) for c in cases)])
    digest = hashlib.sha256(text.encode()).hexdigest()[:12]
    return pipeline.cache_folder(cache) / "sweeps" / f"sweep-{digest}"


def _gather(cases: list[dict], grid: dict | None, done: dict) -> xr.Dataset:
    """One Dataset of every case (NaN where a case failed)."""
    revs = sorted(
        {
            round(float(r), 9)
            for rec in done.values()
            if rec["status"] == "ok"
            for r in rec["data"]["revolution"].values
        }
    )
    rev_axis = np.asarray(revs, float)
    n_levels = len(LEVELS)
    shape = [len(v) for v in grid.values()] if grid is not None else [len(cases)]
    dims = list(grid) if grid is not None else ["case"]
    arrays = {
        "rsd": np.full((*shape, len(rev_axis)), np.nan),
        "intensity": np.full((*shape, len(rev_axis)), np.nan),
        "revolutions_to_rsd": np.full((*shape, n_levels), np.nan),
    }
    scalars = ("final_rsd", "mix_wall_time", "case_wall_time", "flow_wall_time")
    arrays.update({name: np.full(shape, np.nan) for name in scalars})
    status = np.full(shape, "missing", dtype=object)
    error = np.full(shape, "", dtype=object)
    for n, values in enumerate(cases):
        index = tuple(grid[k].index(values[k]) for k in grid) if grid is not None else (n,)
        rec = done[case_id(values)]
        status[index] = rec["status"]
        if rec["status"] != "ok":
            error[index] = rec.get("error", "")
            continue
        data = rec["data"]
        at = np.searchsorted(rev_axis, np.round(data["revolution"].values.astype(float), 9))
        arrays["rsd"][index][at] = data["rsd"].values
        arrays["intensity"][index][at] = data["intensity"].values
        arrays["revolutions_to_rsd"][index] = data["revolutions_to_rsd"].values
        for name in scalars:
            arrays[name][index] = float(data[name])
    ds = xr.Dataset(
        {
            "rsd": ((*dims, "revolution"), arrays["rsd"]),
            "intensity": ((*dims, "revolution"), arrays["intensity"]),
            "revolutions_to_rsd": ((*dims, "rsd_level"), arrays["revolutions_to_rsd"]),
            **{name: (dims, arrays[name]) for name in scalars},
            "status": (dims, status.astype(str)),
            "error": (dims, error.astype(str)),
        },
        coords={"revolution": rev_axis, "rsd_level": np.asarray(LEVELS, float)},
    )
    if grid is not None:
        for key, values in grid.items():
            ds = ds.assign_coords({key: (key, np.asarray(values))})
    else:
        keys = sorted({k for c in cases for k in c})
        for key in keys:
            column = [c.get(key) for c in cases]
            ds = ds.assign_coords({key: ("case", np.asarray(column, dtype=object).astype(str))})
        ds = ds.assign_coords(case=("case", [case_id(c) for c in cases]))
    ds["status"].attrs["long_name"] = "ok, failed (see error) or missing"
    ds["error"].attrs["long_name"] = "why a case failed"
    return _with_metadata(ds)
