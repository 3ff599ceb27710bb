"""Exact properties of the analytic flows (blendxr.flow.analytic)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from blendxr.flow.analytic import solid_body_rotation, swirl, uniform
from blendxr.schema import validate


def spacing(ds, axis):
    return float(ds[axis][1] - ds[axis][0])


def divergence(ds, phase=0):
    """Central-difference divergence on the cells whose neighbours all exist."""
    axes = [a for a in ("x", "y", "z") if a in ds.dims]
    inner = (slice(1, -1),) * len(axes)
    total = 0.0
    for k, axis in enumerate(axes):
        v = ds[f"v{axis}"].isel(rev_phase=phase).values
        upper = [slice(1, -1)] * len(axes)
        lower = [slice(1, -1)] * len(axes)
        upper[k], lower[k] = slice(2, None), slice(None, -2)
        total = total + (v[tuple(upper)] - v[tuple(lower)]) / (2 * spacing(ds, axis))
    assert total.shape == ds.vessel.values[inner].shape
    return total


def material_interior(ds, phase=0):
    """Cells with material whose every neighbour holds material too."""
    m = ds.fill.isel(rev_phase=phase).values > 0
    inner = m.copy()
    for axis in range(m.ndim):
        for shift in (1, -1):
            inner &= np.roll(m, shift, axis=axis)
    return inner[(slice(1, -1),) * m.ndim]


# ---------------------------------------------------------------------------------------
# Every flow: valid, with the right dimensions and recipe
# ---------------------------------------------------------------------------------------

FLOWS = [
    (uniform, {"velocity": (0.2, 0.1), "cells": 5}),
    (
        uniform,
        {"velocity": (0.2, 0.1, -0.3), "cells": (3, 4, 5), "extent": [(0, 1), (-1, 1), (2, 3)]},
    ),
    (swirl, {"ndim": 2, "cells": 6, "n_phases": 4}),
    (swirl, {"ndim": 3, "cells": 4, "n_phases": 3}),
    (solid_body_rotation, {"ndim": 2, "cells": 6}),
    (solid_body_rotation, {"ndim": 3, "cells": 6, "length": 0.15}),
    (solid_body_rotation, {"ndim": 2, "cells": 8, "fill_fraction": 0.3, "n_phases": 4}),
    (solid_body_rotation, {"ndim": 3, "cells": 6, "fill_fraction": 0.6, "n_phases": 3}),
]


@pytest.mark.parametrize("function, kwargs", FLOWS)
def test_every_flow_validates_and_has_its_dims(function, kwargs):
    ds = function(**kwargs)
    validate(ds)
    ndim = len(kwargs["velocity"]) if "velocity" in kwargs else kwargs["ndim"]
    if ndim == 2:
        assert "z" not in ds.dims and "z" not in ds.coords and "vz" not in ds
        assert ds.vx.dims == ("rev_phase", "x", "y")
    else:
        assert ds.vx.dims == ("rev_phase", "x", "y", "z") and "vz" in ds
    assert set(np.unique(ds.vessel.values)) <= {0, 1}
    assert ds.attrs["frame"] in ("vessel", "lab")
    assert ds.attrs["rpm"] > 0 and ds.attrs["gravity"] == 9.81
    recipe = json.loads(ds.attrs["analytic"])
    assert recipe["flow"] == function.__name__
    rebuilt = function(**{k: v for k, v in recipe.items() if k != "flow"})
    np.testing.assert_array_equal(rebuilt.vx.values, ds.vx.values)
    np.testing.assert_array_equal(rebuilt.fill.values, ds.fill.values)


# ---------------------------------------------------------------------------------------
# Uniform flow
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("velocity", [(0.3, -0.2), (0.1, 0.0, 0.5)])
def test_uniform_is_constant_and_full(velocity):
    ds = uniform(velocity, cells=4, n_phases=3)
    for name, value in zip(("vx", "vy", "vz"), velocity, strict=False):
        assert np.all(ds[name].values == value)
    assert np.all(ds.fill.values == 1.0) and np.all(ds.vessel.values == 1)
    assert ds.sizes["rev_phase"] == 3
    np.testing.assert_array_equal(ds.rev_phase.values, [0, 1 / 3, 2 / 3])


def test_uniform_grid_is_cell_centred():
    ds = uniform((1.0, 0.0), cells=(4, 2), extent=[(-1.0, 1.0), (0.0, 0.5)])
    np.testing.assert_allclose(ds.x.values, [-0.75, -0.25, 0.25, 0.75])
    np.testing.assert_allclose(ds.y.values, [0.125, 0.375])


# ---------------------------------------------------------------------------------------
# Swirl
# ---------------------------------------------------------------------------------------


def test_swirl_matches_the_formula():
    size, rpm, amplitude = 2.0, 30.0, 0.5
    ds = swirl(ndim=2, cells=(6, 8), n_phases=4, rpm=rpm, size=size, amplitude=amplitude)
    period = 60.0 / rpm
    xh, yh = np.meshgrid(ds.x.values / size, ds.y.values / size, indexing="ij")
    for k, phase in enumerate(ds.rev_phase.values):
        g = amplitude * size / period * math.cos(2 * math.pi * phase)
        u = np.sin(np.pi * xh) ** 2 * np.sin(2 * np.pi * yh) * g
        v = -(np.sin(np.pi * yh) ** 2) * np.sin(2 * np.pi * xh) * g
        np.testing.assert_allclose(ds.vx.values[k], u, atol=1e-15)
        np.testing.assert_allclose(ds.vy.values[k], v, atol=1e-15)


@pytest.mark.parametrize("ndim", [2, 3])
def test_swirl_reverses_over_a_revolution(ndim):
    # The linear interpolant through the phases integrates to zero over a revolution.
    ds = swirl(ndim=ndim, cells=5, n_phases=7)
    for name in ("vx", "vy", "vz")[:ndim]:
        v = ds[name].values
        assert np.max(np.abs(v.sum(axis=0))) <= 1e-14 * np.max(np.abs(v))


@pytest.mark.parametrize("ndim, coarse", [(2, (16, 24)), (3, (8, 12, 10))], ids=["2d", "3d"])
def test_swirl_is_divergence_free_to_second_order(ndim, coarse):
    fine = tuple(2 * n for n in coarse)
    errors = []
    for cells in (coarse, fine):
        ds = swirl(ndim=ndim, cells=cells, n_phases=2)
        div = divergence(ds)
        scale = np.max(np.abs(ds.vx.values[0])) / ds.attrs["rpm"]  # velocity / length
        errors.append(np.max(np.abs(div)) / max(scale, 1e-300))
    assert errors[1] < errors[0]
    order = math.log2(errors[0] / errors[1])
    assert 1.8 < order < 2.2, (errors, order)


def test_swirl_on_equal_spacing_is_discretely_solenoidal():
    # With equal spacing the central-difference truncation errors cancel exactly.
    ds = swirl(ndim=3, cells=8, n_phases=2)
    assert np.max(np.abs(divergence(ds))) < 1e-12


def test_swirl_is_full_box():
    ds = swirl(ndim=3, cells=3, n_phases=2, size=0.5)
    assert np.all(ds.fill.values == 1) and np.all(ds.vessel.values == 1)
    assert ds.x.values.min() > 0 and ds.x.values.max() < 0.5


# ---------------------------------------------------------------------------------------
# Solid-body rotation
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("ndim", [2, 3])
def test_solid_body_speed_is_omega_r(ndim):
    rpm = 12.0
    ds = solid_body_rotation(ndim=ndim, cells=10, rpm=rpm, fill_fraction=0.5, n_phases=4)
    omega = 2 * math.pi * rpm / 60
    grid = np.meshgrid(*(ds[a].values for a in ("x", "y", "z")[:ndim]), indexing="ij")
    for k in range(ds.sizes["rev_phase"]):
        material = ds.fill.values[k] > 0
        vx, vy = ds.vx.values[k], ds.vy.values[k]
        speed = np.hypot(vx, vy)
        r = np.hypot(grid[0], grid[1])
        np.testing.assert_allclose(speed[material], omega * r[material], rtol=1e-14)
        # counter-clockwise seen from +z: v = omega (-y, x)
        np.testing.assert_allclose(vx[material], -omega * grid[1][material], rtol=1e-14)
        np.testing.assert_allclose(vy[material], omega * grid[0][material], rtol=1e-14)
        assert np.all(vx[~material] == 0) and np.all(vy[~material] == 0)
        if ndim == 3:
            assert np.all(ds.vz.values[k] == 0)


@pytest.mark.parametrize("ndim", [2, 3])
def test_solid_body_is_divergence_free(ndim):
    ds = solid_body_rotation(ndim=ndim, cells=12)
    div = divergence(ds)[material_interior(ds)]
    assert div.size > 0
    omega = 2 * math.pi * ds.attrs["rpm"] / 60
    assert np.max(np.abs(div)) <= 1e-12 * omega


def test_full_vessel_shape():
    radius, length = 0.1, 0.3
    ds = solid_body_rotation(ndim=3, radius=radius, length=length, cells=16)
    assert ds.sizes["rev_phase"] == 1
    h = spacing(ds, "x")
    assert h == pytest.approx(2 * radius / 16)
    x, y, z = np.meshgrid(ds.x.values, ds.y.values, ds.z.values, indexing="ij")
    inside = (np.hypot(x, y) < radius) & (np.abs(z) < length / 2)
    np.testing.assert_array_equal(ds.vessel.values, inside)
    assert np.all(ds.fill.values[0] == ds.vessel.values)
    # a layer of empty cells around the vessel, also beyond the end walls
    for axis in range(3):
        assert not ds.vessel.values.take([0, -1], axis=axis).any()
    volume = ds.vessel.values.sum() * h**3
    assert volume == pytest.approx(math.pi * radius**2 * length, rel=0.05)


@pytest.mark.parametrize("ndim, fraction", [(2, 0.4), (3, 0.25), (2, 0.9)])
def test_moving_bed_keeps_its_volume(ndim, fraction):
    ds = solid_body_rotation(ndim=ndim, cells=16, fill_fraction=fraction, n_phases=12)
    cell = spacing(ds, "x") ** ndim
    vessel_volume = ds.vessel.values.sum() * cell
    axes = [a for a in ("x", "y", "z") if a in ds.dims]
    volumes = ds.fill.sum(axes).values * cell
    assert np.all(np.abs(volumes - fraction * vessel_volume) <= cell)
    # stronger than asked: the chord is solved per phase, so it holds to round-off
    np.testing.assert_allclose(volumes, fraction * vessel_volume, rtol=1e-12)
    assert np.all(ds.fill.values[:, ds.vessel.values == 0] == 0)


def _centroid(ds, k):
    f = ds.fill.isel(rev_phase=k)
    if "z" in f.dims:
        f = f.sum("z")
    x, y = np.meshgrid(ds.x.values, ds.y.values, indexing="ij")
    w = f.values
    return np.array([(w * x).sum(), (w * y).sum()]) / w.sum()


@pytest.mark.parametrize("ndim", [2, 3])
def test_moving_bed_turns_with_the_flow(ndim):
    n = 12
    ds = solid_body_rotation(ndim=ndim, cells=16, fill_fraction=0.3, n_phases=n)
    h = spacing(ds, "x")
    start = _centroid(ds, 0)
    assert abs(start[0]) < 1e-12 and start[1] < -0.5 * 0.1  # at the bottom at phase 0
    for k, phase in enumerate(ds.rev_phase.values):
        angle = 2 * math.pi * phase
        turned = np.array(
            [
                math.cos(angle) * start[0] - math.sin(angle) * start[1],
                math.sin(angle) * start[0] + math.cos(angle) * start[1],
            ]
        )
        assert np.linalg.norm(_centroid(ds, k) - turned) < 0.25 * h, (k, phase)


def test_moving_bed_quarter_turn_is_exact():
    # The grid and the discrete circle are symmetric under a quarter turn, so the fill
    # at phase 1/4 is the phase-0 fill rotated: F1[i, j] = F0[j, n-1-i].
    ds = solid_body_rotation(ndim=2, cells=12, fill_fraction=0.35, n_phases=8)
    f0, f1 = ds.fill.values[0], ds.fill.values[2]
    n = f0.shape[0]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    np.testing.assert_allclose(f1, f0[j, n - 1 - i], atol=1e-12)
    assert ds.attrs["frame"] == "lab"


# ---------------------------------------------------------------------------------------
# Arguments
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "function, kwargs, match",
    [
        (uniform, {"velocity": (1.0,)}, "velocity"),
        (uniform, {"velocity": (1.0, np.nan)}, "velocity"),
        (uniform, {"cells": 1}, "cells"),
        (uniform, {"cells": (4, 4, 4)}, "cells"),
        (uniform, {"extent": -1.0}, "extent"),
        (uniform, {"extent": [(0, 1), (1, 0)]}, "extent"),
        (uniform, {"frame": "rotor"}, "frame"),
        (swirl, {"ndim": 4}, "ndim"),
        (swirl, {"n_phases": 1}, "n_phases"),
        (swirl, {"rpm": 0.0}, "rpm"),
        (swirl, {"size": 0.0}, "size"),
        (solid_body_rotation, {"fill_fraction": 0.0}, "fill_fraction"),
        (solid_body_rotation, {"fill_fraction": 1.5}, "fill_fraction"),
        (solid_body_rotation, {"fill_fraction": 0.5, "n_phases": 1}, "n_phases"),
        (solid_body_rotation, {"radius": -0.1}, "radius"),
        (solid_body_rotation, {"cells": 3}, "cells"),
        (solid_body_rotation, {"ndim": 2, "length": 0.2}, "length"),
    ],
)
def test_bad_arguments_are_refused(function, kwargs, match):
    with pytest.raises(ValueError, match=match):
        function(**kwargs)


def test_partial_fill_defaults_to_several_phases():
    ds = solid_body_rotation(ndim=2, cells=6, fill_fraction=0.5)
    assert ds.sizes["rev_phase"] > 1
