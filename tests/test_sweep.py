"""bx.sweep on dask.distributed: the same answers as the cases run one by one, each flow
solved once, resumption from the store, failures recorded."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

import blendxr as bx
from blendxr.sweep import case_id, sweep_cases

pytestmark = pytest.mark.slow

#: a drum whose flow the solver makes in about a second, mixed on a coarse grid
TINY = {
    "flow.cell": 0.02,
    "solver.settle_time": 0.1,
    "mixing.revolutions": 0.5,
    "numerics.cells": 24,
}


@pytest.fixture(scope="module")
def client():
    from dask.distributed import Client, LocalCluster

    with (
        LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            env={"NUMBA_NUM_THREADS": "1"},
        ) as cluster,
        Client(cluster) as c,
    ):
        yield c


@pytest.fixture()
def base():
    return bx.load_scene("drum-2d-mpm", TINY)


def test_cases_of_a_grid_and_of_a_list():
    cases, grid = sweep_cases({"mixing.k1": [0, 0.01], "numerics.scheme": ["lax-wendroff"]})
    assert cases == [
        {"mixing.k1": 0, "numerics.scheme": "lax-wendroff"},
        {"mixing.k1": 0.01, "numerics.scheme": "lax-wendroff"},
    ]
    assert grid == {"mixing.k1": [0, 0.01], "numerics.scheme": ["lax-wendroff"]}
    listed, none = sweep_cases([{"mixing.k1": 0.0}, {"numerics.cells": 30}])
    assert none is None and len(listed) == 2
    assert case_id({"mixing.k1": 0}) == case_id({"mixing.k1": 0.0})
    with pytest.raises(ValueError, match="twice"):
        sweep_cases({"mixing.k1": [0.01, 0.01]})
    with pytest.raises(ValueError, match="no values"):
        sweep_cases({"mixing.k1": []})


def test_a_bad_value_is_refused_before_anything_runs(base, tmp_path):
    with pytest.raises(bx.SceneError, match="mixing.k1"):
        bx.sweep(base, {"mixing.k1": [0.01, -1.0]}, store=tmp_path / "s", client=object())


def test_sweep_equals_the_cases_run_one_by_one_and_solves_each_flow_once(client, base, tmp_path):
    cache = tmp_path / "cache"
    vary = {"mixing.k1": [0.0, 0.02], "operation.rpm": [20.0, 30.0]}
    result = bx.sweep(base, vary, client=client, store=tmp_path / "store", cache=cache)
    assert result.sizes["mixing.k1"] == 2 and result.sizes["operation.rpm"] == 2
    assert (result["status"] == "ok").all()
    # rpm changes the flow, k1 does not: two flows for four cases
    assert result.attrs["flows_solved"] == 2
    assert len(list((cache / "flows").glob("*.nc"))) == 2
    for k1 in vary["mixing.k1"]:
        for rpm in vary["operation.rpm"]:
            scene = bx.load_scene(base, {"mixing.k1": k1, "operation.rpm": rpm})
            flow, source = bx.scene_flow(scene, cache=cache)
            assert source.cache == "hit"
            alone = bx.mix(flow, scene, progress=False)
            point = result.sel({"mixing.k1": k1, "operation.rpm": rpm})
            rsd = point["rsd"].sel(revolution=alone["revolution"].values)
            np.testing.assert_array_equal(rsd.values, alone["rsd"].values)


def test_a_killed_sweep_resumes_from_its_store(client, base, tmp_path):
    store = tmp_path / "store"
    vary = {"mixing.k1": [0.0, 0.01, 0.02]}
    first = bx.sweep(base, vary, client=client, store=store, cache=tmp_path / "cache")
    assert first.attrs["cases_run"] == 3
    # as if killed before the last case was written
    lost = store / f"case-{case_id({'mixing.k1': 0.02})}.nc"
    lost.unlink()
    again = bx.sweep(base, vary, client=client, store=store, cache=tmp_path / "cache")
    assert again.attrs["cases_run"] == 1 and again.attrs["cases_from_store"] == 2
    assert again.attrs["flows_solved"] == 0
    for name in ("rsd", "revolutions_to_rsd", "final_rsd", "status"):
        np.testing.assert_array_equal(again[name].values, first[name].values)


def test_a_failing_case_is_recorded_and_the_others_run(client, base, tmp_path):
    cases = [
        {"mixing.k1": 0.01},
        # refused when the run plans its memory (not by the scene's schema)
        {"mixing.k1": 0.01, "numerics.cells": 4000, "numerics.memory_budget_mb": 1},
    ]
    result = bx.sweep(base, cases, client=client, store=tmp_path / "s", cache=tmp_path / "c")
    assert list(result["status"].values) == ["ok", "failed"]
    assert "memory" in str(result["error"].values[1])
    assert np.isfinite(result["final_rsd"].values[0])
    assert np.isnan(result["final_rsd"].values[1])
    # recorded in the store: not run again
    again = bx.sweep(base, cases, client=client, store=tmp_path / "s", cache=tmp_path / "c")
    assert again.attrs["cases_run"] == 0
    assert list(again["status"].values) == ["ok", "failed"]


def test_shell_sweep_on_its_own_local_cluster(tmp_path, capsys, monkeypatch):
    from blendxr.cli import main

    monkeypatch.setenv("BLENDXR_CACHE", str(tmp_path / "cache"))
    sets = [arg for key, value in TINY.items() for arg in ("--set", f"{key}={value}")]
    argv = ["sweep", "drum-2d-mpm", *sets, "--vary", "mixing.k1=0,0.01", "--workers", "1"]
    status = main([*argv, "-o", str(tmp_path / "out"), "-q"])
    printed = capsys.readouterr().out
    assert status == 0, printed
    assert "2 cases: 2 run, 0 from the store, 1 flows solved" in printed
    with xr.open_dataset(tmp_path / "out" / "sweep.nc") as ds:
        assert list(ds["mixing.k1"].values) == [0.0, 0.01]
        assert (ds["status"] == "ok").all()
    # a bad --vary is one line and status 2
    assert main(["sweep", "drum-2d-mpm", "--vary", "mixing.k1"]) == 2


def test_cases_reading_a_lazy_flow_file_finish(client, tmp_path):
    """More cases than workers, each reading a many-phase flow file lazily: a case's
    reads stay in its own thread (they once went back to the cluster as sub-tasks and
    the cases holding every worker's thread waited on them for ever)."""
    path = tmp_path / "swirl.nc"
    bx.write_dataset(bx.flows.swirl(ndim=2, cells=16, n_phases=24, rpm=10.0, size=0.2), path)
    base = bx.load_scene(
        "swirl-2d",
        {"flow.source": "file", "flow.path": str(path), "mixing.revolutions": 0.5,
         "numerics.cells": 24, "mixing.snapshots": [0, 0.5]},
    )  # fmt: skip
    vary = {"mixing.k1": [0.0, 0.01, 0.02, 0.05, 0.1]}
    result = bx.sweep(base, vary, client=client, store=tmp_path / "s", cache=tmp_path / "c")
    assert (result["status"] == "ok").all()
    assert result.attrs["flows_solved"] == 0
    # more diffusion mixes more
    final = result["final_rsd"].values
    assert np.all(np.diff(final) < 0), final
