"""Phase averaging onto the output cells, and eq. (30) between averages.

The eq. (30) helpers take the output grid (:class:`OutputGrid`): the cells, the rotation
rate and the frame of the averages, not the simulation that made them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import kernels as mpm


@dataclass(frozen=True)
class OutputGrid:
    """The output cells of a run's averages and the motion they were averaged in.

    Parameters
    ----------
    axes : tuple of ndarray
        Cell centres along x, y[, z] (m).
    omega : float
        Rotation rate of the vessel (rad/s).
    lab_frame : bool
        The averages are in the lab frame already (a drum's).
    """

    axes: tuple
    omega: float
    lab_frame: bool

    @property
    def ndim(self) -> int:
        return len(self.axes)

    @property
    def rotating(self) -> bool:
        return self.omega > 0 and not self.lab_frame


def rotation(theta: float, ndim: int) -> np.ndarray:
    """The lab-frame rotation by theta about z (counter-clockwise seen from +z)."""
    c, s = math.cos(theta), math.sin(theta)
    r = np.eye(ndim)
    r[0, 0], r[0, 1], r[1, 0], r[1, 1] = c, -s, s, c
    return r


def vessel_to_lab(x: np.ndarray, v: np.ndarray, theta: float, omega: float):
    """Positions and velocities (..., d) of the vessel frame seen from the lab, the
    vessel turned by theta at rate omega: x_lab = R x, v_lab = R (v + omega e_z x x)."""
    r = rotation(theta, x.shape[-1])
    u = v.copy()
    u[..., 0] -= omega * x[..., 1]
    u[..., 1] += omega * x[..., 0]
    return x @ r.T, u @ r.T


def lab_to_vessel(x: np.ndarray, v: np.ndarray, theta: float, omega: float):
    """The inverse of :func:`vessel_to_lab`."""
    r = rotation(theta, x.shape[-1])
    xv, u = x @ r, v @ r  # R^T, row by row
    u[..., 0] += omega * xv[..., 1]
    u[..., 1] -= omega * xv[..., 0]
    return xv, u


def _centred_in_z(origin: np.ndarray, h: float, shape: tuple) -> bool:
    """Whether an output grid's cells lie symmetric about the plane z = 0."""
    top = origin[2] + h * shape[2]
    return shape[2] % 2 == 0 and math.isclose(-origin[2], top, abs_tol=1e-9 * h)


def output_grid(vessel, h: float):
    """The flow dataset's cells for a vessel: (origin, shape, axes, vessel mask).

    Cell centres on multiples of h plus a half, one empty layer beyond the vessel's
    bounds; a cell belongs to the vessel when its centre lies inside or within half a
    cell of the wall (partly filled wall cells carry their fill and stay in the domain).
    """
    lower, upper = (np.asarray(b, float) for b in vessel.bounds)
    lo = np.floor(lower / h - 1e-9) * h - h
    hi = np.ceil(upper / h + 1e-9) * h + h
    shape = tuple(int(round(n)) for n in (hi - lo) / h)
    axes = [lo[a] + h * (np.arange(n) + 0.5) for a, n in enumerate(shape)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    inside = (vessel.sdf(centres) < 0.5 * h).astype(np.int8)
    return lo, shape, axes, inside


class PhaseAverager:
    """Accumulates particle volume and volume-weighted velocity in phase bins.

    Bin k collects the samples whose phase lies within half a bin of ``k / n``; the fill
    of a bin is its mean particle volume per cell over its samples, the velocity its
    volume-weighted mean, each particle spread over the cells around it by the solver's
    quadratic B-splines (:func:`kernels.deposit_parts_3d`), renormalised over the cells of
    ``inside`` (default: every cell) so that none of its volume lands outside. With
    ``mirror`` the particles, all at z >= 0, stand for themselves and their mirror
    images across z = 0 (a mirror-symmetric run): only the upper half of the (symmetric)
    output grid accumulates, and the fields are the whole grid's, the lower half the
    reflection of the upper.
    With ``halves``, even- and odd-numbered particles are kept apart (their sum is the
    same average): two estimates of the same field from disjoint halves of the
    particles, whose difference measures the sampling noise of the average
    (:meth:`half_fields`).
    """

    def __init__(
        self,
        lower: np.ndarray,
        shape: tuple,
        h: float,
        phases: int,
        halves=False,
        mirror=False,
        inside: np.ndarray | None = None,
    ):
        self.origin = np.array(lower, float)
        self.shape = tuple(shape)
        self.h = float(h)
        self.phases = int(phases)
        self.ndim = len(shape)
        self.mirror = bool(mirror)
        inside = np.ones(self.shape, np.int8) if inside is None else np.asarray(inside, np.int8)
        if inside.shape != self.shape:
            raise ValueError(f"inside has shape {inside.shape}, expected {self.shape}")
        if self.mirror:
            # the particles lie at z >= 0: only the upper half of the cells is kept
            if not _centred_in_z(self.origin, self.h, self.shape):
                raise ValueError("mirror: the output grid must be symmetric about z = 0")
            self.origin[2] = 0.0
            self.shape = (*shape[:2], shape[2] // 2)
            inside = inside[..., shape[2] // 2 :]
        self.inside = np.ascontiguousarray(inside)
        parts = 2 if halves else 1
        # one contiguous block per phase bin: the deposit's parts are adjacent in it
        self.vol = np.zeros((phases, parts, *self.shape))
        self.mom = np.zeros((phases, parts, *self.shape, self.ndim))
        self.samples = np.zeros(phases, np.int64)

    @property
    def nbytes(self) -> int:
        return self.vol.nbytes + self.mom.nbytes

    def bin_of(self, phase: float) -> int:
        return int(math.floor(phase * self.phases + 0.5)) % self.phases

    def add(self, k: int, x: np.ndarray, v: np.ndarray, vol: np.ndarray) -> None:
        # the halves deposit in parallel, each into its own accumulator
        out = (self.vol[k], self.mom[k])
        if self.ndim == 3:
            mpm.deposit_parts_3d(x, v, vol, self.origin, 1.0 / self.h, self.inside,
                                 self.mirror, *out)  # fmt: skip
        else:
            mpm.deposit_parts_2d(x, v, vol, self.origin, 1.0 / self.h, self.inside, *out)
        self.samples[k] += 1

    def take(self, other: PhaseAverager) -> None:
        """Hold ``other``'s averages (its halves summed when this one has none)."""
        if self.vol.shape[1] == other.vol.shape[1]:
            self.vol[...] = other.vol
            self.mom[...] = other.mom
        else:
            self.vol[:, 0] = other.vol.sum(axis=1)
            self.mom[:, 0] = other.mom.sum(axis=1)
        self.samples[...] = other.samples

    def clear(self) -> None:
        self.vol[...] = 0.0
        self.mom[...] = 0.0
        self.samples[...] = 0

    def complete(self) -> bool:
        """Whether every phase bin holds samples."""
        return bool(self.samples.min() > 0)

    def fields(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(fill, velocity (n, ..., d), raw fill before clipping) of every bin."""
        return self._fields(self.vol.sum(axis=1), self.mom.sum(axis=1))

    def half_fields(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`fields` of each half of the particles (each fill about half the total)."""
        parts = range(self.vol.shape[1])
        return [self._fields(2.0 * self.vol[:, q], 2.0 * self.mom[:, q]) for q in parts]

    def _fields(self, vol, mom):
        if self.mirror:
            # the lower half of the cells: the reflection of the upper half
            vol = np.concatenate([vol[..., ::-1], vol], axis=-1)
            image = mom[..., ::-1, :].copy()
            image[..., 2] *= -1.0
            mom = np.concatenate([image, mom], axis=-2)
        if np.any(self.samples == 0):
            empty = np.flatnonzero(self.samples == 0).tolist()
            raise RuntimeError(f"phase bins {empty} received no samples; use fewer phases")
        cell_volume = self.h**self.ndim
        shape = (-1,) + (1,) * self.ndim
        raw = vol / (cell_volume * self.samples.reshape(shape))
        with np.errstate(invalid="ignore", divide="ignore"):
            vel = np.where(vol[..., None] > 0, mom / vol[..., None], 0.0)
        return np.clip(raw, 0.0, 1.0), vel, raw

    def arrays(self, prefix: str) -> dict[str, np.ndarray]:
        # checkpoints hold the accumulators part first, as they always have
        return {
            f"{prefix}_vol": np.moveaxis(self.vol, 1, 0),
            f"{prefix}_mom": np.moveaxis(self.mom, 1, 0),
            f"{prefix}_n": self.samples,
        }

    def load(self, prefix: str, arrays: dict) -> None:
        self.vol[...] = np.moveaxis(arrays[f"{prefix}_vol"], 0, 1)
        self.mom[...] = np.moveaxis(arrays[f"{prefix}_mom"], 0, 1)
        self.samples[...] = arrays[f"{prefix}_n"]


def periodicity(v_prev: np.ndarray, v_last: np.ndarray, fill_prev, fill_last, floor=0.05):
    """Eq. (30): mean relative change of each velocity component between revolutions.

    ``mean_n |(v_n^j - v_n^{j+1}) / v_n^j|`` over the cells holding material in both
    revolutions (fill > 0.5), per component. Eq. (30) divides by the local velocity, which
    is unbounded where a component passes through zero, so cells where ``|v^j|`` is below
    ``floor`` times that component's largest magnitude are left out (stated in the
    output). Also returned: the norm form ``sum |dv| / sum |v|`` over the same cells.
    """
    mask = (fill_prev > 0.5) & (fill_last > 0.5)
    out = {}
    names = "xyz"
    for a in range(v_prev.shape[-1]):
        vj, vk = v_prev[..., a][mask], v_last[..., a][mask]
        if vj.size == 0:
            out[f"v{names[a]}"] = float("nan")
            out[f"v{names[a]}_norm"] = float("nan")
            continue
        big = np.abs(vj) > floor * np.abs(vj).max()
        rel = np.abs((vj[big] - vk[big]) / vj[big])
        out[f"v{names[a]}"] = float(rel.mean()) if rel.size else float("nan")
        total = np.abs(vj).sum()
        out[f"v{names[a]}_norm"] = float(np.abs(vj - vk).sum() / total) if total > 0 else 0.0
    return out


def coarsen_fields(fill: np.ndarray, vel: np.ndarray, factor: int):
    """Phase-binned fields on cells ``factor`` times larger along every axis.

    Blocks of ``factor**d`` cells become one: the fill is the block's mean, the velocity
    the fill-weighted mean (the block's volume flux over its material volume), so the
    material volume and its momentum are kept exactly. The upper end of each axis is
    padded with empty cells to a whole number of blocks, so no material is dropped.
    Used to ask at which scale two flows differ: eq. (30) between revolutions on
    coarsened fields leaves out what changes within a block only.

    Parameters
    ----------
    fill : ndarray, shape (n, *cells)
        Fill (volume fraction) of each phase bin and cell.
    vel : ndarray, shape (n, *cells, d)
        Velocity of each phase bin and cell.
    factor : int
        Cells per block along each axis, >= 1.

    Returns
    -------
    fill, vel : ndarray
        The coarsened fill (n, *blocks) and velocity (n, *blocks, d); zero velocity in
        blocks without material.
    """
    factor = int(factor)
    if factor < 1:
        raise ValueError(f"factor must be a whole number >= 1, got {factor}")
    cells = fill.shape[1:]
    if vel.shape != (*fill.shape, len(cells)):
        raise ValueError(f"vel has shape {vel.shape}, expected {(*fill.shape, len(cells))}")
    pad = [(0, 0)] + [(0, -n % factor) for n in cells]
    volume = np.pad(fill, pad)
    flux = np.pad(vel * fill[..., None], pad + [(0, 0)])
    blocks = [n // factor for n in volume.shape[1:]]
    split = [volume.shape[0]] + [s for b in blocks for s in (b, factor)]
    block_axes = tuple(range(2, 2 * len(cells) + 1, 2))
    volume = volume.reshape(split).sum(axis=block_axes)
    flux = flux.reshape(split + [len(cells)]).sum(axis=block_axes)
    with np.errstate(invalid="ignore", divide="ignore"):
        coarse_vel = np.where(volume[..., None] > 0, flux / volume[..., None], 0.0)
    return volume / factor ** len(cells), coarse_vel


#: bin edges of :func:`fill_histogram` (raw fill over the seeded packing; the last bin
#: takes everything above its lower edge)
FILL_HISTOGRAM_EDGES = (0.5, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2, 1.3, 1.5)


#: cells within this many cells of the first cell outside the vessel count as "wall"
WALL_LAYERS = 2.0


def fill_histogram(raw: np.ndarray, vessel: np.ndarray) -> dict:
    """The packing histogram of the phase-averaged fill before clipping.

    Over every phase bin and every output cell whose raw fill is at least 0.5 (the
    bed), the share of those cells in each bin of :data:`FILL_HISTOGRAM_EDGES`, for all
    of them and apart for the cells next to the wall (within :data:`WALL_LAYERS` cells of
    the first cell outside the vessel) and the rest, with the share above 1.15 (the
    packing a granular bed cannot exceed by much).
    """
    from scipy.ndimage import distance_transform_edt

    depth = distance_transform_edt(np.asarray(vessel) > 0)
    wall = np.broadcast_to(depth <= WALL_LAYERS, raw.shape)
    bed = raw >= FILL_HISTOGRAM_EDGES[0]
    edges = np.array([*FILL_HISTOGRAM_EDGES, np.inf])
    out = {"fill_histogram_edges": np.array(FILL_HISTOGRAM_EDGES)}
    for label, pick in (("", bed), ("_wall", bed & wall), ("_interior", bed & ~wall)):
        values = raw[pick]
        counts = np.histogram(values, edges)[0]
        share = counts / max(values.size, 1)
        out[f"fill_histogram{label}"] = share
        out[f"fill_share_above_1_15{label}"] = float(np.mean(values > 1.15)) if values.size else 0.0
    out["fill_histogram_definition"] = (
        "share of the bed's cells (phase-averaged fill before clipping >= 0.5, every "
        "phase bin) in each bin [edge_i, edge_i+1) of fill_histogram_edges, the last "
        f"open; _wall: the cells within {WALL_LAYERS:g} cells of the first cell outside the "
        "vessel, "
        "_interior: the rest"
    )
    return out


def lab_velocities(grid: OutputGrid, vel: np.ndarray) -> np.ndarray:
    """Phase-binned vessel-frame velocities seen from the lab: R(theta_k) (v + w x r).

    Parameters
    ----------
    grid : OutputGrid
        The output cells and rotation rate the fields have.
    vel : ndarray, shape (n, *cells, d)
        Vessel-frame velocities of the n phase bins on the output cells.

    Returns
    -------
    ndarray, same shape
        The velocities in the lab frame, the vessel turned by 2 pi k / n in bin k.
    """
    out = np.empty_like(vel)
    centres = np.stack(np.meshgrid(*grid.axes, indexing="ij"), axis=-1)
    for k in range(vel.shape[0]):
        theta = 2.0 * math.pi * k / vel.shape[0]
        out[k] = vessel_to_lab(centres, vel[k], theta, grid.omega)[1]
    return out


def fields_change(grid: OutputGrid, before: tuple, after: tuple, *, vessel_frame=False) -> dict:
    """Eq. (30) (:func:`periodicity`) from one set of phase-binned fields of a run to
    another, on lab-frame velocities (the frame of the paper's fixed mesh); with
    ``vessel_frame`` also on the stored vessel-frame ones of a rotating vessel, as
    ``vessel_frame_*`` (stricter: they lack the rigid rotation).

    Parameters
    ----------
    grid : OutputGrid
        The output cells, frame and rotation rate of the fields.
    before, after : tuple of ndarray
        ``(fill, velocity)`` as :meth:`PhaseAverager.fields` gives them: one revolution's
        averages, or any fill-weighted combination of them.
    """
    (fill_b, vel_b), (fill_a, vel_a) = before, after
    out = {}
    if grid.rotating:
        if vessel_frame:
            vessel = periodicity(vel_b, vel_a, fill_b, fill_a)
            out.update({f"vessel_frame_{name}": value for name, value in vessel.items()})
        vel_b, vel_a = lab_velocities(grid, vel_b), lab_velocities(grid, vel_a)
    return {**periodicity(vel_b, vel_a, fill_b, fill_a), **out}
