"""The paper's Lax-Wendroff scheme (eq. 6-24) behind the :class:`Scheme` interface.

State: the colour concentration c and its double buffer (:class:`ColourScheme`). A cell
is material where the flow's blended fill reaches ``MATERIAL_THRESHOLD``; interior cells
(their whole box material) take the stencil, clipped to [0, 1], and surface cells copy the
value one cell inward (the paper's free-surface rule). The kernels are in
:mod:`blendxr.ade.kernels`.
"""

from __future__ import annotations

import numpy as np

from .. import kernels
from .base import ColourScheme


class LaxWendroff(ColourScheme):
    """Second-order Taylor finite differences for c (the paper's scheme)."""

    name = "lax-wendroff"

    def __init__(self, grid, vessel, with_diffusion):
        super().__init__(grid, vessel, with_diffusion)
        self.plan = kernels.LaxWendroffPlan(grid.shape)

    # --- per phase pair, per refresh, per step -------------------------------
    def max_dt(self, a, b):
        pair = kernels.lw_max_dt_pair_3d if self.ndim == 3 else kernels.lw_max_dt_pair_2d
        return float(
            pair(
                a.vel,
                self.diffusivity_of(a),
                b.vel,
                self.diffusivity_of(b),
                self.material_of_pair(a, b),
                *self.grid.spacing,
            )  # fmt: skip
        )

    def blend_fields(self, a, b, w):
        # the fill (material mask and surface normals) at the block's time
        self.blend_material(a, b, w)
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
