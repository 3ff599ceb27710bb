"""The ADE grid and the flow-to-grid maps against exact answers and their NumPy twin."""

from __future__ import annotations

import numpy as np
import pytest

from blendxr.ade.grid import AdeGrid, AxisMap, extend_into_empty, interpolate, interpolate_into


@pytest.mark.parametrize("shape, target", [((7, 6, 5), (15, 13, 11)), ((9, 8), (20, 17))])
def test_compiled_interpolation_matches_numpy_twin(shape, target):
    rng = np.random.default_rng(0)
    src = rng.normal(size=shape)
    maps = tuple(
        AxisMap.between(0.1 * np.arange(n), np.linspace(-0.1, 0.1 * n, m))
        for n, m in zip(shape, target, strict=True)
    )
    np.testing.assert_allclose(
        interpolate_into(src, maps, np.empty(target)), interpolate(src, maps), atol=1e-12
    )


def test_linear_fields_are_interpolated_exactly_inside():
    x, y, z = (0.05 * np.arange(n) + 0.025 for n in (6, 5, 4))
    X, Y, Z = np.meshgrid(x, y, z, indexing="ij")
    field = 2.0 * X - 3.0 * Y + 0.5 * Z + 1.0
    tx, ty, tz = (np.linspace(c[0], c[-1], 17) for c in (x, y, z))
    maps = tuple(AxisMap.between(s, t) for s, t in zip((x, y, z), (tx, ty, tz), strict=True))
    TX, TY, TZ = np.meshgrid(tx, ty, tz, indexing="ij")
    got = interpolate_into(field, maps, np.empty(TX.shape))
    np.testing.assert_allclose(got, 2.0 * TX - 3.0 * TY + 0.5 * TZ + 1.0, atol=1e-12)


def test_grid_covers_the_box_with_one_padding_cell():
    grid = AdeGrid.covering([0.0, -0.5], [2.0, 0.5], 8)
    assert grid.spacing == (0.25, 0.25)
    assert grid.shape == (10, 6)
    assert grid.coords[0][1] == pytest.approx(0.125) and grid.coords[0][-2] == pytest.approx(1.875)


def test_extension_fills_neighbours_with_the_mean_of_known_cells():
    field = np.zeros((5, 5))
    known = np.zeros((5, 5), bool)
    field[2, 2], known[2, 2] = 4.0, True
    field[2, 3], known[2, 3] = 2.0, True
    out = extend_into_empty(field, known, np.ones((5, 5), bool), layers=1)
    assert out[1, 2] == 4.0 and out[2, 4] == 2.0 and out[1, 3] == 2.0
    assert out[0, 0] == 0.0  # beyond one layer nothing is set


@pytest.mark.parametrize("shape", [(9, 7), (6, 8, 5)])
@pytest.mark.parametrize("layers", [1, 2, 4])
def test_extend_into_empty_matches_its_numpy_twin(shape, layers):
    from blendxr.ade import reference

    rng = np.random.default_rng(len(shape) * 10 + layers)
    field = rng.normal(size=shape)
    known = rng.random(shape) < 0.2
    allowed = rng.random(shape) < 0.8
    got = extend_into_empty(field, known, allowed, layers=layers)
    want = reference.extend_into_empty(field, known, allowed, layers=layers)
    np.testing.assert_array_equal(got, want)
