"""The main job: scene values by dotted key, the flow cache, the report, the stop rule."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import blendxr as bx
from blendxr import pipeline
from blendxr.cli import main
from blendxr.scene import parse_assignment

# --------------------------------------------------------------------- dotted keys


@pytest.mark.parametrize(
    "text, key, value",
    [
        ("mixing.k1=0.02", "mixing.k1", 0.02),
        ("numerics.cells=64", "numerics.cells", 64),
        ("mixing.loading=side-side", "mixing.loading", "side-side"),
        ("numerics.cells=[40, 30]", "numerics.cells", [40, 30]),
        ("solver.lost_contact=false", "solver.lost_contact", False),
        ("mixing.stop_rsd=floor", "mixing.stop_rsd", "floor"),
    ],
)
def test_assignments_read_their_value_as_toml(text, key, value):
    assert parse_assignment(text) == (key, value)


def test_load_scene_sets_values_by_dotted_key_and_keeps_the_rest():
    base = bx.load_scene("tote-small")
    scene = bx.load_scene("tote-small", **{"mixing.k1": 0.02, "fill.fraction": 0.6})
    assert scene["mixing"]["k1"] == 0.02 and scene["fill"]["fraction"] == 0.6
    assert scene["flow"] == base["flow"] and scene["mixing"]["loading"] == "top-bottom"
    # a default-filled section is not frozen: a value set later still takes effect
    assert scene.with_values({"mixing.k1": 0.0})["mixing"]["k1"] == 0.0


@pytest.mark.parametrize(
    "values, words",
    [
        ({"mixing.k11": 0.1}, ["mixing.k11", "did you mean mixing.k1"]),
        ({"vessel.hopper_angel_deg": 45}, ["hopper_angel_deg", "hopper_angle_deg"]),
        ({"mixing.k1": -1}, ["mixing.k1", ">= 0"]),
        ({"numerics.scheme": "upwind"}, ["numerics.scheme", "finite-volume"]),
        ({"nosection.k1": 1}, ["nosection.k1", "not a scene key"]),
        # NaN passes every range comparison: refused before the ranges are checked
        ({"operation.rpm": math.nan}, ["operation.rpm = nan", "not a finite number"]),
        ({"solver.stiffness_scaling": math.inf}, ["solver.stiffness_scaling = inf"]),
        ({"mixing.snapshots": [1.0, -math.inf]}, ["mixing.snapshots.1 = -inf"]),
        ({"mixing.revolutions": 1e9}, ["mixing.revolutions", "<= 100000"]),
        ({"mixing.k1": 1e6}, ["mixing.k1", "<= 10"]),
    ],
)
def test_a_wrong_key_or_value_is_refused_naming_it(values, words):
    with pytest.raises(bx.SceneError) as err:
        bx.load_scene("tote-small", values)
    for word in words:
        assert word in str(err.value)


def test_a_solver_speed_above_the_critical_one_is_refused_with_the_limit():
    """Froude number 1 at the farthest wall: the drum of 150 mm centrifuges above
    sqrt(g / R) = 109.2 rpm (R = 75 mm)."""
    from blendxr.flow.solver import FlowSimulation

    critical = 60.0 / (2.0 * math.pi) * math.sqrt(9.81 / 0.075)
    with pytest.raises(bx.SceneError, match=f"<= {critical:.4g}"):
        FlowSimulation(bx.load_scene("drum-2d-mpm", **{"operation.rpm": 1.05 * critical}))


@pytest.mark.parametrize(
    "values, words",
    [
        ({"flow.parameters.omegga": 1}, ["flow.parameters.omegga", "rolling_drum", "allowed"]),
        ({"flow.parameters.fill_dept": 0.3}, ["did you mean flow.parameters.fill_depth"]),
        ({"flow.parameters.rpm": 5.0}, ["flow.parameters.rpm", "operation.rpm"]),
        ({"flow.cell": 0.01}, ["flow.cell", "solver's flows only"]),
        ({"solver.cell": 0.01}, ["solver section", "analytic flow rolling_drum"]),
    ],
)
def test_an_analytic_flow_refuses_values_it_would_ignore(values, words):
    scene = bx.load_scene("drum-2d", values)
    with pytest.raises(bx.SceneError) as err:
        pipeline.analytic_flow(scene)
    for word in words:
        assert word in str(err.value)


def test_an_analytic_flow_turns_at_the_scenes_rpm():
    scene = bx.load_scene("drum-2d", **{"operation.rpm": 7.5, "flow.parameters.cells": 24})
    flow = pipeline.analytic_flow(scene)
    assert flow.attrs["rpm"] == 7.5


def test_a_typo_in_a_scene_file_is_refused(tmp_path):
    path = tmp_path / "typo.toml"
    path.write_text('name = "typo"\n[vessel]\nkind = "tote"\nhopper_angel_deg = 45\n')
    with pytest.raises(bx.SceneError, match="did you mean vessel.hopper_angle_deg"):
        bx.load_scene(path)


def test_set_on_the_shell_changes_the_scene_and_refuses_bad_keys(capsys, tmp_path):
    assert main(["scene", "tote-small", "--set", "mixing.k1=0.03", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["mixing"]["k1"] == 0.03
    status = main(["mix", "swirl-2d", "-o", str(tmp_path), "-q", "--set", "mixing.loadng=axial"])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1 and "did you mean mixing.loading" in err


@pytest.mark.slow
def test_a_flag_given_as_zero_is_a_value_and_is_validated(capsys, tmp_path):
    status = main(["flow", "drum-2d-mpm", "-o", str(tmp_path), "-q", "--cell", "0"])
    err = capsys.readouterr().err
    assert status == 2 and "solver.cell" in err
    assert not (tmp_path / "flow.nc").exists()


# --------------------------------------------------------------------- cache key


@pytest.mark.parametrize(
    "key, value",
    [
        ("operation.rpm", 12.0),
        ("vessel.width", 0.2),
        ("material.friction_angle_deg", 30.0),
        ("fill.fraction", 0.5),
        ("flow.cell", 0.025),
        ("flow.phases", 6),
        ("solver.stiffness_scaling", 50.0),
    ],
)
def test_a_flow_input_changes_the_cache_key(key, value):
    assert pipeline.flow_key(bx.load_scene("tote-small", {key: value})) != pipeline.flow_key(
        "tote-small"
    )


@pytest.mark.parametrize(
    "key, value",
    [
        ("mixing.k1", 0.03),
        ("mixing.loading", "side-side"),
        ("mixing.revolutions", 3),
        ("numerics.cells", 40),
        ("numerics.scheme", "lax-wendroff"),
        ("name", "another-name"),
        ("description", "another text"),
    ],
)
def test_a_mixing_input_keeps_the_cache_key(key, value):
    assert pipeline.flow_key(bx.load_scene("tote-small", {key: value})) == pipeline.flow_key(
        "tote-small"
    )


def test_the_paper_cases_of_one_fill_share_their_flow_and_the_version_is_in_the_key(
    monkeypatch,
):
    assert pipeline.flow_key("tote-40-top-bottom") == pipeline.flow_key("tote-40-side-side")
    assert pipeline.flow_key("tote-40-top-bottom") != pipeline.flow_key("tote-60-top-bottom")
    before = pipeline.flow_key("tote-small")
    monkeypatch.setattr(pipeline, "__version__", "0.0.0-other")
    assert pipeline.flow_key("tote-small") != before
    monkeypatch.undo()
    assert pipeline.flow_key("tote-small") == before
    # a changed solver (a development install between releases) changes the key too
    monkeypatch.setattr(pipeline, "solver_source_digest", lambda: "edited")
    assert pipeline.flow_key("tote-small") != before


def test_the_cache_folder_follows_argument_then_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("BLENDXR_CACHE", str(tmp_path / "env"))
    assert pipeline.cache_folder() == tmp_path / "env"
    assert pipeline.cache_folder(tmp_path / "arg") == tmp_path / "arg"
    monkeypatch.delenv("BLENDXR_CACHE")
    assert "blendxr" in str(pipeline.cache_folder())


# --------------------------------------------------------------------- report


def test_revolutions_to_a_level_is_exact_on_an_exponential_decay():
    rate = 0.7
    rev = np.arange(0, 10.01, 0.25)
    rsd = np.exp(-rate * rev)
    for level in (0.2, 0.1, 0.05):
        got = pipeline.revolutions_to_level(rev, rsd, level)
        assert got == pytest.approx(math.log(1 / level) / rate, rel=1e-12)


def test_revolutions_to_a_level_not_reached_first_value_and_gaps():
    rev = np.array([0.0, 1.0, 2.0, 3.0])
    assert pipeline.revolutions_to_level(rev, [1.0, 0.5, 0.3, 0.2], 0.1) is None
    assert pipeline.revolutions_to_level(rev, [0.05, 0.04, 0.03, 0.02], 0.1) == 0.0
    # a NaN record is skipped: the crossing lies between revolutions 1 and 3
    got = pipeline.revolutions_to_level(rev, [1.0, 0.4, np.nan, 0.1], 0.2)
    assert got == pytest.approx(1 + 2 * math.log(2) / math.log(4))
    # the first crossing counts, not a later one after a rise
    assert pipeline.revolutions_to_level(rev, [1.0, 0.1, 0.3, 0.05], 0.1) == 1.0


def _small_drum_scene(**values):
    base = {
        "flow.parameters.cells": 32,
        "numerics.cells": 36,
        "mixing.revolutions": 3,
        "mixing.output_every": 0.25,
    }
    return bx.load_scene("drum-2d", {**base, **values})


@pytest.mark.slow
def test_the_stop_rule_stops_at_the_first_record_at_or_below_the_level():
    scene = _small_drum_scene(**{"mixing.stop_rsd": 0.3})
    mixed = bx.mix(bx.scene_flow(scene)[0], scene, progress=False)
    rsd = mixed["rsd"].values
    assert rsd[-1] <= 0.3 and np.all(rsd[:-1] > 0.3)
    assert mixed.attrs["stopped_by"].startswith("rsd")
    assert mixed["revolution"].values[-1] < 3
    # the run ends with a snapshot of its last state
    assert mixed["snapshot_revolution"].values[-1] == pytest.approx(mixed["revolution"].values[-1])


@pytest.mark.slow
def test_the_last_state_is_not_kept_twice_beside_a_planned_snapshot_a_rounding_away():
    from blendxr.ade.stepper import _Run, _settings_from

    scene = _small_drum_scene()
    flow = bx.scene_flow(scene)[0]
    run = _Run(flow, scene, _settings_from(scene, {"progress": False}))
    run.initialise()
    run.snapshots[0.5] = np.zeros(run.grid.shape)
    run.t = 0.5 * run.period * (1 + 4e-16)  # the clock a rounding past the planned 0.5
    run.keep_snapshot()
    assert list(run.snapshots) == [0.5]


@pytest.mark.slow
def test_a_stop_at_a_planned_snapshot_keeps_one_snapshot_there():
    planned = [0.25 * k for k in range(13)]  # every record is a planned snapshot
    scene = _small_drum_scene(**{"mixing.stop_rsd": 0.3, "mixing.snapshots": planned})
    mixed = bx.mix(bx.scene_flow(scene)[0], scene, progress=False)  # validated on return
    revs = mixed["snapshot_revolution"].values
    assert mixed.attrs["stopped_by"].startswith("rsd")
    assert np.all(np.diff(revs) > 0) and revs[-1] == pytest.approx(mixed["revolution"].values[-1])


@pytest.mark.slow
@pytest.mark.parametrize(
    "keyword, value",
    [("stop_rsd", -0.1), ("stop_rsd", "flor"), ("stop_intensity", 0), ("min_intensity_cells", 1)],
)
def test_mix_keywords_are_checked_against_the_scene_schema(keyword, value):
    scene = _small_drum_scene()
    flow = bx.scene_flow(scene)[0]
    with pytest.raises(bx.SceneError, match=f"mixing.{keyword}"):
        bx.mix(flow, scene, progress=False, **{keyword: value})


@pytest.mark.slow
def test_the_floor_stop_uses_the_random_mixture_of_the_sampling_cells():
    scene = _small_drum_scene(**{"mixing.stop_intensity": "floor", "mixing.revolutions": 6})
    mixed = bx.mix(bx.scene_flow(scene)[0], scene, progress=False)
    cell = mixed.attrs["sampling_cell"]
    floor = 1.0 / (cell / scene["material"]["particle_diameter"]) ** 2  # 2-D: N = (cell/d)^2
    assert mixed.attrs["random_mixture_intensity"] == pytest.approx(floor, rel=1e-12)
    intensity = mixed["intensity"].values
    assert intensity[-1] <= floor and np.all(intensity[:-1] > floor)
    assert "floor" in mixed.attrs["stopped_by"]
    mean = mixed.attrs["mean_c"]
    assert mixed.attrs["random_mixture_rsd"] == pytest.approx(
        math.sqrt(floor * (1 - mean) / mean), rel=1e-12
    )


@pytest.mark.slow
def test_sampling_cells_qualify_by_the_flows_fill():
    scene = _small_drum_scene(**{"mixing.revolutions": 2})
    flow = bx.scene_flow(scene)[0]
    mixed = bx.mix(flow, scene, progress=False, revolutions=2)
    # the steady flow's fill on the mixing grid, reduced independently: its sampling cells
    # holding >= 95 % material are the ones the run may count
    from blendxr.ade.grid import AdeGrid
    from blendxr.ade.phases import CyclicPhaseReader

    coords = [flow[d].values for d in ("x", "y")]
    h = [c[1] - c[0] for c in coords]
    grid = AdeGrid.covering(
        [c[0] - 0.5 * s for c, s in zip(coords, h, strict=True)],
        [c[-1] + 0.5 * s for c, s in zip(coords, h, strict=True)],
        scene["numerics"]["cells"],
    )
    reader = CyclicPhaseReader(flow, grid, None, memory_budget=2**28)
    fill = reader.get(0).fill
    reader.close()
    import xarray as xr

    da = xr.DataArray(fill, dims=("x", "y"), coords=dict(zip(("x", "y"), grid.coords, strict=True)))
    qualified = bx.metrics.sample_means(da, fill=da, cell=mixed.attrs["sampling_cell"])
    counts = mixed["intensity_cells"].values
    assert counts.max() <= int(qualified.notnull().sum())
    # the steady bed keeps its sampling cells: the count does not decay with the revolutions
    assert counts.min() >= 0.9 * counts.max()


@pytest.mark.slow
def test_run_writes_the_report_and_reuses_the_cached_flow(tmp_path):
    cache = tmp_path / "cache"

    def run(folder, **values):
        scene = bx.load_scene(
            "drum-2d-mpm", {"mixing.revolutions": 1, "numerics.cells": 32, **values}
        )
        return pipeline.run_scene(scene, tmp_path / folder, cache=cache, progress=False)

    first = run("a")
    assert first["flow_cache"]["state"] == "miss"
    for name in ("flow.nc", "mixing.nc", "report.json", "mixing.png", "snapshots.png"):
        assert (tmp_path / "a" / name).stat().st_size > 0
    assert not list((cache / "flows").glob("*.checkpoint"))
    again = run("b", **{"mixing.k1": 0.05})
    assert again["flow_cache"]["state"] == "hit"
    assert again["flow_cache"]["key"] == first["flow_cache"]["key"]
    other = run("c", **{"operation.rpm": 25.0})
    assert other["flow_cache"]["state"] == "miss"
    # the report agrees with the files it sits beside
    report = json.loads((tmp_path / "b" / "report.json").read_text())
    mixed = bx.open_mixing(tmp_path / "b" / "mixing.nc")
    assert report["mixing"]["k1"] == 0.05
    assert report["mixing"]["final_rsd"] == pytest.approx(float(mixed["rsd"][-1]), rel=1e-6)
    for level, r in report["mixing"]["revolutions_to_rsd"].items():
        assert r == pipeline.revolutions_to_level(
            mixed["revolution"].values, mixed["rsd"].values, float(level)
        )
    flow = bx.open_flow(tmp_path / "b" / "flow.nc")
    assert report["flow"]["fill_share"] == pytest.approx(
        flow.attrs["fill_volume_m3"] / flow.attrs["material_volume_m3"]
    )
    for stage in ("flow", "mixing", "report"):
        assert report["stages"][stage]["wall_s"] >= 0
        assert report["stages"][stage]["peak_memory_mb"] > 0


@pytest.mark.slow
def test_run_refuses_an_output_that_is_a_file_before_any_work(tmp_path, capsys):
    target = tmp_path / "taken"
    target.write_text("x")
    status = main(["run", "drum-2d-mpm", "-o", str(target), "-q", "--cache", str(tmp_path)])
    err = capsys.readouterr().err
    assert status == 2 and "existing file" in err
    assert not (tmp_path / "flows").exists()


@pytest.mark.slow
def test_calibrate_on_the_shell_prints_the_best_k1_and_writes_the_cost_plot(tmp_path, capsys):
    values = {"flow.parameters.cells": 32, "numerics.cells": 72}
    scene = bx.load_scene("drum-2d", values)
    truth = bx.mix(bx.scene_flow(scene)[0], scene, k1=0.5, revolutions=1.0, progress=False)
    floor = truth.attrs["random_mixture_intensity"]
    rows = [f"{r:g},{max(v, floor):.9g}" for r, v in zip(
        truth["revolution"].values, truth["intensity"].values, strict=True)]  # fmt: skip
    data = tmp_path / "measured.csv"
    data.write_text("revolution,intensity\n" + "\n".join(rows) + "\n")
    argv = ["calibrate", "drum-2d", str(data), "--k1", "0.2,0.4,0.6,0.8", "-o", str(tmp_path), "-q"]
    for key, value in values.items():
        argv += ["--set", f"{key}={value}"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    best = float(out.split("best k1 = ")[1].split()[0])
    # noise-free, the refined k1 lies within the bracket of the true value's grid points
    assert 0.4 <= best <= 0.6
    assert (tmp_path / "calibration.png").stat().st_size > 0
    import xarray as xr

    with xr.open_dataset(tmp_path / "calibration.nc") as ds:
        assert list(ds["k1"].values) == [0.2, 0.4, 0.6, 0.8]
        assert ds.attrs["best_k1"] == pytest.approx(best, rel=1e-3)


@pytest.mark.slow
def test_a_failed_run_leaves_the_previous_outputs_whole(tmp_path, monkeypatch):
    """Outputs are staged and renamed together: a failure while writing them (here the
    snapshot picture) keeps every file of the previous run and leaves no staged file."""
    from blendxr import plot

    values = {"flow.parameters.cells": 24, "numerics.cells": 24, "mixing.revolutions": 0.5}
    scene = bx.load_scene("swirl-2d", values)
    bx.run_scene(scene, tmp_path, progress=False)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(plot, "save_snapshot_figure", broken)
    with pytest.raises(OSError, match="disk full"):
        bx.run_scene(scene.with_values({"mixing.k1": 0.1}), tmp_path, progress=False)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_stale_temporaries_of_a_killed_write_are_removed_at_the_next_run(tmp_path):
    import os
    import time

    from blendxr.io import STALE_TEMPORARY_S

    old = tmp_path / ".mixing.nc.abc123.tmp"
    young = tmp_path / ".report.json.def456.staged.json"
    for path in (old, young):
        path.write_text("half")
    stamp = time.time() - 2 * STALE_TEMPORARY_S
    os.utime(old, (stamp, stamp))
    pipeline.check_output_folder(tmp_path)
    assert not old.exists() and young.exists()  # a young one may be a write under way
