"""Mixing indices against independent answers (hand computations and exact cases)."""

import math

import dask
import dask.array as da
import numpy as np
import pytest
import xarray as xr

from blendxr import metrics

H = 0.01  # grid spacing used throughout, m


def centres(n, h=H):
    return (np.arange(n) + 0.5) * h


def field(values, lead=None):
    """Wrap an array as a concentration field on the uniform grid of spacing H."""
    values = np.asarray(values, dtype=float)
    names = ("x", "y", "z")[: values.ndim - (1 if lead else 0)]
    dims = ((lead,) if lead else ()) + names
    coords = {d: centres(values.shape[dims.index(d)]) for d in names}
    return xr.DataArray(values, dims=dims, coords=coords, name="c")


def forbid_compute():
    """A dask scheduler that fails: building a lazy result must not compute anything."""

    def scheduler(*args, **kwargs):
        raise AssertionError("a lazy metric computed something while being built")

    return dask.config.set(scheduler=scheduler)


# --------------------------------------------------------------------------- RSD


def test_rsd_matches_hand_computation_on_random_field():
    rng = np.random.default_rng(1)
    v = rng.random((7, 6, 5))
    v[0, :, :] = np.nan  # cells without material are left out
    got = float(metrics.rsd(field(v)))
    ok = v[~np.isnan(v)]
    assert got == pytest.approx(np.std(ok, ddof=1) / np.mean(ok), rel=1e-12)


def test_rsd_unit_weights_equal_unweighted_and_weights_follow_formula():
    rng = np.random.default_rng(2)
    c = field(rng.random((6, 5, 4)))
    ones = xr.ones_like(c)
    assert float(metrics.rsd(c, fill=ones)) == float(metrics.rsd(c))

    w = rng.random((6, 5, 4))
    v = c.values
    v1, v2 = w.sum(), (w**2).sum()
    mean = (w * v).sum() / v1
    var = (w * (v - mean) ** 2).sum() / (v1 - v2 / v1)
    got = float(metrics.rsd(c, fill=field(w)))
    assert got == pytest.approx(math.sqrt(var) / mean, rel=1e-12)


def test_rsd_uniform_field_is_zero():
    assert float(metrics.rsd(field(np.full((4, 5, 3), 0.3)))) == 0.0


def test_rsd_fully_segregated_50_50_is_exact():
    v = np.zeros((4, 6, 3))
    v[:, 3:, :] = 1.0
    m = v.size
    assert float(metrics.rsd(field(v))) == pytest.approx(math.sqrt(m / (m - 1)), rel=1e-14)


def test_rsd_keeps_leading_dims_and_attrs():
    rng = np.random.default_rng(3)
    c = field(rng.random((3, 4, 5, 2)), lead="time")
    out = metrics.rsd(c)
    assert out.dims == ("time",)
    for k in range(3):
        v = c.values[k]
        assert float(out[k]) == pytest.approx(v.std(ddof=1) / v.mean(), rel=1e-12)
    assert out.attrs["units"] == "1" and "long_name" in out.attrs


def test_rsd_rejects_bad_input():
    with pytest.raises(ValueError, match="spatial dims"):
        metrics.rsd(xr.DataArray(np.ones((3, 3)), dims=("a", "b")))
    with pytest.raises(ValueError, match="DataArray"):
        metrics.rsd(np.ones((3, 3)))
    c = field(np.ones((3, 3)))
    with pytest.raises(ValueError, match="size"):
        metrics.rsd(c, fill=field(np.ones((4, 3))))
    with pytest.raises(ValueError, match="rev_phase"):
        metrics.rsd(c, fill=field(np.ones((2, 3, 3)), lead="rev_phase"))


# --------------------------------------------------------------------------- intensity


def test_intensity_fully_segregated_aligned_cells_is_m_over_m_minus_1():
    v = np.zeros((8, 8))
    v[4:, :] = 1.0  # interface at a sampling-cell boundary for 2-cell samples
    got = float(metrics.segregation_intensity(field(v), cell=2 * H))
    m = 16  # 4 x 4 sampling cells
    assert got == pytest.approx(m / (m - 1), rel=1e-14)
    # grid cells as samples
    got = float(metrics.segregation_intensity(field(v)))
    assert got == pytest.approx(64 / 63, rel=1e-14)


def test_intensity_uniform_is_zero():
    assert float(metrics.segregation_intensity(field(np.full((6, 6, 4), 0.4)), cell=2 * H)) == 0.0


def test_intensity_grid_checkerboard_coarsened_by_two_is_exactly_zero():
    i, j, k = np.indices((6, 4, 4))
    v = ((i + j + k) % 2).astype(float)
    assert float(metrics.segregation_intensity(field(v), cell=2 * H)) == 0.0
    # at grid scale the checkerboard is fully segregated
    assert float(metrics.segregation_intensity(field(v))) == pytest.approx(96 / 95, rel=1e-14)


def test_intensity_drops_sampling_cells_below_min_fill():
    # Two rows of 2x2 sampling cells: the lower row full of material; the upper row has
    # one empty grid cell in each sampling cell (75 % material) and all its material is 1.
    v = np.zeros((4, 4))
    v[:, 2:] = 1.0
    v[0, 3] = np.nan
    v[2, 3] = np.nan
    c = field(v)
    samples = metrics.sample_means(c, cell=2 * H)
    assert samples.sizes == {"x": 2, "y": 2}
    assert np.isnan(samples.values[:, 1]).all()
    assert np.allclose(samples.values[:, 0], 0.0)
    # Only the all-zero row qualifies: mean 0, so I is undefined.
    assert np.isnan(float(metrics.segregation_intensity(c, cell=2 * H)))
    # Let the partial cells in and the answer changes to the segregated value 4/3.
    got = float(metrics.segregation_intensity(c, cell=2 * H, min_fill=0.7))
    assert got == pytest.approx(4 / 3, rel=1e-14)


def test_intensity_fill_threshold_and_weighted_sample_means():
    # With fill: a sampling cell's value is the fill-weighted mean; its fraction the mean fill.
    v = np.array([[0.0, 1.0], [1.0, 1.0]])
    w = np.array([[1.0, 0.5], [1.0, 1.0]])
    s = metrics.sample_means(field(v), fill=field(w), cell=2 * H, min_fill=0.8)
    assert float(s.squeeze()) == pytest.approx(2.5 / 3.5, rel=1e-14)
    s = metrics.sample_means(field(v), fill=field(w), cell=2 * H)
    assert np.isnan(float(s.squeeze()))  # 87.5 % material < 95 %


def test_sample_means_trims_and_checks_cell():
    c = field(np.zeros((5, 7, 3)))
    assert metrics.sample_means(c, cell=2 * H).sizes == {"x": 2, "y": 3, "z": 1}
    with pytest.raises(ValueError, match="smaller than the grid spacing"):
        metrics.sample_means(c, cell=0.5 * H)
    with pytest.raises(ValueError, match="whole number of grid cells"):
        metrics.sample_means(c, cell=2.5 * H)
    with pytest.raises(ValueError, match="positive"):
        metrics.sample_means(c, cell=-H)
    # float32 coordinates are accepted
    c32 = c.assign_coords(x=c.x.astype(np.float32), y=c.y.astype(np.float32))
    assert metrics.sample_means(c32, cell=3 * H).sizes == {"x": 1, "y": 2, "z": 1}


@pytest.mark.parametrize("shape, k", [((11, 9, 7), 2), ((10, 13), 3), ((6, 6, 6), 1)])
def test_array_recorder_equals_the_labelled_metrics(shape, k):
    """The records' plain-array metrics give the labelled functions' numbers exactly
    (NaN cells, partial fills, sampling cells trimmed at the far ends)."""
    rng = np.random.default_rng(len(shape) * 10 + k)
    values = rng.random(shape)
    values[rng.random(shape) < 0.2] = np.nan
    fill = np.clip(rng.random(shape) * 1.3, 0.0, 1.0)
    fill[rng.random(shape) < 0.05] = np.nan
    c, f = field(values), field(fill)
    recorder = metrics.ArrayRecorder(shape, (k,) * len(shape), min_fill=0.5)
    w = recorder.weights(values, fill)
    assert recorder.rsd(values, w) == float(metrics.rsd(c, fill=f))
    samples = metrics.sample_means(c, fill=f, cell=k * H, min_fill=0.5)
    mine = recorder.sample_means(values, w)
    np.testing.assert_array_equal(mine, samples.values)
    assert np.count_nonzero(~np.isnan(mine)) >= 2
    assert recorder.intensity(mine) == float(metrics.intensity_of_samples(samples))


def test_array_recorder_rejects_factors_that_do_not_fit():
    with pytest.raises(ValueError, match="do not fit"):
        metrics.ArrayRecorder((4, 4, 4), (2, 2))


# --------------------------------------------------------------------------- random floor, Lacey


def test_random_mixture_intensity_paper_drum():
    assert metrics.random_mixture_intensity(1e-3, 5e-3, ndim=2) == pytest.approx(0.04, rel=1e-14)


def test_random_mixture_intensity_3d_by_hand():
    d, cell, packing = 1e-3, 4e-3, 0.6
    n = packing * cell**3 / (math.pi * d**3 / 6)  # about 73.3 beads
    assert metrics.random_mixture_intensity(d, cell) == pytest.approx(1 / n, rel=1e-14)
    assert metrics.random_mixture_intensity(d, cell, packing=0.5) == pytest.approx(
        1 / (n * 0.5 / 0.6), rel=1e-14
    )


@pytest.mark.parametrize(
    "args, kwargs",
    [
        ((0, 1e-3), {}),
        ((-1e-3, 1e-3), {}),
        ((2e-3, 1e-3), {}),
        ((1e-3, 5e-3), {"ndim": 1}),
        ((1e-3, 5e-3), {"packing": 1.5}),
    ],
)
def test_random_mixture_intensity_rejects_bad_input(args, kwargs):
    with pytest.raises(ValueError):
        metrics.random_mixture_intensity(*args, **kwargs)


def test_lacey_segregated_is_zero_and_random_is_one():
    v = np.zeros((8, 8))
    v[4:, :] = 1.0
    c = field(v)
    m = 16
    i_r = 0.04
    got = float(metrics.lacey_index(c, cell=2 * H, sigma_r2=0.25 * i_r))
    # the n - 1 variance of eq. (26) makes the segregated value -1/((M-1)(1-I_R)) ~ 0
    assert got == pytest.approx(-1 / ((m - 1) * (1 - i_r)), rel=1e-12)
    assert abs(got) < 0.1
    # a large fully segregated bed: 0 to within 1/M
    big = np.zeros((200, 200))
    big[:, 100:] = 1.0
    assert float(metrics.lacey_index(field(big), d=1e-3)) == pytest.approx(0.0, abs=1e-4)

    rng = np.random.default_rng(4)
    r = field(rng.random((6, 6, 4)))
    ok = r.values.ravel()
    sigma2 = ok.var(ddof=1)
    assert float(metrics.lacey_index(r, sigma_r2=sigma2)) == pytest.approx(1.0, rel=1e-12)
    # without a floor M = 1 - I
    i = float(metrics.segregation_intensity(r))
    assert float(metrics.lacey_index(r)) == pytest.approx(1 - i, rel=1e-12)
    # the floor from the particle size: M = (1 - I) / (1 - I_R)
    i_r = metrics.random_mixture_intensity(1e-3, H, ndim=3)
    assert float(metrics.lacey_index(r, d=1e-3)) == pytest.approx((1 - i) / (1 - i_r), rel=1e-12)
    with pytest.raises(ValueError, match="not both"):
        metrics.lacey_index(r, sigma_r2=0.01, d=1e-3)


# --------------------------------------------------------------------------- thieves


def bed_3d():
    """A box bed of 12 x 10 x 8 cells in a 16 x 12 x 10 grid; c varies with x only."""
    nx, ny, nz = 16, 12, 10
    x = centres(nx)
    v = np.broadcast_to((0.1 + 0.05 * np.arange(nx))[:, None, None], (nx, ny, nz)).copy()
    fill = np.zeros((nx, ny, nz))
    fill[2:14, 0:10, 1:9] = 1.0
    v[fill == 0] = np.nan
    return field(v), field(fill), x


def test_thief_positions_inside_material_3d():
    _, fill, _ = bed_3d()
    pos = metrics.thief_positions(fill)
    assert pos.sizes["thief"] == 9
    xs, zs = pos.x.values, pos.z.values
    # the material columns span x centres 0.025..0.135, z centres 0.015..0.085
    assert np.allclose(np.unique(xs), 0.025 + 0.11 * np.array([0.2, 0.5, 0.8]))
    assert np.allclose(np.unique(zs), 0.015 + 0.07 * np.array([0.2, 0.5, 0.8]))
    for px, pz in zip(xs, zs, strict=True):
        col = fill.sel(x=px, z=pz, method="nearest")
        assert float(col.max()) == 1.0
    assert metrics.thief_positions(fill, n=(2, 5)).sizes["thief"] == 10
    with pytest.raises(ValueError, match="rev_phase"):
        metrics.thief_positions(fill.expand_dims(rev_phase=2))
    with pytest.raises(ValueError, match="margin"):
        metrics.thief_positions(fill, margin=0.6)


def test_thief_samples_equal_exact_column_means():
    c, fill, x = bed_3d()
    f = 0.1 + 0.05 * np.arange(len(x))
    # probes on grid-cell centres with half a cell radius sample one column: exactly f(x)
    pos = xr.Dataset(
        {"x": ("thief", x[[3, 7, 12]]), "z": ("thief", centres(10)[[2, 5, 8]])},
    )
    got = metrics.thief_samples(c, fill=fill, positions=pos, radius=0.5 * H)
    assert np.allclose(got.values, f[[3, 7, 12]], rtol=1e-14)

    # default pattern and radius (1.5 cells): mean over the columns within the disc
    got = metrics.thief_samples(c, fill=fill)
    pos = metrics.thief_positions(fill)
    zc = centres(10)
    for k in range(9):
        px, pz = float(pos.x[k]), float(pos.z[k])
        vals = []
        for i in range(len(x)):
            for j in range(len(zc)):
                if (x[i] - px) ** 2 + (zc[j] - pz) ** 2 <= (1.5 * H) ** 2 * (1 + 1e-9):
                    vals += [c.values[i, yy, j] for yy in range(12) if fill.values[i, yy, j]]
        assert float(got[k]) == pytest.approx(np.mean(vals), rel=1e-12)


def test_thief_depth_slabs_and_rsd():
    # c varies with height only: each of two slabs of the 10-cell column is a 5-cell mean
    nx, ny = 9, 12
    v = np.broadcast_to(np.arange(ny, dtype=float)[None, :] / 20, (nx, ny)).copy()
    v[:, 10:] = np.nan
    c = field(v)
    s = metrics.thief_samples(c, n_depths=2)
    assert s.dims == ("thief", "depth")
    assert np.allclose(s.sel(depth=0).values, np.mean(np.arange(5, 10)) / 20)  # top slab
    assert np.allclose(s.sel(depth=1).values, np.mean(np.arange(0, 5)) / 20)
    samples = s.values.ravel()
    got = float(metrics.thief_rsd(c, n_depths=2))
    assert got == pytest.approx(samples.std(ddof=1) / samples.mean(), rel=1e-12)


def test_thief_2d_case():
    nx, ny = 20, 8
    x = centres(nx)
    f = 0.2 + 0.03 * np.arange(nx)
    v = np.broadcast_to(f[:, None], (nx, ny)).copy()
    v[:4, 5:] = np.nan  # a sloping surface: columns of different heights
    c = field(v)
    pos = metrics.thief_positions(c.notnull())
    assert pos.sizes["thief"] == 3 and "z" not in pos
    assert np.allclose(pos.x.values, x[0] + (x[-1] - x[0]) * np.array([0.2, 0.5, 0.8]))
    one = xr.Dataset({"x": ("thief", x[[1, 10, 18]])})
    got = metrics.thief_samples(c, positions=one, radius=0.5 * H)
    assert np.allclose(got.values, f[[1, 10, 18]], rtol=1e-14)
    # default radius 1.5 cells: three columns weighted by their material cells
    got = metrics.thief_samples(c, positions=xr.Dataset({"x": ("thief", x[[3]])}))
    expected = (f[2] * 5 + f[3] * 5 + f[4] * 8) / 18
    assert float(got[0]) == pytest.approx(expected, rel=1e-12)
    r = metrics.thief_rsd(c, positions=one, radius=0.5 * H)
    ff = f[[1, 10, 18]]
    assert float(r) == pytest.approx(ff.std(ddof=1) / ff.mean(), rel=1e-12)


# --------------------------------------------------------------------------- lazy


def test_lazy_results_equal_eager_and_stay_lazy():
    rng = np.random.default_rng(5)
    v = rng.random((3, 8, 8, 6))
    v[:, :, 6:, :] = np.nan
    w = rng.uniform(0.9, 1.0, (8, 8, 6))
    c = field(v, lead="time")
    fill = field(w)
    cl = c.chunk({"time": 1, "x": 4})
    fl = fill.chunk({"x": 4})
    calls = {
        "rsd": lambda a, b: metrics.rsd(a, fill=b),
        "intensity": lambda a, b: metrics.segregation_intensity(a, fill=b, cell=2 * H),
        "intensity_grid": lambda a, b: metrics.segregation_intensity(a),
        "lacey": lambda a, b: metrics.lacey_index(a, fill=b, cell=2 * H, d=1e-3),
        "samples": lambda a, b: metrics.sample_means(a, fill=b, cell=2 * H),
        "thief": lambda a, b: metrics.thief_samples(a, fill=b, n_depths=2),
        "thief_rsd": lambda a, b: metrics.thief_rsd(a),
    }
    for name, call in calls.items():
        eager = call(c, fill)
        with forbid_compute():
            lazy = call(cl, fl)
        assert isinstance(lazy.data, da.Array), name
        assert lazy.dims == eager.dims, name
        np.testing.assert_allclose(lazy.compute().values, eager.values, rtol=1e-12, err_msg=name)
        for d in eager.coords:
            np.testing.assert_array_equal(lazy[d].values, eager[d].values, err_msg=name)
    with forbid_compute():
        pos = metrics.thief_positions(fl)
    assert isinstance(pos.x.data, da.Array)
