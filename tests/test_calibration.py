"""Calibration of k1 against a measured curve (paper §5.2, Figs. 7–8).

The "measurements" are the model's own curve at a known k1, so the answer is known. The
drum is small (32 flow cells, 72 ADE cells). At that resolution the scheme's numerical
diffusion is far larger than eq. (5)'s at the paper's k1 ~ 0.01, so k1 in the paper's
range hardly moves the curve beyond the noise. The tests work at k1 ~ 0.5, where k1 moves
the curve clearly; the calibration does not depend on k1's scale.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import xarray as xr

import blendxr as bx
from blendxr.studies import (
    CalibrationWarning,
    calibrate_k1,
    calibration_figure,
    parabola_minimum,
    read_curve,
)

K1_TRUE = 0.47  # between grid points, and off the bracket's midpoint
GRID = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0, 1.2)
# noise-free: the parabola's error on the V-shaped cost scales with the spacing
FINE_GRID = (0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
NOISE = 0.02  # relative, Gaussian
SCENE = {"flow.parameters.cells": 32, "numerics.cells": 72}


@pytest.fixture(scope="module")
def drum():
    """Scene, flow and the noise-free curves at K1_TRUE (records every 1/16 revolution)."""
    scene = bx.load_scene("drum-2d", SCENE)
    flow = bx.scene_flow(scene)[0]
    truth = bx.mix(flow, scene, k1=K1_TRUE, revolutions=1.5, output_every=0.0625, progress=False)
    # a measurement cannot fall below the random mixture: the clean curve is clamped too
    floor = truth.attrs["random_mixture_intensity"]
    clean = truth["intensity"].clip(min=floor)
    return scene, flow, truth, clean


@pytest.fixture(scope="module")
def noisy(drum):
    scene, flow, _, clean = drum
    rng = np.random.default_rng(2024)
    measured = clean * (1 + NOISE * rng.standard_normal(clean.size))
    return measured, calibrate_k1(measured, scene, flow, k1=GRID)


@pytest.fixture(scope="module")
def clean_result(drum):
    scene, flow, _, clean = drum
    return calibrate_k1(clean, scene, flow, k1=FINE_GRID)


def _worst_v_bias(x, cost) -> float:
    """The largest error of the parabola's vertex on a V-shaped cost, over every truth
    position between the lowest grid point's neighbours.

    The noise-free cost sum |m_i(k1) - m_i(k1*)| is a V with a kink at k1*, not a
    parabola; its slopes are taken from the chords outside the bracket.
    """
    x, cost = np.asarray(x), np.asarray(cost)
    j = int(np.argmin(cost))
    left = (cost[j - 2] - cost[j - 1]) / (x[j - 1] - x[j - 2])
    right = (cost[j + 2] - cost[j + 1]) / (x[j + 2] - x[j + 1])
    worst = 0.0
    for t in np.linspace(x[j - 1], x[j + 1], 2001)[1:-1]:
        v = np.where(x < t, left * (t - x), right * (x - t))
        worst = max(worst, abs(parabola_minimum(x, v)[0] - t))
    return worst


# ----------------------------------------------------------------------------- recovery


def test_noise_free_curve_recovers_k1_within_the_parabolas_bias_on_a_v(clean_result):
    a = clean_result.attrs
    bound = _worst_v_bias(FINE_GRID, clean_result["cost"].values)
    assert a["grid_best_k1"] == 0.5 and a["refined"] == 1 and a["at_grid_edge"] == 0
    assert abs(a["best_k1"] - K1_TRUE) <= bound
    # the refined run fits better than any grid point
    assert a["best_cost_source"] == "run"
    assert a["best_cost"] < clean_result["cost"].min()


def test_noisy_curve_recovers_k1_within_the_estimators_own_spread(drum, noisy, clean_result):
    """The tolerance is the 99.5 % quantile of the error of this very estimator (grid
    costs, then the parabola) over 4000 noise draws at 2 %: the model curves on the grid
    do not depend on the measurement, so each draw's costs follow from ``model``."""
    _, _, _, clean = drum
    measured, result = noisy
    model = result["model"].values
    rng = np.random.default_rng(7)
    draws = clean.values * (1 + NOISE * rng.standard_normal((4000, clean.size)))
    costs = np.abs(model[None] - draws[:, None]).sum(axis=-1)
    errors = [abs(parabola_minimum(GRID, c)[0] - K1_TRUE) for c in costs]
    tolerance = float(np.quantile(errors, 0.995))
    a = result.attrs
    assert abs(a["parabola_k1"] - K1_TRUE) <= tolerance
    assert abs(a["best_k1"] - K1_TRUE) <= tolerance
    # the calibration is informative (well inside the grid's range), and without noise
    # on a finer grid the recovery is tighter: its bound is below the noisy tolerance
    assert tolerance < 0.25 * K1_TRUE
    assert _worst_v_bias(FINE_GRID, clean_result["cost"].values) < tolerance
    assert np.allclose(result["measured"].values, measured.values)


def test_cost_is_the_summed_absolute_difference(drum, noisy):
    _, _, truth, _ = drum
    _, result = noisy
    by_hand = np.abs(result["model"].values - result["measured"].values[None]).sum(axis=1)
    np.testing.assert_allclose(result["cost"].values, by_hand, rtol=1e-13)
    fitted = np.abs(result["fitted"].values - result["measured"].values).sum()
    assert result.attrs["best_cost"] == pytest.approx(fitted, rel=1e-13)
    # the curves are clamped at the floor, and the runs stopped once they reached it
    floor = result.attrs["floor"]
    cells_per_side = truth.attrs["sampling_cell"] / truth.attrs["d"]
    assert floor == pytest.approx(1 / cells_per_side**2, rel=1e-12)  # 2-D: I_R = 1/N
    assert np.all(result["model"].values >= floor)
    assert np.all(result["run_revolutions"].values < result["revolution"].values[-1])
    for name in ("cost", "measured", "fitted", "model", "k1", "revolution"):
        assert result[name].attrs["units"] == "1" and result[name].attrs["long_name"]


def test_stopping_at_the_floor_gives_the_clamped_full_curve(drum):
    scene, flow, _, clean = drum
    grid = (0.2, 0.4, 0.8)
    stopped = calibrate_k1(clean, scene, flow, k1=grid, refine=False)
    full = calibrate_k1(clean, scene, flow, k1=grid, floor=False, refine=False)
    assert math.isnan(full.attrs["floor"])
    np.testing.assert_allclose(full["run_revolutions"].values, 1.5)
    assert np.all(stopped["run_revolutions"].values < 1.5)
    # the measured revolutions are on the runs' records, so no interpolation is involved
    clamped = np.maximum(full["model"].values, stopped.attrs["floor"])
    np.testing.assert_allclose(stopped["model"].values, clamped, rtol=1e-12)
    # refine=False: the parabola's k1 is reported, the fitted curve is the grid's best
    a = stopped.attrs
    assert a["best_k1"] == a["parabola_k1"] and a["refine_run"] == 0
    assert a["best_cost_source"] == "parabola (not run)" and a["fitted_k1"] == a["grid_best_k1"]


def test_parabola_refinement_is_exact_on_a_quadratic():
    x = np.array([0.0, 0.0025, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03])
    vertex, depth = 0.0123, 0.7
    best, value, refined, at_edge = parabola_minimum(x, 3e3 * (x - vertex) ** 2 + depth)
    assert best == pytest.approx(vertex, rel=1e-12)
    assert value == pytest.approx(depth, rel=1e-12)
    assert refined and not at_edge
    assert parabola_minimum(x, -x) == (0.03, -0.03, False, True)
    assert parabola_minimum(x, np.ones_like(x))[2:] == (False, True)
    assert parabola_minimum([0, 1, 2], [1, 1, 1])[2:] == (False, True)


def test_a_minimum_at_the_grid_edge_is_flagged(drum):
    scene, flow, _, clean = drum
    with pytest.warns(CalibrationWarning, match="lower end of the k1 grid"):
        result = calibrate_k1(clean, scene, flow, k1=[1.2, 0.8, 1.0])
    a = result.attrs
    np.testing.assert_array_equal(result["k1"].values, [0.8, 1.0, 1.2])  # sorted
    assert a["at_grid_edge"] == 1 and a["refined"] == 0 and a["refine_run"] == 0
    assert a["best_k1"] == 0.8 == a["grid_best_k1"] and "widen" in a["note"]


# ----------------------------------------------------------------------------- input


def test_csv_input_and_metric_from_header(tmp_path, drum):
    scene, _, truth, _ = drum
    path = tmp_path / "drum.csv"
    path.write_text("revolution,intensity\n0.5,0.2\n0,0.95\n\n1.0,0.06\n")
    curve = read_curve(path)
    assert curve.name == "intensity" and curve.dims == ("revolution",)
    np.testing.assert_array_equal(curve["revolution"].values, [0.0, 0.5, 1.0])  # sorted
    np.testing.assert_array_equal(curve.values, [0.95, 0.2, 0.06])
    # an RSD curve: the header sets the metric, the floor and the stop are the RSD's
    rsd = truth["rsd"].isel(time=slice(0, 13, 2))
    path = tmp_path / "rsd.csv"
    lines = [
        f"{r:.17g},{v:.17g}" for r, v in zip(rsd["revolution"].values, rsd.values, strict=True)
    ]
    path.write_text("Revolutions, RSD\n" + "\n".join(lines) + "\n")
    result = calibrate_k1(path, scene, k1=(0.2, 0.4, 0.8), refine=False)  # the scene's flow
    assert result.attrs["metric"] == "rsd"
    assert result.attrs["floor"] == pytest.approx(truth.attrs["random_mixture_rsd"])
    assert 0.2 < result.attrs["best_k1"] < 0.8
    fig = calibration_figure(result)
    assert len(fig.axes) == 2
    fig.savefig(tmp_path / "calibration.png")


def test_a_dataarray_needs_a_known_metric():
    values = xr.DataArray([0.9, 0.3], dims="revolution", coords={"revolution": [0.0, 1.0]})
    with pytest.raises(ValueError, match="cannot tell the metric"):
        read_curve(values)
    assert read_curve(values, metric="rsd").name == "rsd"
    with pytest.raises(ValueError, match="metric 'lacey' is unknown"):
        read_curve(values.rename("intensity"), metric="lacey")
    with pytest.raises(ValueError, match="named 'intensity' but metric='rsd'"):
        read_curve(values.rename("intensity"), metric="rsd")


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("rev,intensity\n0,1\n1,0.5\n", "header"),
        ("revolution,lacey\n0,1\n1,0.5\n", "column 'lacey' is unknown"),
        ("revolution,intensity,error\n0,1,0\n1,0.5,0\n", "header"),
        ("revolution,intensity\n0,1\n", "1 point"),
        ("revolution,intensity\n0,1\n1,nan\n", "non-finite"),
        ("revolution,intensity\n0,1\n1,x\n", "row 3"),
        ("revolution,intensity\n-1,1\n1,0.5\n", "negative revolution"),
        ("revolution,intensity\n0,1\n1,0.5\n1,0.4\n", "revolution 1 appears more than once"),
        ("", "empty file"),
    ],
)
def test_bad_measurements_are_refused_naming_the_problem(tmp_path, text, words):
    path = tmp_path / "m.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=words):
        calibrate_k1(path, "drum-2d", flow=xr.Dataset())


@pytest.mark.parametrize(
    ("grid", "words"),
    [
        ((0.005, 0.01), "at least 3 distinct"),
        ((0.01, 0.01, 0.02), "at least 3 distinct"),
        ((-0.01, 0.0, 0.01), "finite values >= 0"),
        ((0.0, math.inf, 0.01), "finite values >= 0"),
    ],
)
def test_bad_k1_grids_are_refused(grid, words):
    measured = xr.DataArray(
        [0.9, 0.3], dims="revolution", coords={"revolution": [0.0, 1.0]}, name="intensity"
    )
    with pytest.raises(ValueError, match=words):
        calibrate_k1(measured, "drum-2d", flow=xr.Dataset(), k1=grid)


def test_keywords_the_calibration_sets_itself_are_refused(drum):
    scene, flow, _, clean = drum
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(TypeError, match="stop_intensity"):
            calibrate_k1(clean, scene, flow, stop_intensity=0.1)
