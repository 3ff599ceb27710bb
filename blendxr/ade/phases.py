"""Cyclic reading of a stored revolution: a sliding window of prepared phases.

A flow dataset stores one revolution in ``rev_phase`` bins. The stepper needs, at any
time t, the fields at the two phases that bracket t (cyclically) and blends them
linearly. :class:`CyclicPhaseReader` reads a phase from the (lazy) dataset only when it is
first needed, prepares it once (diffusivity of eq. 5 on the flow grid, then interpolation
onto the ADE grid), keeps a small window of prepared phases, and prefetches the next phase
in a background thread while the kernels work on the current pair. When the whole
prepared revolution fits the memory budget it is kept, so later revolutions read nothing.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from .grid import (
    AdeGrid,
    AxisMap,
    extend_into_empty,
    inside_mask,
    interpolate,
    interpolate_fields_into,
)
from .solenoidal import remove_divergence

__all__ = ["PreparedPhase", "CyclicPhaseReader"]

_VELOCITY_NAMES = ("vx", "vy", "vz")
#: prepared velocities and diffusivities are held in single precision (the flow is
#: stored so on disk): half the memory and the bytes every kernel that reads them moves.
#: The fill stays double: it sets the material volume the finite volumes conserve (and
#: check against the flow's to 1e-9); the schemes compute and keep their state in double
PHASE_DTYPE = np.float32
#: a whole revolution of prepared phases is kept (each prepared once per run, not once
#: per revolution) only when it fits in this many bytes as well as in the run's memory
#: budget, so that a 100^3 run from a 72-phase flow stays within 2 GB
KEEP_ALL_BYTES = 2**30


@dataclass
class PreparedPhase:
    """One stored phase on the ADE grid, ready for the kernels.

    Velocity and diffusivity components are stacked (component first) so that blending two
    phases and bounding their stable dt are single kernel calls.
    """

    index: int
    vel: np.ndarray  # (ndim, *shape), m/s
    dif: np.ndarray | None  # (ndim, *shape), m2/s, or None when there is no diffusion
    fill: np.ndarray  # material volume fraction
    #: the largest diffusivity of each component over the grid (zeros without diffusion)
    dif_max: np.ndarray = None

    def __post_init__(self):
        if self.dif_max is None:
            ndim = self.vel.shape[0]
            self.dif_max = (
                np.zeros(ndim) if self.dif is None else self.dif.reshape(ndim, -1).max(axis=1)
            )

    @property
    def velocities(self) -> tuple:
        return tuple(self.vel)

    @property
    def diffusivities(self) -> tuple | None:
        return None if self.dif is None else tuple(self.dif)

    @property
    def nbytes(self) -> int:
        return self.vel.nbytes + self.fill.nbytes + (0 if self.dif is None else self.dif.nbytes)


#: how far above a bed's plausible speed a flow's velocity may be before it is refused
SPEED_MARGIN = 10.0


def plausible_speed(flow, coords) -> float:
    """The fastest a tumbling bed in this flow's domain can move, times
    :data:`SPEED_MARGIN`: the wall's speed omega D plus the speed of a free fall over
    the domain, sqrt(2 g D), D the domain's diagonal (rpm and gravity from the flow's
    attributes)."""
    diagonal = math.sqrt(sum((c[-1] - c[0]) ** 2 for c in coords))
    omega = 2.0 * math.pi * float(flow.attrs["rpm"]) / 60.0  # both required by flow/1
    gravity = float(flow.attrs["gravity"])
    return SPEED_MARGIN * (omega * diagonal + math.sqrt(2.0 * gravity * diagonal))


def _divergence_treatment(flow, n_phases: int, requested: str) -> str:
    """What is done with the stored velocity's divergence, and why.

    A steady flow's bed must carry its material without divergence (solenoidal.py), so a
    steady computed flow is projected when ``requested`` is ``"remove"``. A transient one's
    divergence balances the change of its fill between phases; an analytic flow is the
    exact field it is written from (and some, like the uniform flow, pass through the
    grid's edge, which a steady bed's material does not).
    """
    if requested not in ("remove", "keep"):
        raise ValueError(f"steady_divergence must be 'remove' or 'keep', not {requested!r}")
    if n_phases > 1:
        return "keep (transient flow)"
    if "analytic" in flow.attrs:
        return "keep (analytic flow)"
    return requested


class CyclicPhaseReader:
    """Serve prepared flow phases cyclically, reading each from the dataset lazily.

    Parameters
    ----------
    flow : xarray.Dataset
        A flow dataset (may be dask-backed).
    grid : AdeGrid
        The ADE grid.
    diffusion : callable or tuple or None
        ``None``: no diffusion. A tuple of constants: a constant diagonal diffusivity (m2/s).
        A callable ``(velocities, fill, spacing) -> tuple of arrays``: diffusivity on the
        flow grid (eq. 5).
    memory_budget : float
        Bytes that prepared phases may occupy. If the whole revolution fits, every phase
        is kept after its first use; otherwise a window of three (current pair + prefetch).
    prefetch : bool
        Prepare the next phase in a background thread.
    """

    def __init__(
        self,
        flow,
        grid: AdeGrid,
        diffusion,
        memory_budget: float,
        prefetch=True,
        steady_divergence: str = "remove",
    ):
        self.flow = flow
        self.grid = grid
        self.ndim = grid.ndim
        self.n_phases = flow.sizes["rev_phase"]
        self._diffusion = diffusion
        flow_coords = [np.asarray(flow[d].values, float) for d in grid.dims]
        self._flow_spacing = tuple(float(c[1] - c[0]) for c in flow_coords)
        self._maps = tuple(
            AxisMap.between(src, dst) for src, dst in zip(flow_coords, grid.coords, strict=True)
        )
        self._inside = inside_mask(self._maps)
        vessel_flow = np.asarray(flow["vessel"].values) > 0
        self._vessel_flow = vessel_flow
        self.vessel = (interpolate(vessel_flow.astype(float), self._maps) >= 0.5) & self._inside
        self.speed_limit = plausible_speed(flow, flow_coords)
        per_phase = np.prod(grid.shape) * (2 * self.ndim * np.dtype(PHASE_DTYPE).itemsize + 8)
        self.keep_all = per_phase * self.n_phases <= min(memory_budget, KEEP_ALL_BYTES)
        self._window = 3
        self._cache: OrderedDict[int, PreparedPhase] = OrderedDict()
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        # the interpolation's buffers, one set per preparing thread (see _prepare)
        self._work: dict[int, dict] = {}
        self._pool = ThreadPoolExecutor(max_workers=1) if prefetch and self.n_phases > 2 else None
        self.phases_read = 0
        self.divergence_treatment = _divergence_treatment(flow, self.n_phases, steady_divergence)
        self.solenoidal = self.divergence_treatment == "remove"
        self.divergence: dict = {}

    # reading and preparing -------------------------------------------------
    def _read(self, k: int):
        snap = self.flow.isel(rev_phase=k)
        names = ["fill", *_VELOCITY_NAMES[: self.ndim]]
        arrays = {n: np.asarray(snap[n].values, float) for n in names}
        self.phases_read += 1
        for name, values in arrays.items():
            bad = ~np.isfinite(values)
            if bad.any():
                cell = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ValueError(
                    f"flow variable {name} is not finite at rev_phase index {k}, cell {cell}"
                )
            if name != "fill":
                self._check_speed(name, values, k)
        return arrays

    def _check_speed(self, name: str, values: np.ndarray, k: int) -> None:
        """Refuse a velocity no tumbling bed can reach (a fault of the flow, which would
        otherwise shrink the stable dt until the run never ends)."""
        worst = np.unravel_index(np.argmax(np.abs(values)), values.shape)
        if abs(values[worst]) <= self.speed_limit:
            return
        where = ", ".join(
            f"{d}={float(self.flow[d].values[i]):.4g} m"
            for d, i in zip(self.grid.dims, worst, strict=True)
        )
        raise ValueError(
            f"flow variable {name} = {values[worst]:.4g} m/s at rev_phase index {k}, cell "
            f"{tuple(int(i) for i in worst)} ({where}) is far above what the vessel's speed "
            f"and gravity allow, {self.speed_limit:.3g} m/s ({SPEED_MARGIN:g} (omega D + "
            "sqrt(2 g D)), D the flow domain's diagonal): the flow is faulty"
        )

    def _prepare(self, k: int) -> PreparedPhase:
        arrays = self._read(k)
        fill = np.clip(arrays["fill"], 0.0, 1.0)
        material = fill > 0
        n = self.ndim
        velocities = tuple(arrays[name] for name in _VELOCITY_NAMES[:n])
        if self.solenoidal:
            velocities, self.divergence = remove_divergence(velocities, fill, self._flow_spacing)
        # every field of the phase on the flow grid, then onto the ADE grid in one pass
        sources = [extend_into_empty(v, material, self._vessel_flow) for v in velocities]
        if callable(self._diffusion):
            d_flow = self._diffusion(velocities, fill, self._flow_spacing)
            sources += [extend_into_empty(d, material, self._vessel_flow) for d in d_flow]
        elif self._diffusion is not None:
            sources += [np.full(fill.shape, float(value)) for value in self._diffusion]
        n_dif = len(sources) - n
        bounds = [(-math.inf, math.inf)] * n + [(0.0, math.inf)] * n_dif
        out = np.empty((len(sources), *self.grid.shape), PHASE_DTYPE)
        with self._lock:
            work = self._work.setdefault(threading.get_ident(), {})
        interpolate_fields_into(np.stack(sources), self._maps, self.vessel, bounds, out, work)
        fill_ade = np.empty((1, *self.grid.shape))
        interpolate_fields_into(fill[None], self._maps, self.vessel, [(0.0, 1.0)], fill_ade,
                                work)  # fmt: skip
        return PreparedPhase(k, out[:n], out[n:] if n_dif else None, fill_ade[0])

    def get(self, k: int) -> PreparedPhase:
        """The prepared phase ``k`` (cyclic), reading it if needed; prefetches ``k + 1``."""
        k %= self.n_phases
        with self._lock:
            phase = self._cache.get(k)
            future = self._pending.pop(k, None)
        if phase is None:
            phase = future.result() if future is not None else self._prepare(k)
            with self._lock:
                self._cache[k] = phase
                if not self.keep_all:
                    while len(self._cache) > self._window:
                        self._cache.popitem(last=False)
        else:
            with self._lock:
                self._cache.move_to_end(k)
        self._prefetch((k + 1) % self.n_phases)
        return phase

    def _prefetch(self, k: int) -> None:
        if self._pool is None:
            return
        with self._lock:
            if k in self._cache or k in self._pending:
                return
            self._pending[k] = self._pool.submit(self._prepare, k)

    def close(self) -> None:
        """Stop the prefetch thread and free the interpolation's buffers."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        self._work.clear()

    def bracket(self, phase_position: float):
        """The two phases around a position in phase-index units and the weight of the second.

        Parameters
        ----------
        phase_position : float
            rev_phase · n_phases (may exceed n_phases: taken cyclically).
        """
        if self.n_phases == 1:
            p = self.get(0)
            return p, p, 0.0
        k = int(np.floor(phase_position + 1e-12))
        w = min(max(phase_position - k, 0.0), 1.0)
        first = self.get(k)
        if w == 0.0:  # exactly on a stored phase: the next one is not needed
            return first, first, 0.0
        return first, self.get(k + 1), w

    def pair(self, k: int):
        """Stored phases k and k + 1 (cyclic): the ends of one interval between phases."""
        if self.n_phases == 1:
            p = self.get(0)
            return p, p
        return self.get(k), self.get(k + 1)
