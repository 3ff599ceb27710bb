"""Mixing indices of a concentration field: RSD, segregation intensity, Lacey, thieves.

Every function takes the concentration ``c`` (fraction of species A in the solids, NaN where
there is no material) as an :class:`xarray.DataArray` on a uniform cell-centred grid with
spatial dims ``(x, y, z)`` or ``(x, y)`` (y up), possibly with extra leading dims such as
``time`` or ``snapshot``, which are kept in the result. A ``fill`` DataArray (material volume
fraction of each cell, 0-1, on the same grid) may weight the cells.

The reductions are written with xarray operations only, so a dask-backed ``c`` gives a
dask-backed result: nothing is computed until the caller asks for it.

The equations are those of the Tote paper: segregation intensity eq. (25)-(28), random
mixture floor eq. (29), relative standard deviation eq. (31)-(32); sampling cells follow its
Appendix A (non-overlapping square cells holding at least 95 % material).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping

import numpy as np
import xarray as xr

__all__ = [
    "SPATIAL_DIMS",
    "lacey_index",
    "intensity_of_samples",
    "random_mixture_intensity",
    "random_mixture_rsd",
    "rsd",
    "sample_means",
    "segregation_intensity",
    "thief_positions",
    "thief_rsd",
    "thief_samples",
]

SPATIAL_DIMS = ("x", "y", "z")

# A sampling cell may be this far (in grid cells) from a whole number of grid cells: grids
# written as float32 carry spacings with relative errors of about 1e-6.
_WHOLE_CELL_TOL = 1e-3
#: Least material fraction of a qualified sampling cell (the paper's Appendix A), and the
#: allowance that keeps a cell whose fraction is that value up to round-off.
MIN_SAMPLE_FILL = 0.95
_MIN_FILL_ALLOWANCE = 1e-12
# Relative tolerance on the uniformity of a grid's spacing.
_UNIFORM_RTOL = 1e-4
# A cell belongs to the bed when more than this fraction of it holds material.
_MATERIAL_THRESHOLD = 0.5


# --------------------------------------------------------------------------- helpers


def _check_field(c, name="c"):
    """Check that ``c`` is a DataArray with spatial dims and return those dims."""
    if not isinstance(c, xr.DataArray):
        raise ValueError(f"{name} must be an xarray.DataArray, got {type(c).__name__}")
    spatial = tuple(d for d in SPATIAL_DIMS if d in c.dims)
    if "x" not in spatial or "y" not in spatial:
        raise ValueError(
            f"{name} must have spatial dims (x, y) or (x, y, z); it has dims {tuple(c.dims)}"
        )
    return spatial


def _as_float(a):
    """Promote to float64 so that sums over millions of cells keep their digits."""
    if a.dtype == np.float64:
        return a
    return a.astype(np.float64)


def _match_fill(fill, c):
    """Return ``fill`` on the grid of ``c`` (same coordinates), or raise a clear error."""
    if not isinstance(fill, xr.DataArray):
        raise ValueError(f"fill must be an xarray.DataArray, got {type(fill).__name__}")
    extra = [d for d in fill.dims if d not in c.dims]
    if extra:
        raise ValueError(
            f"fill has dims {extra} that c does not have (c dims {tuple(c.dims)}); "
            "select one value along them first, e.g. fill.isel(rev_phase=0)"
        )
    for d in fill.dims:
        if fill.sizes[d] != c.sizes[d]:
            raise ValueError(
                f"fill and c differ in size along {d!r}: {fill.sizes[d]} != {c.sizes[d]}"
            )
        if d in fill.coords and d in c.coords:
            a = np.asarray(fill[d].values)
            b = np.asarray(c[d].values)
            if np.issubdtype(a.dtype, np.number) and np.issubdtype(b.dtype, np.number):
                scale = float(np.max(np.abs(b))) if b.size else 1.0
                same = np.allclose(a, b, rtol=1e-5, atol=1e-6 * max(scale, 1e-300))
            else:
                same = np.array_equal(a, b)
            if not same:
                raise ValueError(f"fill and c are not on the same grid: coordinate {d!r} differs")
    # Coordinates read back from float32 files differ from recomputed ones by round-off;
    # once checked above, take c's so that arithmetic does not drop cells on alignment.
    _, fill = xr.align(c, fill, join="override")
    return fill


def _weights(c, fill):
    """Cell weights: fill (or 1) where c holds material, 0 elsewhere."""
    valid = c.notnull()
    if fill is None:
        return valid.astype(np.float64)
    fill = _as_float(_match_fill(fill, c))
    return fill.fillna(0.0).where(valid, 0.0)


def _spacing(c, dim):
    """Uniform grid spacing along ``dim`` from the cell-centre coordinate."""
    if dim not in c.coords:
        raise ValueError(f"c needs a coordinate {dim!r} (cell centres) to know the grid spacing")
    v = np.asarray(c[dim].values, dtype=np.float64)
    if v.size < 2:
        raise ValueError(f"c needs at least 2 cells along {dim!r} to know the grid spacing")
    # The end-to-end span gives the spacing with the least round-off.
    h = (v[-1] - v[0]) / (v.size - 1)
    if h == 0 or not np.allclose(np.diff(v), h, rtol=_UNIFORM_RTOL, atol=0):
        raise ValueError(f"the grid is not uniform along {dim!r}")
    return abs(float(h))


def _positive(name, value):
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be positive and finite, got {value!r}")
    return value


def _dims_list(dims, c, default):
    if dims is None:
        return list(default)
    if isinstance(dims, str) or not isinstance(dims, Iterable):
        dims = [dims]
    dims = list(dims)
    missing = [d for d in dims if d not in c.dims]
    if missing:
        raise ValueError(f"dims {missing} are not dims of c {tuple(c.dims)}")
    if not dims:
        raise ValueError("dims must name at least one dim to reduce over")
    return dims


def _moments_core(values, w, n_axes):
    """Weighted mean and variance over the last ``n_axes`` axes of plain arrays (the
    arithmetic of :func:`_moments`, which applies it to labelled data)."""
    axes = tuple(range(-n_axes, 0))
    has = w > 0
    # Shifting by one of the values makes a uniform field give exactly zero variance (the
    # mean of identical numbers is not always that number in floating point) and keeps
    # the two-pass sums well conditioned.
    with np.errstate(invalid="ignore"):
        ref = np.where(has, values, -np.inf).max(axis=axes)
    ref = np.where(np.isneginf(ref), 0.0, ref)
    ref_b = np.expand_dims(ref, axes)
    v0 = np.where(has, values - ref_b, 0.0)
    v1 = w.sum(axis=axes)
    v2 = (w * w).sum(axis=axes)
    with np.errstate(invalid="ignore", divide="ignore"):
        v1_pos = np.where(v1 > 0, v1, np.nan)
        shift = (w * v0).sum(axis=axes) / v1_pos
        norm = v1 - v2 / v1_pos
        dev = v0 - np.expand_dims(shift, axes)
        var = (w * dev**2).sum(axis=axes) / np.where(norm > 0, norm, np.nan)
    return ref + shift, var


def _moments(values, w, dims):
    """Weighted mean and reliability-weighted variance over ``dims``.

    variance = sum w (v - mean)^2 / (V1 - V2 / V1), V1 = sum w, V2 = sum w^2, which is the
    n - 1 sample variance when every weight is 1. NaN values must carry zero weight. The
    arithmetic is :func:`_moments_core` on the arrays (one pass of NumPy over each, not
    a labelled operation per term); dask-backed data stay lazy.
    """
    values, w = xr.broadcast(values, w)
    return xr.apply_ufunc(
        _moments_core,
        values,
        w,
        kwargs={"n_axes": len(dims)},
        input_core_dims=[list(dims), list(dims)],
        output_core_dims=[[], []],
        dask="allowed",  # the core's NumPy calls dispatch to dask's own reductions
    )


def _finish(result, name, long_name, units="1", **attrs):
    result = result.rename(name)
    result.attrs = {"units": units, "long_name": long_name, **attrs}
    return result


def _check_min_fill(min_fill):
    try:
        min_fill = float(min_fill)
    except (TypeError, ValueError):
        raise ValueError(f"min_fill must be a number in [0, 1], got {min_fill!r}") from None
    if not 0.0 <= min_fill <= 1.0:
        raise ValueError(f"min_fill must be in [0, 1], got {min_fill}")
    return min_fill


# --------------------------------------------------------------------------- RSD


def rsd(c, fill=None, dims=None):
    """Relative standard deviation of the concentration, eq. (31)-(32) of the Tote paper.

    RSD = sigma / c_mean with the n - 1 sample standard deviation over all cells holding
    material (NaN cells are left out). With ``fill`` the cells are weighted by their material
    volume fraction w: c_mean = sum w c / V1 and

        sigma^2 = sum w (c - c_mean)^2 / (V1 - V2 / V1),  V1 = sum w,  V2 = sum w^2,

    the reliability-weighted variance, which is exactly eq. (32) when every weight is 1.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])``; NaN where there is no material.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid (dims a subset of ``c``'s).
    dims : str or sequence of str, optional
        Dims to reduce over; default the spatial dims of ``c`` among x, y, z.

    Returns
    -------
    xarray.DataArray
        RSD (dimensionless) with the dims of ``c`` not reduced over. 0 for a uniform field;
        NaN where fewer than two cells hold material or the mean is 0.
        Lazy if ``c`` or ``fill`` is dask-backed.
    """
    spatial = _check_field(c)
    dims = _dims_list(dims, c, spatial)
    c = _as_float(c)
    mean, var = _moments(c, _weights(c, fill), dims)
    out = np.sqrt(var) / mean.where(mean != 0)
    return _finish(out, "rsd", "relative standard deviation of concentration")


# --------------------------------------------------------------------------- sampling cells


def _coarsen_factors(c, spatial, cell):
    cell = _positive("cell", cell)
    factors = {}
    for d in spatial:
        h = _spacing(c, d)
        k = cell / h
        if k < 1.0 - _WHOLE_CELL_TOL:
            raise ValueError(
                f"cell = {cell:g} m is smaller than the grid spacing along {d!r} ({h:g} m); "
                "a sampling cell must span at least one grid cell"
            )
        kr = round(k)
        if abs(k - kr) > _WHOLE_CELL_TOL:
            raise ValueError(
                f"cell = {cell:g} m is {k:.4g} grid cells along {d!r} (spacing {h:g} m); "
                f"it must be a whole number of grid cells, e.g. {max(kr, 1) * h:g} m"
            )
        if kr > c.sizes[d]:
            raise ValueError(
                f"cell = {cell:g} m spans {kr} grid cells along {d!r} but the grid has only "
                f"{c.sizes[d]}"
            )
        factors[d] = kr
    return factors


def sample_means(c, fill=None, cell=None, min_fill=MIN_SAMPLE_FILL):
    """Concentrations of non-overlapping sampling cells of edge ``cell`` (scale of scrutiny).

    The grid is cut into cubes (squares in 2-D) of ``cell / h`` grid cells per side, starting
    at the first grid cell; incomplete cells at the far ends are dropped (``coarsen`` with
    ``boundary="trim"``). A sampling cell's concentration is the fill-weighted mean of c over
    its grid cells. As in the paper's Appendix A, a sampling cell must be mostly material:
    those whose material fraction (mean of ``fill``, or of the has-material indicator when
    ``fill`` is None) is below ``min_fill`` are set to NaN.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])`` with cell-centre coordinates on x, y, z.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid.
    cell : float, optional
        Edge of a sampling cell in metres; a whole number of grid cells along every spatial
        axis. None: every grid cell is a sample (the rule on ``min_fill`` still applies).
    min_fill : float
        Least material fraction of a qualified sampling cell, default 0.95.

    Returns
    -------
    xarray.DataArray
        Sample concentrations with the spatial dims coarsened (coordinates are the centres
        of the sampling cells); NaN for cells that do not qualify.

    Raises
    ------
    ValueError
        If ``cell`` is smaller than a grid cell, or not close to a whole number of grid
        cells, or the grid is not uniform.
    """
    spatial = _check_field(c)
    min_fill = _check_min_fill(min_fill)
    c = _as_float(c)
    w = _weights(c, fill)
    if cell is None:
        mean = c.where(w > 0)
        frac = w
        scale = "grid cell"
    else:
        factors = _coarsen_factors(c, spatial, cell)
        num = (w * c.fillna(0.0)).coarsen(factors, boundary="trim").sum()
        den = w.coarsen(factors, boundary="trim").sum()
        frac = w.coarsen(factors, boundary="trim").mean()
        mean = num / den.where(den > 0)
        scale = f"{float(cell):g} m"
    out = mean.where(frac >= min_fill - _MIN_FILL_ALLOWANCE)
    return _finish(
        out,
        "c_sample",
        "concentration of sampling cells",
        scale_of_scrutiny=scale,
        min_fill=min_fill,
    )


def segregation_intensity(c, fill=None, cell=None, min_fill=MIN_SAMPLE_FILL):
    """Segregation intensity I = sigma^2 / (c_mean (1 - c_mean)), eq. (25)-(28).

    The samples are the qualified sampling cells of :func:`sample_means`; sigma^2 is their
    n - 1 variance (eq. 26) and c_mean their plain mean (eq. 28). I is 0 for a perfect
    mixture, M / (M - 1) (about 1) for a fully segregated one with M samples, and
    1 / N (eq. 29, :func:`random_mixture_intensity`) for a random mixture.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])``.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid.
    cell : float, optional
        Edge of a sampling cell in metres (scale of scrutiny); None: every grid cell is a
        sample.
    min_fill : float
        Least material fraction of a qualified sampling cell, default 0.95.

    Returns
    -------
    xarray.DataArray
        I (dimensionless) with the non-spatial dims of ``c``; NaN with fewer than two
        qualified samples or when c_mean is 0 or 1.
    """
    _check_field(c)
    return intensity_of_samples(sample_means(c, fill=fill, cell=cell, min_fill=min_fill))


def intensity_of_samples(samples):
    """Segregation intensity, eq. (25)-(28), of sample concentrations (NaN: not a sample).

    Parameters
    ----------
    samples : xarray.DataArray
        Sample concentrations as :func:`sample_means` returns them.

    Returns
    -------
    xarray.DataArray
        I over the spatial dims; NaN with fewer than two samples or c_mean 0 or 1.
    """
    spatial = [d for d in SPATIAL_DIMS if d in samples.dims]
    mean, var = _moments(samples, samples.notnull().astype(np.float64), spatial)
    sigma0 = mean * (1.0 - mean)
    out = var / sigma0.where(sigma0 > 0)
    return _finish(
        out,
        "intensity",
        "segregation intensity",
        scale_of_scrutiny=samples.attrs.get("scale_of_scrutiny", ""),
    )


def random_mixture_rsd(d, cell, mean, *, ndim=3, packing=0.6):
    """RSD of a random mixture on samples of ``N`` particles: sqrt((1 - c) / (c N)).

    The binomial variance c (1 - c) / N of a sample's fraction (eq. 29's N) over the mean
    ``c``, so that RSD_R^2 = I_R (1 - c) / c; 1 / sqrt(N) for c = 0.5.

    Parameters
    ----------
    d, cell, ndim, packing
        As for :func:`random_mixture_intensity`.
    mean : float
        Mean fraction of species A, in (0, 1).

    Returns
    -------
    float
    """
    if not (0.0 < mean < 1.0):
        raise ValueError(f"mean must be in (0, 1), got {mean!r}")
    floor = random_mixture_intensity(d, cell, ndim=ndim, packing=packing)
    return math.sqrt(floor * (1.0 - mean) / mean)


def random_mixture_intensity(d, cell, *, ndim=3, packing=0.6):
    """Segregation intensity of a random mixture, I_R = 1 / N, eq. (29).

    N is the number of particles of diameter ``d`` in a sampling cell of edge ``cell``:

    - ``ndim=2`` (a photographed face, the paper's drum): N = (cell / d)^2, so the paper's
      cells of five diameters give I_R = 1/25 = 0.04;
    - ``ndim=3`` (a cube of bed): N = packing * cell^3 / (pi d^3 / 6).

    Parameters
    ----------
    d : float
        Particle diameter, m.
    cell : float
        Edge of a sampling cell, m; at least ``d``.
    ndim : {2, 3}
        Dimension of the sample.
    packing : float
        Solid volume fraction of the bed, in (0, 1]; used only for ``ndim=3``.

    Returns
    -------
    float
        I_R = 1 / N.
    """
    d = _positive("d", d)
    cell = _positive("cell", cell)
    if cell < d:
        raise ValueError(f"cell ({cell:g} m) must be at least one particle diameter ({d:g} m)")
    if ndim == 2:
        n = (cell / d) ** 2
    elif ndim == 3:
        packing = _positive("packing", packing)
        if packing > 1:
            raise ValueError(f"packing must be in (0, 1], got {packing}")
        n = packing * cell**3 / (math.pi * d**3 / 6.0)
    else:
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    return 1.0 / n


class ArrayRecorder:
    """The mixing curves' metrics on plain arrays of one fixed grid, for a run's records.

    The same arithmetic as :func:`rsd`, :func:`sample_means` and
    :func:`intensity_of_samples` (the same NumPy reductions in the same order, so the
    same numbers), without labelling each intermediate field: a run records these every
    few steps, where the labelled operations took several times the arithmetic.

    Parameters
    ----------
    shape : tuple of int
        The grid's cells per axis (2-D or 3-D).
    factors : tuple of int, optional
        Grid cells per sampling cell along each axis (see :func:`sample_means`); None: no
        sampling cells.
    min_fill : float
        Least material fraction of a qualified sampling cell.
    """

    def __init__(self, shape, factors=None, min_fill=MIN_SAMPLE_FILL):
        self.ndim = len(shape)
        self.min_fill = _check_min_fill(min_fill)
        self.factors = None if factors is None else tuple(int(k) for k in factors)
        if self.factors is not None:
            if len(self.factors) != self.ndim or min(self.factors) < 1:
                raise ValueError(f"factors {factors!r} do not fit a grid of shape {shape}")
            # coarsen(boundary="trim"): whole sampling cells from the first grid cell
            trim, blocks = [], []
            for n, k in zip(shape, self.factors, strict=True):
                trim.append(slice(0, (n // k) * k))
                blocks += [n // k, k]
            self._trim = tuple(trim)
            self._blocks = tuple(blocks)
            self._axes = tuple(range(1, 2 * self.ndim, 2))

    @staticmethod
    def weights(c, fill):
        """Cell weights: ``fill`` (NaN as 0) where c holds material, 0 elsewhere."""
        return np.where(np.isnan(c), 0.0, np.where(np.isnan(fill), 0.0, fill))

    def rsd(self, c, w):
        """:func:`rsd` of ``c`` with cell weights ``w`` (from :meth:`weights`)."""
        mean, var = _moments_core(c, w, self.ndim)
        with np.errstate(invalid="ignore", divide="ignore"):
            return float(np.sqrt(var) / (mean if mean != 0 else np.nan))

    def _block_sum(self, a):
        return a[self._trim].reshape(self._blocks).sum(axis=self._axes)

    def sample_means(self, c, w):
        """:func:`sample_means` of ``c`` with cell weights ``w``: NaN where a sampling cell
        does not qualify."""
        num = self._block_sum(w * np.where(np.isnan(c), 0.0, c))
        den = self._block_sum(w)
        frac = den / float(np.prod(self.factors))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = num / np.where(den > 0, den, np.nan)
        return np.where(frac >= self.min_fill - _MIN_FILL_ALLOWANCE, mean, np.nan)

    def intensity(self, samples):
        """:func:`intensity_of_samples` of the sample concentrations ``samples``."""
        mean, var = _moments_core(samples, (~np.isnan(samples)).astype(np.float64), self.ndim)
        sigma0 = mean * (1.0 - mean)
        with np.errstate(invalid="ignore", divide="ignore"):
            return float(var / (sigma0 if sigma0 > 0 else np.nan))


def lacey_index(
    c,
    fill=None,
    cell=None,
    sigma_r2=None,
    *,
    d=None,
    ndim=None,
    packing=0.6,
    min_fill=MIN_SAMPLE_FILL,
):
    """Lacey mixing index M = (sigma0^2 - sigma^2) / (sigma0^2 - sigmaR^2).

    sigma^2 is the n - 1 variance of the qualified sample concentrations (as in
    :func:`segregation_intensity`), sigma0^2 = c_mean (1 - c_mean) the variance of the fully
    segregated state, and sigmaR^2 the variance of a random mixture. Equivalently
    M = (1 - I) / (1 - I_R).

    M is 1 for a random mixture (sigma^2 = sigmaR^2), above 1 towards a perfect (continuum)
    mixture, and about 0 for a fully segregated bed: with the n - 1 variance of eq. (26) a
    fully segregated bed of M_s samples gives I = M_s / (M_s - 1), so
    M = -1 / ((M_s - 1)(1 - I_R)), which tends to 0 as the samples multiply.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])``.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid.
    cell : float, optional
        Edge of a sampling cell in metres; None: every grid cell is a sample.
    sigma_r2 : float or xarray.DataArray, optional
        Variance of the random mixture, given directly.
    d : float, optional
        Particle diameter, m: sigmaR^2 = sigma0^2 / N with N the particles per sample
        (:func:`random_mixture_intensity` with ``cell``, or the grid cell when ``cell`` is
        None). Without ``sigma_r2`` and ``d``, sigmaR^2 = 0 (continuum floor) and M = 1 - I.
    ndim : {2, 3}, optional
        Dimension of a sample for the random floor; default the number of spatial dims.
    packing : float
        Solid volume fraction for the 3-D random floor.
    min_fill : float
        Least material fraction of a qualified sampling cell.

    Returns
    -------
    xarray.DataArray
        M (dimensionless) with the non-spatial dims of ``c``.
    """
    spatial = _check_field(c)
    if sigma_r2 is not None and d is not None:
        raise ValueError("give either sigma_r2 or d (the particle diameter), not both")
    samples = sample_means(c, fill=fill, cell=cell, min_fill=min_fill)
    mean, var = _moments(samples, samples.notnull().astype(np.float64), list(spatial))
    sigma0 = mean * (1.0 - mean)
    if sigma_r2 is not None:
        sigma_r = sigma_r2
    elif d is not None:
        if ndim is None:
            ndim = len(spatial)
        if cell is None:
            # A grid cell as the sample: its edge is the geometric mean of the spacings.
            hs = [_spacing(c, s) for s in spatial[:ndim]]
            edge = float(np.prod(hs)) ** (1.0 / len(hs))
        else:
            edge = float(cell)
        sigma_r = sigma0 * random_mixture_intensity(d, edge, ndim=ndim, packing=packing)
    else:
        sigma_r = 0.0
    den = sigma0 - sigma_r
    out = (sigma0 - var) / den.where(den != 0)
    return _finish(out, "lacey_index", "Lacey mixing index")


# --------------------------------------------------------------------------- thieves


def thief_positions(fill, n=(3, 3), margin=0.2):
    """Positions of virtual thief probes over the bed (vessel upright).

    The probes are vertical (along y). In 3-D they stand in an ``n[0] x n[1]`` pattern in
    (x, z) spread over the horizontal extent of the material: the x and z ranges of the
    columns holding material (cells more than half full), shrunk by ``margin`` of the range
    on each side. In 2-D there are ``n`` (or ``n[0]``) x positions. The default is the usual
    nine-point pattern of blend-uniformity sampling.

    Parameters
    ----------
    fill : xarray.DataArray
        Material volume fraction with dims exactly the spatial ones, ``(x, y[, z])``, e.g.
        the phase-0 fill of a flow dataset (``flow.fill.isel(rev_phase=0)``).
    n : int or tuple of int
        Probes along x (and z). An int means the same number along both.
    margin : float
        Fraction of the range left free on each side, in [0, 0.5).

    Returns
    -------
    xarray.Dataset
        Variables ``x`` (and ``z`` in 3-D) in metres along dim ``thief``; thief k stands at
        the ``k // n[1]``-th x and ``k % n[1]``-th z position. Lazy if ``fill`` is.
    """
    spatial = _check_field(fill, name="fill")
    extra = [dim for dim in fill.dims if dim not in spatial]
    if extra:
        raise ValueError(
            f"fill must have only spatial dims for thief positions, but has {extra}; "
            "select the upright state first, e.g. fill.isel(rev_phase=0)"
        )
    try:
        margin = float(margin)
    except (TypeError, ValueError):
        raise ValueError(f"margin must be a number in [0, 0.5), got {margin!r}") from None
    if not 0.0 <= margin < 0.5:
        raise ValueError(f"margin must be in [0, 0.5), got {margin}")
    horizontal = [dim for dim in spatial if dim != "y"]
    counts = (n,) * len(horizontal) if isinstance(n, int | np.integer) else tuple(n)
    if len(counts) < len(horizontal):
        raise ValueError(f"n must give a count for each of {horizontal}, got {n!r}")
    counts = counts[: len(horizontal)]
    for k in counts:
        if not isinstance(k, int | np.integer) or k < 1:
            raise ValueError(f"n must hold positive whole numbers, got {n!r}")
    for dim in horizontal:
        if dim not in fill.coords:
            raise ValueError(f"fill needs a coordinate {dim!r} to place the thieves")

    column = (fill > _MATERIAL_THRESHOLD).any("y")
    fractions = []
    for k in counts:
        if k == 1:
            fractions.append(np.array([0.5]))
        else:
            fractions.append(margin + (1.0 - 2.0 * margin) * np.arange(k) / (k - 1))
    grids = np.meshgrid(*fractions, indexing="ij")
    nthief = int(np.prod(counts))
    out = {}
    for dim, frac in zip(horizontal, grids, strict=True):
        others = [o for o in horizontal if o != dim]
        has = column.any(others) if others else column
        coord = _as_float(fill[dim].reset_coords(drop=True))
        lo = coord.where(has).min()
        hi = coord.where(has).max()
        f = xr.DataArray(frac.ravel(), dims="thief")
        pos = (lo + (hi - lo) * f).drop_vars(dim, errors="ignore")
        pos.attrs = {"units": "m", "long_name": f"{dim} position of thief probe axis"}
        out[dim] = pos
    return xr.Dataset(out, coords={"thief": np.arange(nthief)})


def thief_samples(c, fill=None, positions=None, radius=None, n_depths=1):
    """Virtual thief probes: samples of vertical cylinders through the bed.

    Each probe is a vertical cylinder (axis along y; a vertical strip of half-width
    ``radius`` in 2-D) at a position of ``positions``; its sample is the fill-weighted mean
    of c over the material cells whose centres lie inside the cylinder. The grid column
    nearest to the axis always belongs to the probe, so a probe is never empty where there
    is material. With ``n_depths > 1`` the probe's material column (from its lowest to its
    highest material cell) is cut into that many slabs of equal height, one sample each.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])`` with cell-centre coordinates.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid.
    positions : xarray.Dataset, optional
        Probe axes as returned by :func:`thief_positions`. Default: the pattern of
        :func:`thief_positions` over ``fill`` (or over the cells holding material), taking
        the first element along any non-spatial dim (the first snapshot or phase 0).
    radius : float, optional
        Probe radius in metres; default 1.5 grid cells (the larger horizontal spacing).
    n_depths : int
        Number of equal-height slabs along each probe.

    Returns
    -------
    xarray.DataArray
        Sample concentrations with dims ``(..., thief)`` or ``(..., thief, depth)``; depth 0
        is the top slab. NaN for a probe (or slab) without material.
    """
    spatial = _check_field(c)
    horizontal = [d for d in spatial if d != "y"]
    if not isinstance(n_depths, int | np.integer) or n_depths < 1:
        raise ValueError(f"n_depths must be a positive whole number, got {n_depths!r}")
    spacings = {d: _spacing(c, d) for d in spatial}
    if radius is None:
        radius = 1.5 * max(spacings[d] for d in horizontal)
    else:
        radius = _positive("radius", radius)
    if positions is None:
        base = c.notnull() if fill is None else _match_fill(fill, c)
        base = base.isel({d: 0 for d in base.dims if d not in spatial})
        positions = thief_positions(base.reset_coords(drop=True))
    if isinstance(positions, xr.DataArray) or not isinstance(positions, Mapping):
        raise ValueError("positions must be an xarray.Dataset like thief_positions returns")
    missing = [d for d in horizontal if d not in positions]
    if missing:
        raise ValueError(f"positions lack the coordinates {missing} of the probe axes")

    c = _as_float(c)
    w = _weights(c, fill)
    inside = None
    nearest = None
    for d in horizontal:
        grid = c[d].reset_coords(drop=True)
        gap = grid - _as_float(positions[d].reset_coords(drop=True))
        sq = gap**2
        inside = sq if inside is None else inside + sq
        # Nearest column: within half a cell; the allowance keeps both columns on a tie.
        near = abs(gap) <= 0.5 * spacings[d] * (1 + 1e-9)
        nearest = near if nearest is None else nearest & near
    mask = ((inside <= radius**2 * (1 + 1e-9)) | nearest).astype(np.float64)
    # Contract over the horizontal dims without forming the (..., x, y, z, thief) product.
    num_y = xr.dot(w * c.fillna(0.0), mask, dim=horizontal)
    den_y = xr.dot(w, mask, dim=horizontal)

    if n_depths == 1:
        num = num_y.sum("y")
        den = den_y.sum("y")
        out = num / den.where(den > 0)
    else:
        hy = spacings["y"]
        y = _as_float(c["y"].reset_coords(drop=True))
        has = den_y > 0
        top = y.where(has).max("y") + 0.5 * hy
        bottom = y.where(has).min("y") - 0.5 * hy
        slab = (top - bottom) / n_depths
        index = np.floor((top - y) / slab).clip(0, n_depths - 1)
        parts = []
        for k in range(n_depths):
            sel = index == k
            num = num_y.where(sel, 0.0).sum("y")
            den = den_y.where(sel, 0.0).sum("y")
            parts.append(num / den.where(den > 0))
        out = xr.concat(parts, dim=xr.DataArray(np.arange(n_depths), dims="depth", name="depth"))
        out["depth"].attrs = {"long_name": "slab along the probe, 0 at the top", "units": "1"}
    lead = [d for d in out.dims if d not in ("thief", "depth")]
    out = out.transpose(*lead, "thief", ...)
    out = out.assign_coords(
        {f"thief_{d}": positions[d].reset_coords(drop=True) for d in horizontal}
    )
    return _finish(
        out,
        "c_thief",
        "concentration of thief probe samples",
        probe_radius=radius,
    )


def thief_rsd(c, fill=None, **kw):
    """RSD over virtual thief samples, eq. (31)-(32) over the M probe samples.

    Parameters
    ----------
    c : xarray.DataArray
        Concentration, dims ``(..., x, y[, z])``.
    fill : xarray.DataArray, optional
        Material volume fraction on the same grid.
    **kw
        ``positions``, ``radius``, ``n_depths`` of :func:`thief_samples`.

    Returns
    -------
    xarray.DataArray
        RSD of the probe samples (every probe, and every slab with ``n_depths > 1``, is one
        sample) with the non-spatial dims of ``c``.
    """
    samples = thief_samples(c, fill=fill, **kw)
    dims = [d for d in ("thief", "depth") if d in samples.dims]
    v = samples.reset_coords(drop=True)
    mean, var = _moments(v, v.notnull().astype(np.float64), dims)
    out = np.sqrt(var) / mean.where(mean != 0)
    return _finish(out, "thief_rsd", "relative standard deviation of thief samples")
