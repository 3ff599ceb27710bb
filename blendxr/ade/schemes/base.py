"""The interface every advection scheme of the mixing model keeps.

The driver (:mod:`blendxr.ade.stepper`) plans the time steps, walks the stored phases,
records the mixing curves and checkpoints; a scheme owns its prognostic fields and does
the rest. Per stored-phase interval (phases ``a`` and ``b``) the driver asks the scheme
for its stable dt (:meth:`Scheme.max_dt`, once per pair and run, since the revolution
repeats) and for what the interval's dt costs it (:meth:`Scheme.begin_interval`); per
refresh block it passes the blend weight (:meth:`Scheme.prepare`), then it calls
:meth:`Scheme.step` once per step. At records it reads the concentration, the conserved
species content and the scheme's own checks. A new scheme is one module defining a
subclass and one line in :data:`blendxr.ade.schemes.SCHEMES`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from ..grid import AdeGrid
from ..phases import PreparedPhase

#: How far outside [0, 1] a value may stray (round-off) before the run is stopped.
BOUND_TOLERANCE = 1e-6


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
    def zero_stack(self) -> np.ndarray:
        """Zeros of shape (ndim, *grid shape): the diffusivity of a run without one."""
        if self._zeros is None:
            self._zeros = np.zeros((self.ndim, *self.grid.shape))
        return self._zeros

    def diffusivity_of(self, phase: PreparedPhase) -> np.ndarray:
        return phase.dif if phase.dif is not None else self.zero_stack()
