"""The conservative bounded finite-volume scheme behind the :class:`Scheme` interface.

State: the material volume fraction m and the species content q = m c, updated in place
(each block of lines is buffered in its thread's scratch, so cells away from material
are never touched); dimension-split sweeps whose order alternates every step (Strang-like
symmetry over two steps). Material moves only among cells the flow fills (blended fill
above :data:`SUPPORT_FILL`); no flux crosses the free surface into cells the flow leaves
empty. Explicit diffusion runs as sub-steps inside each sweep, as many as
``D dt_sub / h**2 <= 1/2`` needs. The kernels are in :mod:`blendxr.ade.kernels`.
"""

from __future__ import annotations

import math

import numpy as np

from .. import kernels, stability
from .base import BOUND_TOLERANCE, Scheme

#: c is defined where the carried material fraction exceeds this
M_MIN = 1e-9
#: material moves only among cells the flow fills (blended fill above this)
SUPPORT_FILL = 1e-9
#: the count of cells holding material is refreshed every this many steps (it is only
#: the throughput figure's denominator)
COUNT_EVERY = 50


class FiniteVolume(Scheme):
    """Flux-form transport of m and q = m c (conservative, bounded without clipping)."""

    name = "finite-volume"
    least_fill = M_MIN
    state_fields = ("m", "q")

    def __init__(self, grid, vessel, with_diffusion):
        super().__init__(grid, vessel, with_diffusion)
        shape = grid.shape
        self.m = np.zeros(shape)
        self.q = np.zeros(shape)
        self.work = kernels.fv_workspace(shape)
        self.reverse = False
        self.support = vessel.copy()
        # the velocities advanced half a step along their own axes
        self.transport = tuple(np.zeros(shape) for _ in range(self.ndim))
        self.dif = np.zeros((self.ndim, *shape)) if with_diffusion else None
        # the step's diffusivity arguments, made once (zeros without diffusion)
        self._dif_args = tuple(self.dif if self.dif is not None else self.zero_stack())
        self.n_sub = 0
        self._active = None

    # --- state ---------------------------------------------------------------
    def initialise(self, fill, c0):
        self.m[...] = np.where(self.vessel, fill, 0.0)
        self.q[...] = self.m * c0

    def state_meta(self):
        return {"reverse": int(self.reverse)}

    def load_meta(self, meta):
        self.reverse = bool(meta["reverse"])

    # --- per phase pair, per refresh, per step -------------------------------
    def max_dt(self, a, b):
        return float(
            kernels.fv_max_dt_pair(a.vel, b.vel, self.vessel, np.asarray(self.grid.spacing))
        )

    def begin_interval(self, a, b, dt):
        """Diffusion sub-steps of one step, refused above
        :data:`~blendxr.ade.schemes.base.MAX_DIFFUSION_SUBSTEPS`."""
        if not self.with_diffusion:
            self.n_sub = 0
            return 0
        # the largest diffusivity of any blend of a and b is the larger of their largest
        dmax = tuple(np.full((1,) * self.ndim, d) for d in np.maximum(a.dif_max, b.dif_max))
        n_sub = stability.diffusion_substeps(dmax, self.grid.spacing, dt)
        self.n_sub = self.checked_substeps(n_sub, dt, "D dt / h^2 <= 1/2 along each axis")
        return self.n_sub

    def blend_fields(self, a, b, w):
        kernels.fv_support(a.fill.reshape(-1), b.fill.reshape(-1), w,
                           self.vessel.reshape(-1), SUPPORT_FILL,
                           self.support.reshape(-1))  # fmt: skip
        if self.dif is not None:
            kernels.lerp_into(self.dif.reshape(-1), a.dif.reshape(-1), b.dif.reshape(-1), w)

    def prepare_step(self, a, b, w, dt, limit):
        # face Courant numbers may grow by limit/dt at most: still within the limit
        cap = limit / dt if math.isfinite(limit) else 1.0
        for axis, out in enumerate(self.transport):
            kernels.fv_transport_velocity(a.vel[axis], out, axis, dt, self.grid.spacing[axis],
                                          cap, v_b=b.vel[axis], w=w)  # fmt: skip

    def step(self):
        step = kernels.fv_step_3d if self.ndim == 3 else kernels.fv_step_2d
        step(self.m, self.q, self.m, self.q, self.work, *self.transport,
             *self._dif_args, self.support, self._dt, *self.grid.spacing, self.reverse,
             self.n_sub)  # fmt: skip
        self.reverse = not self.reverse

    def active_cells(self, steps):
        if steps % COUNT_EVERY == 0 or self._active is None:
            self._active = int(np.count_nonzero(self.m > M_MIN))
        return self._active

    # --- what records and checks read ----------------------------------------
    def concentration(self, fill):
        c = np.empty(self.grid.shape)
        kernels.concentration(self.m, self.q, c, M_MIN)
        return c, np.where(np.isfinite(c), self.m, 0.0)

    def species(self, c, weight):
        return float(self.q.sum())  # exactly what the scheme conserves

    def fill_mismatch(self, fill):
        return float(np.abs(self.m - fill).sum() / max(self.m.sum(), 1e-300))

    def faults(self):
        c, _ = self.concentration(None)
        bad = ~np.isfinite(self.q) | ~np.isfinite(self.m) | (self.m < -BOUND_TOLERANCE)
        with np.errstate(invalid="ignore"):
            bad |= np.isfinite(c) & ((c < -BOUND_TOLERANCE) | (c > 1 + BOUND_TOLERANCE))
        return bad, c
