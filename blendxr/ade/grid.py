"""The ADE grid and the maps from a flow grid onto it.

The ADE grid is uniform and cell-centred, covers the flow grid's extent and adds one
empty cell on every side (kernels never update the outermost layer). Fields move from
the flow grid to the ADE grid by separable linear interpolation (trilinear in 3-D).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

__all__ = [
    "AdeGrid",
    "AxisMap",
    "extend_into_empty",
    "interpolate",
    "interpolate_fields_into",
    "interpolate_into",
]


@dataclass(frozen=True)
class AdeGrid:
    """A uniform cell-centred grid.

    Attributes
    ----------
    coords : tuple of ndarray
        Cell centres along x, y (and z), metres.
    spacing : tuple of float
        Cell size along each axis, metres.
    """

    coords: tuple
    spacing: tuple

    @property
    def ndim(self) -> int:
        return len(self.coords)

    @property
    def shape(self) -> tuple:
        return tuple(len(c) for c in self.coords)

    @property
    def dims(self) -> tuple:
        return ("x", "y", "z")[: self.ndim]

    @property
    def cell_volume(self) -> float:
        return float(np.prod(self.spacing))

    @staticmethod
    def covering_shape(lows, highs, cells) -> tuple[int, ...]:
        """The shape :meth:`covering` gives (padding included), without building it."""
        lengths = np.asarray(highs, float) - np.asarray(lows, float)
        if np.isscalar(cells) or np.ndim(cells) == 0:
            h = float(lengths.max()) / int(cells)
            counts = np.maximum(np.ceil(lengths / h - 1e-9).astype(np.int64), 1)
        else:
            counts = np.asarray(cells, np.int64)
            if counts.shape != lengths.shape:
                raise ValueError(f"cells: {len(counts)} values given for a {len(lengths)}-D flow")
        return tuple(int(n) + 2 for n in counts)

    @classmethod
    def covering(cls, lows, highs, cells) -> AdeGrid:
        """A grid over the box [lows, highs] plus one padding cell on every side.

        Parameters
        ----------
        lows, highs : sequence of float
            The box to cover, per axis.
        cells : int or sequence of int
            An int gives cubic cells, that many along the longest axis; a sequence gives
            the number of cells per axis.
        """
        lows = np.asarray(lows, float)
        lengths = np.asarray(highs, float) - lows
        counts = np.array(AdeGrid.covering_shape(lows, highs, cells)) - 2  # without padding
        if np.isscalar(cells) or np.ndim(cells) == 0:
            spacing = np.full(len(lengths), float(lengths.max()) / int(cells))
        else:
            spacing = lengths / counts
        coords = []
        for lo, length, n, h in zip(lows, lengths, counts, spacing, strict=True):
            centre = lo + 0.5 * length
            # n cells centred on the box, plus one padding cell each side
            first = centre - 0.5 * (n - 1) * h - h
            coords.append(first + h * np.arange(n + 2))
        return cls(tuple(coords), tuple(float(h) for h in spacing))


@dataclass(frozen=True)
class AxisMap:
    """Linear interpolation weights from one source axis onto one target axis."""

    lower: np.ndarray  # source index below each target point
    weight: np.ndarray  # weight of the upper neighbour
    inside: np.ndarray  # target point lies within the source grid's cells

    @classmethod
    def between(cls, source: np.ndarray, target: np.ndarray) -> AxisMap:
        source = np.asarray(source, float)
        n = len(source)
        h = source[1] - source[0]
        s = (np.asarray(target, float) - source[0]) / h
        inside = (s >= -0.5 - 1e-9) & (s <= n - 0.5 + 1e-9)
        s = np.clip(s, 0.0, n - 1.0)
        lower = np.minimum(np.floor(s).astype(np.intp), n - 2)
        return cls(lower, s - lower, inside)


def interpolate(values: np.ndarray, maps: tuple) -> np.ndarray:
    """Separable linear interpolation of a source array through per-axis maps.

    Points beyond the outermost source centres take the nearest value (constant
    extrapolation), which is what cell-centred data means up to the cell faces.
    """
    out = np.asarray(values, float)
    for axis, m in enumerate(maps):
        lo = np.take(out, m.lower, axis=axis)
        hi = np.take(out, m.lower + 1, axis=axis)
        shape = [1] * out.ndim
        shape[axis] = len(m.weight)
        w = m.weight.reshape(shape)
        out = lo + w * (hi - lo)
    return out


@njit(parallel=True, cache=True)
def _lerp_last_axis(src, l2, w2, out):
    """out[f, a, b, k] = src[f, a, b] linearly interpolated at target k of the last axis."""
    n_fields, n0, n1, _ = src.shape
    for a in prange(n0):
        for f in range(n_fields):
            for b in range(n1):
                s = src[f, a, b]
                o = out[f, a, b]
                for k in range(l2.size):
                    c = l2[k]
                    o[k] = s[c] + w2[k] * (s[c + 1] - s[c])


@njit(parallel=True, cache=True)
def _lerp_middle_axis(src, l1, w1, out):
    """out[f, a, j] = src[f, a] linearly interpolated at target j of the middle axis."""
    n_fields, n0 = src.shape[0], src.shape[1]
    for a in prange(n0):
        for f in range(n_fields):
            for j in range(l1.size):
                b, wb = l1[j], w1[j]
                lo, hi, o = src[f, a, b], src[f, a, b + 1], out[f, a, j]
                for k in range(o.size):
                    o[k] = lo[k] + wb * (hi[k] - lo[k])


@njit(parallel=True, cache=True)
def _lerp_first_axis(src, l0, w0, lows, highs, keep, out):
    """The last pass: along the first axis, clipped per field, zero outside ``keep``."""
    n_fields = src.shape[0]
    for i in prange(l0.size):
        a, wa = l0[i], w0[i]
        for f in range(n_fields):
            low, high = lows[f], highs[f]
            for j in range(out.shape[2]):
                lo, hi, o, inside = src[f, a, j], src[f, a + 1, j], out[f, i, j], keep[i, j]
                for k in range(o.size):
                    value = min(max(lo[k] + wa * (hi[k] - lo[k]), low), high)
                    o[k] = value if inside[k] != 0 else 0.0


def _trilinear_fields(src, l0, w0, l1, w1, l2, w2, lows, highs, keep, out, work=None):
    """Trilinear interpolation of several fields, one axis at a time (z, then y, then x).

    Each pass does the lerps of one axis once for every point the next pass reads, not
    once per target cell and corner: a quarter of the arithmetic of a per-cell loop (for
    a target grid twice as fine as the source) in loops that run along rows. Each target
    value is formed by the same operations in the same order as the per-cell formula
    (the lerp along z of each corner, then y, then x), so the result is the same bits.
    ``work`` keeps the passes' buffers between calls (see :func:`interpolate_fields_into`).
    """
    n_fields, n0, n1, _ = src.shape
    along_z = _work_buffer(work, "along_z", (n_fields, n0, n1, l2.size))
    _lerp_last_axis(src, l2, w2, along_z)
    along_yz = _work_buffer(work, "along_yz", (n_fields, n0, l1.size, l2.size))
    _lerp_middle_axis(along_z, l1, w1, along_yz)
    _lerp_first_axis(along_yz, l0, w0, lows, highs, keep, out)


def _work_buffer(work: dict | None, name: str, shape: tuple) -> np.ndarray:
    """A float64 buffer of this shape from ``work`` (made and kept there when missing or
    of another shape); a new one each call without ``work``."""
    if work is None:
        return np.empty(shape)
    buffer = work.get(name)
    if buffer is None or buffer.shape != shape:
        buffer = work[name] = np.empty(shape)
    return buffer


@njit(parallel=True, cache=True)
def _bilinear_fields(src, l0, w0, l1, w1, lows, highs, keep, out):
    n_fields = src.shape[0]
    for i in prange(l0.size):
        a, wa = l0[i], w0[i]
        for j in range(l1.size):
            b, wb = l1[j], w1[j]
            inside = keep[i, j] != 0
            for f in range(n_fields):
                s = src[f]
                lo = s[a, b] + wb * (s[a, b + 1] - s[a, b])
                hi = s[a + 1, b] + wb * (s[a + 1, b + 1] - s[a + 1, b])
                value = min(max(lo + wa * (hi - lo), lows[f]), highs[f])
                out[f, i, j] = value if inside else 0.0


def interpolate_fields_into(
    fields: np.ndarray, maps: tuple, keep: np.ndarray, bounds, out: np.ndarray, work=None
) -> np.ndarray:
    """Several fields interpolated in one pass, clipped, zero outside ``keep``.

    The same separable linear interpolation as :func:`interpolate` per field (same
    order of operations), with each target cell's weights found once for all fields;
    ``out`` may be float32 (the values are rounded once, at the end).

    Parameters
    ----------
    fields : ndarray, shape (n_fields, *source shape)
        Source fields on the flow grid.
    maps : tuple of AxisMap
        One per axis.
    keep : ndarray of uint8 or bool, target shape
        Cells that receive values; the others get 0.
    bounds : sequence of (low, high)
        Per field, the range the interpolated value is clipped to.
    out : ndarray, shape (n_fields, *target shape)
        Receives the fields.
    work : dict, optional
        Holds the 3-D passes' intermediate buffers between calls (one dict per thread
        that calls): fresh pages of tens of MB each call cost more in page faults than
        the passes themselves.
    """
    src = np.ascontiguousarray(fields, dtype=np.float64)
    lows = np.array([b[0] for b in bounds], float)
    highs = np.array([b[1] for b in bounds], float)
    args = []
    for m in maps:
        args += [m.lower, m.weight]
    keep = keep.view(np.uint8) if keep.dtype == bool else keep
    if src.ndim == 4:
        _trilinear_fields(src, *args, lows, highs, keep, out, work)
    else:
        _bilinear_fields(src, *args, lows, highs, keep, out)
    return out


def interpolate_into(values: np.ndarray, maps: tuple, out: np.ndarray) -> np.ndarray:
    """Compiled separable linear interpolation of one field into ``out`` (the same result
    as :func:`interpolate`, its NumPy twin, in the same order of operations per axis)."""
    keep = np.ones(out.shape, np.uint8)
    interpolate_fields_into(np.asarray(values)[None], maps, keep, [(-np.inf, np.inf)],
                            out[None])  # fmt: skip
    return out


def inside_mask(maps: tuple) -> np.ndarray:
    """Target cells whose centre lies within the source grid's extent."""
    mask = np.ones([len(m.inside) for m in maps], bool)
    for axis, m in enumerate(maps):
        shape = [1] * len(maps)
        shape[axis] = len(m.inside)
        mask &= m.inside.reshape(shape)
    return mask


@njit(parallel=True, cache=True)
def _extend_layer(out, known, allowed, dims, strides, out_new, known_new):
    """One layer of :func:`extend_into_empty` on flat arrays (double-buffered)."""
    ndim = dims.size
    for p in prange(out.size):
        out_new[p] = out[p]
        known_new[p] = known[p]
        if known[p] != 0 or allowed[p] == 0:
            continue
        total = 0.0
        count = 0.0
        for axis in range(ndim):
            step = strides[axis]
            index = (p // step) % dims[axis]
            # the same neighbours in the same order as the NumPy twin's rolls
            if index > 0 and known[p - step] != 0:
                total += out[p - step]
                count += 1.0
            if index < dims[axis] - 1 and known[p + step] != 0:
                total += out[p + step]
                count += 1.0
        if count > 0.0:
            out_new[p] = total / count
            known_new[p] = 1


def extend_into_empty(field: np.ndarray, known: np.ndarray, allowed: np.ndarray, layers: int = 2):
    """Extend a field from known cells into neighbouring unknown cells, layer by layer.

    Each new layer takes the mean of its known face neighbours. Velocities are extended a
    couple of cells beyond the material so that face velocities at a free surface are
    those of the material, not half of them, and so that linear interpolation onto a finer
    grid does not drag the surface velocity towards zero. Compiled; its NumPy twin is
    :func:`blendxr.ade.reference.extend_into_empty`.

    Parameters
    ----------
    field : ndarray
        Values, trusted where ``known``.
    known, allowed : ndarray of bool
        Cells with trusted values; cells that may receive extended values (the vessel).
    layers : int
        How many cell layers to extend.
    """
    shape = np.shape(field)
    out = np.ascontiguousarray(np.where(known, field, 0.0), dtype=np.float64).reshape(-1)
    mask = np.ascontiguousarray(known, dtype=np.uint8).reshape(-1)
    allowed = np.ascontiguousarray(allowed, dtype=np.uint8).reshape(-1)
    dims = np.asarray(shape, np.int64)
    strides = np.asarray([int(np.prod(shape[axis + 1 :])) for axis in range(len(shape))], np.int64)
    out_new, mask_new = np.empty_like(out), np.empty_like(mask)
    for _ in range(layers):
        _extend_layer(out, mask, allowed, dims, strides, out_new, mask_new)
        out, out_new = out_new, out
        mask, mask_new = mask_new, mask
    return out.reshape(shape)
