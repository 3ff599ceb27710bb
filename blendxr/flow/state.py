"""The solver's state: the material points and the background grid they move on."""

from __future__ import annotations

import numpy as np

from . import kernels as mpm
from . import mohr_coulomb as mc

GRID_PADDING = 3  # empty nodes around the vessel's bounding box (B-spline support + margin)
_MIRROR = np.array([1.0, 1.0, -1.0])  # z -> -z


class Particles:
    """Particle arrays of one run (structure of arrays, float64)."""

    FIELDS = ("x", "v", "C", "stress", "gap", "mass", "vol0", "vol", "J", "colour")

    def __init__(self, positions: np.ndarray, volume: float, density: float, mirror=False):
        n, d = positions.shape
        # a mirror-symmetric run keeps the colour of each particle's image too
        self.fields = self.FIELDS + (("image_colour",) if mirror else ())
        self.ndim = d
        self.x = np.ascontiguousarray(positions, dtype=float)
        self.v = np.zeros((n, d))
        self.C = np.zeros((n, d, d))  # also the velocity gradient (MLS-MPM)
        self.stress = np.zeros((n, 3, 3))
        self.gap = np.zeros(n)  # volume lost to contact (mohr_coulomb.close_gap)
        self.vol0 = np.full(n, float(volume))
        self.vol = self.vol0.copy()
        self.J = np.ones(n)
        self.mass = self.vol0 * density
        self.colour = np.zeros(n)
        self.image_colour = np.zeros(n) if mirror else None
        self.codes = np.zeros(n, np.int8)
        self._spares: dict[str, np.ndarray] = {}  # permute's second buffers

    @property
    def count(self) -> int:
        return self.x.shape[0]

    @property
    def nbytes(self) -> int:
        """Bytes of every per-particle array (the return codes included)."""
        return sum(a.nbytes for a in self.arrays().values()) + self.codes.nbytes

    @property
    def volume_over_seeded(self) -> float:
        """The particles' current volume (J times the seeded) over their seeded volume."""
        return float(self.vol.sum() / self.vol0.sum())

    def permute(self, order: np.ndarray) -> None:
        """Reorder every particle array by ``order`` (a permutation of the particles).

        Each array is gathered into a spare of its shape, which then takes its place,
        the old array becoming the next spare: double-buffered, so that a re-sort
        allocates nothing after the first.
        """
        spares = self._spares
        for name in self.fields:
            current = getattr(self, name)
            spare = spares.get(name)
            if spare is None or spare.shape != current.shape:
                spare = np.empty_like(current)
            n = current.shape[0]
            mpm.gather_rows(current.reshape(n, -1), order, spare.reshape(n, -1))
            setattr(self, name, spare)
            spares[name] = current

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: getattr(self, name) for name in self.fields}

    def load(self, arrays: dict) -> None:
        for name in self.fields:
            setattr(self, name, np.ascontiguousarray(arrays[name]))
        self.codes = np.zeros(self.x.shape[0], np.int8)


class BackgroundGrid:
    """Nodes at ``origin + i h`` covering the vessel, with wall distances precomputed.

    The vessel does not move in its own frame, so the signed distance and the outward
    normal at every node are computed once. With ``mirror`` the grid covers z >= 0 plus
    ``GRID_PADDING`` ghost node planes below (``mirror_index`` is the plane z = 0).
    """

    def __init__(self, vessel, h: float, threads: int, mirror: bool = False):
        lower, upper = (np.asarray(b, float) for b in vessel.bounds)
        if mirror:
            lower[2] = 0.0
        self.h = float(h)
        self.ndim = vessel.ndim
        self.origin = (np.floor(lower / h) - GRID_PADDING) * h
        top = (np.ceil(upper / h) + GRID_PADDING) * h
        self.shape = tuple(int(round(n)) + 1 for n in (top - self.origin) / h)
        self.mirror_index = GRID_PADDING if mirror else -1
        # nodes at h times whole numbers: mirror-image nodes get bitwise mirror-image
        # coordinates (origin + i h would not), so their wall distances are equal too and
        # no wall-band test or face tie is decided differently on the two sides
        first = np.round(self.origin / h).astype(np.int64)
        axes = [h * np.arange(first[a], first[a] + n) for a, n in enumerate(self.shape)]
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        self.node_sdf = np.ascontiguousarray(vessel.sdf(nodes))
        self.node_normal = np.ascontiguousarray(vessel.normal(nodes))
        self.scratch = np.zeros((threads, 4))
        self.shape_array = np.asarray(self.shape, np.int64)
        self.threads = threads
        # per-thread P2G grids: each node's mass and momentum side by side
        self.thread_grids = np.zeros((threads, *self.shape, self.ndim + 1))
        self.mass = np.zeros(self.shape)
        self.momentum = np.zeros((*self.shape, self.ndim))
        self.velocity = np.zeros((*self.shape, self.ndim))
        self.g2p_work = mpm.g2p_work(threads) if self.ndim == 3 else mc.batch_work(threads, 1)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.thread_grids, self.mass, self.momentum, self.velocity))
