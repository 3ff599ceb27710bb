"""The interface every advection scheme of the mixing model keeps.

The driver (:mod:`blendxr.ade.stepper`) plans the time steps, walks the stored phases,
records the mixing curves and checkpoints; a scheme owns its prognostic fields and does
the rest. Per stored-phase interval (phases ``a`` and ``b``) the driver asks the scheme
for its stable dt (:meth:`Scheme.max_dt`, once per pair and run, since the revolution
repeats) and for what the interval's dt costs it (:meth:`Scheme.begin_interval`); per
refresh block it passes the blend weight (:meth:`Scheme.prepare`), then it calls
:meth:`Scheme.step` once per step. At records it reads the concentration, the conserved
species content and the scheme's own checks. A new scheme is one module defining a
subclass and one line in :data:`blendxr.ade.schemes.SCHEMES`; a scheme that carries the
colour alone starts from :class:`ColourScheme` (its state, material mask and checks).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from .. import kernels
from ..grid import AdeGrid
from ..phases import PreparedPhase

#: How far outside [0, 1] a value may stray (round-off) before the run is stopped.
BOUND_TOLERANCE = 1e-6
#: At most this many diffusion sub-steps in one step (schemes that sub-cycle diffusion).
MAX_DIFFUSION_SUBSTEPS = 1000


class Scheme(ABC):
    """One advection(-diffusion) scheme on one ADE grid.

    Parameters
    ----------
    grid : AdeGrid
        The ADE grid.
    vessel : ndarray of uint8
        1 in the cells inside the vessel.
    with_diffusion : bool
        Whether the run has a diffusivity (False: k1 = k2 = 0 and no constant D; the
        scheme then does no diffusion work at all).
    """

    #: the name users give (``numerics.scheme``)
    name: ClassVar[str]
    #: the least blended fill the scheme counts as material (c is undefined below it)
    least_fill: ClassVar[float]
    #: the prognostic arrays a checkpoint holds (attributes of the scheme)
    state_fields: ClassVar[tuple[str, ...]]

    def __init__(self, grid: AdeGrid, vessel: np.ndarray, with_diffusion: bool):
        self.grid = grid
        self.ndim = grid.ndim
        self.vessel = vessel
        self.with_diffusion = with_diffusion
        self._zeros: np.ndarray | None = None
        self._fields = None  # (index of a, index of b, w) of the prepared flow
        self._dt = None  # the dt the per-cell data were prepared for

    # --- state ---------------------------------------------------------------
    @abstractmethod
    def initialise(self, fill: np.ndarray, c0: np.ndarray) -> None:
        """Set the state from the flow's fill at t = 0 and the initial colour ``c0``."""

    def state(self) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """The arrays (:attr:`state_fields`) and scalars a checkpoint must hold to resume
        bit-identically."""
        return {name: getattr(self, name) for name in self.state_fields}, self.state_meta()

    def state_meta(self) -> dict[str, float]:
        """Scalars of the state besides its arrays (none by default)."""
        return {}

    def load_state(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        """Restore what :meth:`state` returned."""
        for name in self.state_fields:
            getattr(self, name)[...] = arrays[name]
        self.load_meta(meta)

    def load_meta(self, meta: dict) -> None:
        """Restore what :meth:`state_meta` returned (nothing by default)."""
        return None

    # --- per phase pair, per refresh, per step -------------------------------
    @abstractmethod
    def max_dt(self, a: PreparedPhase, b: PreparedPhase) -> float:
        """The largest dt stable for every blend of phases ``a`` and ``b``."""

    def begin_interval(self, a: PreparedPhase, b: PreparedPhase, dt: float) -> int:
        """Set up an interval stepped with ``dt``; returns its diffusion sub-steps (0:
        none, or diffusion is part of the step). Raises ValueError when the interval
        cannot be stepped at that dt."""
        return 0

    def prepare(self, a: PreparedPhase, b: PreparedPhase, w: float, dt: float,
                limit: float) -> None:  # fmt: skip
        """Make the per-cell data of the flow at weight ``w`` between ``a`` and ``b``
        (piecewise constant over the steps that follow) for steps of ``dt``; ``limit``
        is the pair's :meth:`max_dt`. Work is redone only for what changed: the blended
        fields when the phases or the weight change, the step's data when dt does too."""
        w = 0.0 if a is b else w
        fields = (a.index, b.index, w)
        changed = fields != self._fields
        if changed:
            self.blend_fields(a, b, w)
            self._fields = fields
        if changed or dt != self._dt:
            self.prepare_step(a, b, w, dt, limit)
            self._dt = dt

    @abstractmethod
    def blend_fields(self, a: PreparedPhase, b: PreparedPhase, w: float) -> None:
        """What the scheme keeps of the flow at weight ``w`` (independent of dt)."""

    @abstractmethod
    def prepare_step(self, a: PreparedPhase, b: PreparedPhase, w: float, dt: float,
                     limit: float) -> None:  # fmt: skip
        """The per-cell data of a step of ``dt`` (after :meth:`blend_fields`)."""

    @abstractmethod
    def step(self) -> None:
        """Advance one step of the prepared dt."""

    @abstractmethod
    def active_cells(self, steps: int) -> int:
        """The cells the last step updated (the throughput figure's count); ``steps``:
        the run's steps before it."""

    # --- what records and checks read ----------------------------------------
    @abstractmethod
    def concentration(self, fill: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """c (NaN where no material) and its weight, given the flow's fill now."""

    @abstractmethod
    def species(self, c: np.ndarray, weight: np.ndarray) -> float:
        """The species content the scheme carries, in cell volumes."""

    def fill_mismatch(self, fill: np.ndarray) -> float:
        """How far the carried material is from the flow's fill (0: the scheme carries
        none of its own)."""
        return 0.0

    @abstractmethod
    def faults(self) -> tuple[np.ndarray, np.ndarray]:
        """(bad, values): cells whose state is non-finite or out of bounds, and the
        values to report for them."""

    # --- helpers ------------------------------------------------------------
    @staticmethod
    def checked_substeps(n_sub: int, dt: float, rule: str) -> int:
        """``n_sub``, or a ValueError naming ``rule`` (the explicit limit the count was
        made from) above :data:`MAX_DIFFUSION_SUBSTEPS`."""
        if n_sub > MAX_DIFFUSION_SUBSTEPS:
            raise ValueError(
                f"the diffusivity needs {n_sub} sub-steps in one step of {dt:.3g} s "
                f"(explicit diffusion is stable for {rule}); at most "
                f"{MAX_DIFFUSION_SUBSTEPS}: lower mixing.k1 and mixing.k2, or use fewer "
                "numerics.cells"
            )
        return n_sub

    def zero_stack(self) -> np.ndarray:
        """Zeros of shape (ndim, *grid shape): the diffusivity of a run without one."""
        if self._zeros is None:
            self._zeros = np.zeros((self.ndim, *self.grid.shape))
        return self._zeros

    def diffusivity_of(self, phase: PreparedPhase) -> np.ndarray:
        return phase.dif if phase.dif is not None else self.zero_stack()


class ColourScheme(Scheme):
    """A scheme that carries the colour c alone (not the material), in the cells where the
    flow's blended fill reaches :attr:`MATERIAL_THRESHOLD`: the state, the material mask
    and what records and checks read. Species content is not conserved by such a scheme;
    the driver reports its drift."""

    #: a cell is material when its blended fill reaches this fraction
    MATERIAL_THRESHOLD: ClassVar[float] = 0.5
    least_fill = MATERIAL_THRESHOLD
    state_fields = ("c",)

    def __init__(self, grid: AdeGrid, vessel: np.ndarray, with_diffusion: bool):
        super().__init__(grid, vessel, with_diffusion)
        shape = grid.shape
        self.c = np.zeros(shape)
        self.c_next = np.zeros(shape)
        self.fill = np.zeros(shape)
        self.material = np.zeros(shape, np.uint8)
        self._active = 0

    def initialise(self, fill, c0):
        self.c[...] = c0

    def material_of_pair(self, a: PreparedPhase, b: PreparedPhase) -> np.ndarray:
        """uint8 mask of the cells that are material in either phase (every blend's)."""
        both = (a.fill >= self.MATERIAL_THRESHOLD) | (b.fill >= self.MATERIAL_THRESHOLD)
        return both.view(np.uint8)

    def blend_material(self, a: PreparedPhase, b: PreparedPhase, w: float) -> None:
        """The blended fill and its material mask at weight ``w``."""
        kernels.lerp_into(self.fill.reshape(-1), a.fill.reshape(-1), b.fill.reshape(-1), w)
        np.greater_equal(self.fill, self.MATERIAL_THRESHOLD, out=self.material.view(bool))

    def active_cells(self, steps):
        return self._active

    def concentration(self, fill):
        material = fill >= self.MATERIAL_THRESHOLD
        return np.where(material, self.c, np.nan), np.where(material, fill, 0.0)

    def species(self, c, weight):
        return float(np.nansum(c * weight))

    def faults(self):
        c = self.c
        bad = ~np.isfinite(c) | (c < -BOUND_TOLERANCE) | (c > 1 + BOUND_TOLERANCE)
        return bad, c
