"""The paper's Lax-Wendroff scheme (eq. 6-24) behind the :class:`Scheme` interface.

State: the colour concentration c and its double buffer. A cell is material where the
flow's blended fill reaches :data:`MATERIAL_THRESHOLD`; interior cells (their whole box
material) take the stencil, clipped to [0, 1], and surface cells copy the value one cell
inward (the paper's free-surface rule). The kernels are in :mod:`blendxr.ade.kernels`.
"""

from __future__ import annotations

import numpy as np

from .. import kernels
from .base import BOUND_TOLERANCE, Scheme

#: a cell is material when its interpolated fill reaches this fraction
MATERIAL_THRESHOLD = 0.5


class LaxWendroff(Scheme):
    """Second-order Taylor finite differences for c (the paper's scheme)."""

    name = "lax-wendroff"
    least_fill = MATERIAL_THRESHOLD
    state_fields = ("c",)

    def __init__(self, grid, vessel, with_diffusion):
        super().__init__(grid, vessel, with_diffusion)
        shape = grid.shape
        self.c = np.zeros(shape)
        self.c_next = np.zeros(shape)
        self.plan = kernels.LaxWendroffPlan(shape)
        self.fill = np.zeros(shape)
        self.material = np.zeros(shape, np.uint8)
        self._active = 0

    # --- state ---------------------------------------------------------------
    def initialise(self, fill, c0):
        self.c[...] = c0

    # --- per phase pair, per refresh, per step -------------------------------
    def max_dt(self, a, b):
        material = (a.fill >= MATERIAL_THRESHOLD) | (b.fill >= MATERIAL_THRESHOLD)
        pair = kernels.lw_max_dt_pair_3d if self.ndim == 3 else kernels.lw_max_dt_pair_2d
        return float(
            pair(
                a.vel,
                self.diffusivity_of(a),
                b.vel,
                self.diffusivity_of(b),
                material.view(np.uint8),
                *self.grid.spacing,
            )  # fmt: skip
        )

    def blend_fields(self, a, b, w):
        # the fill (material mask and surface normals) at the block's time
        kernels.lerp_into(self.fill.reshape(-1), a.fill.reshape(-1), b.fill.reshape(-1), w)
        np.greater_equal(self.fill, MATERIAL_THRESHOLD, out=self.material.view(bool))
        self.plan.classify(self.material)

    def prepare_step(self, a, b, w, dt, limit):
        # velocity and diffusivity are blended inside the coefficient kernel
        self.plan.coefficients_between(
            a.vel, b.vel, self.diffusivity_of(a), self.diffusivity_of(b), w, dt,
            self.grid.spacing,
        )  # fmt: skip
        np.copyto(self.c_next, self.c)  # cells the stencil skips stay equal in both
        self._active = self.plan.interior_cells()

    def step(self):
        self.plan.apply(self.c, self.c_next)
        self.plan.surface(self.c_next, self.fill)
        self.c, self.c_next = self.c_next, self.c

    def active_cells(self, steps):
        return self._active

    # --- what records and checks read ----------------------------------------
    def concentration(self, fill):
        material = fill >= MATERIAL_THRESHOLD
        return np.where(material, self.c, np.nan), np.where(material, fill, 0.0)

    def species(self, c, weight):
        return float(np.nansum(c * weight))

    def faults(self):
        c = self.c
        bad = ~np.isfinite(c) | (c < -BOUND_TOLERANCE) | (c > 1 + BOUND_TOLERANCE)
        return bad, c
