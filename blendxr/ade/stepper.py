"""The time loop of the advection-diffusion equation: ``mix``.

The driver maps a labelled flow dataset onto plain arrays for the kernels and labels
what comes back. Per interval between two stored phases it chooses a stable dt from the
scheme's limits, blends the two bracketing phases linearly in time at each step's
midpoint, calls the kernel, and at output times reduces the concentration to the mixing
curves. Time t runs from 0; the stored revolution repeats with period T = 60 / rpm.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time as wallclock
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import xarray as xr

from .. import metrics
from .._version import __version__
from ..driver import CheckpointSchedule, StopRules, memory_limit, progress_bar
from ..scene import Scene, check_values, default_of, fit_snapshots, load_scene
from ..schema import conform_flow, mixing_dataset, validate
from . import schemes
from .diffusivity import shear_diffusivity
from .grid import AdeGrid
from .phases import CyclicPhaseReader
from .schemes import BOUND_TOLERANCE

__all__ = ["SCHEMES", "LOADINGS", "MixSettings", "mix", "BlowUpError"]

#: the schemes' names (numerics.scheme), each a module of :mod:`blendxr.ade.schemes`
SCHEMES = tuple(schemes.SCHEMES)
LOADINGS = ("top-bottom", "axial", "transverse", "side-side", "left-right")
_ALIASES = {"side-side": "axial", "left-right": "axial"}

#: bytes a mixing run holds per ADE cell besides its snapshots (state, double buffers,
#: blended fields, the three prepared phases of the reader's window, metric
#: temporaries), measured with tracemalloc on every scheme (the largest, rounded up)
BYTES_PER_CELL = {2: 350, 3: 420}
#: at most this many records of the mixing curves (outputs) in one run
MAX_RECORDS = 1_000_000
#: at most this many cell updates planned with a given dt
MAX_PLANNED_CELL_UPDATES = 1e13
#: at most this many steps planned with a given dt
MAX_PLANNED_STEPS = 1e9


class _StopRun(Exception):
    """max_steps or wall_time reached inside a stored-phase interval."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


#: mix() keywords whose defaults and ranges the scene schema holds (the one home of both:
#: a keyword given directly is checked there, not here again)
SCHEMA_KEYS = {
    "scheme": "numerics.scheme",
    "k1": "mixing.k1",
    "k2": "mixing.k2",
    "d": "material.particle_diameter",
    "revolutions": "mixing.revolutions",
    "cells": "numerics.cells",
    "output_every": "mixing.output_every",
    "snapshots": "mixing.snapshots",
    "sampling_cell": "mixing.sampling_cell",
    "packing": "material.packing_fraction",
    "safety": "numerics.safety",
    "steady_divergence": "numerics.steady_divergence",
    "memory_budget_mb": "numerics.memory_budget_mb",
    "stop_rsd": "mixing.stop_rsd",
    "stop_intensity": "mixing.stop_intensity",
    "min_intensity_cells": "mixing.min_intensity_cells",
}


def _schema_default(keyword: str):
    """A dataclass default read from the scene schema when the settings are made."""
    return field(default_factory=lambda: default_of(SCHEMA_KEYS[keyword]))


def _as_json(value):
    """Tuples as lists, numpy scalars as Python numbers: what the schema validator reads."""
    if isinstance(value, tuple | list | np.ndarray):
        return [_as_json(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


class BlowUpError(FloatingPointError):
    """The concentration became non-finite or left [0, 1]: the run is stopped."""


@dataclass
class MixSettings:
    """Resolved settings of one ADE run (scene values overridden by keyword arguments)."""

    scheme: str = _schema_default("scheme")
    initial: object = field(default_factory=lambda: default_of("mixing.loading"))
    k1: float = _schema_default("k1")
    k2: float | None = None
    d: float = _schema_default("d")
    diffusivity: tuple | None = None
    revolutions: float = _schema_default("revolutions")
    cells: object = _schema_default("cells")
    output_every: float = _schema_default("output_every")
    snapshots: tuple | None = None
    sampling_cell: float | None = None
    packing: float = _schema_default("packing")
    safety: float = _schema_default("safety")
    steady_divergence: str = _schema_default("steady_divergence")
    dt: float | None = None
    memory_budget_mb: float = _schema_default("memory_budget_mb")
    progress: bool | None = None
    checkpoint: str | None = None
    checkpoint_every: float = 1.0
    resume: bool = True
    wall_time: float | None = None
    max_steps: int | None = None
    check_every: int = 25
    refresh_per_phase: int | None = 2
    callback: object = None
    stop_rsd: float | str | None = None
    stop_intensity: float | str | None = None
    min_intensity_cells: int = _schema_default("min_intensity_cells")
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        check_values({key: _as_json(getattr(self, name)) for name, key in SCHEMA_KEYS.items()})
        faults = []
        for name in ("checkpoint_every", "wall_time"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int | float) and value > 0):
                faults.append(f"{name} = {value!r} is out of range; allowed: a number > 0")
        for name in ("max_steps", "check_every"):
            value = getattr(self, name)
            if value is not None and not (isinstance(value, int) and value >= 1):
                faults.append(f"{name} = {value!r} is out of range; allowed: an integer >= 1")
        if self.refresh_per_phase is not None and not (
            isinstance(self.refresh_per_phase, int) and self.refresh_per_phase >= 1
        ):
            faults.append(
                f"refresh_per_phase = {self.refresh_per_phase!r}: needs an integer >= 1 or None"
            )
        if self.dt is not None and not (
            isinstance(self.dt, int | float) and 0 < self.dt < math.inf
        ):
            faults.append(f"dt = {self.dt!r} is out of range; allowed: a finite number > 0")
        if isinstance(self.initial, str) and self.initial not in LOADINGS:
            faults.append(
                f"initial loading {self.initial!r} is unknown; allowed: {', '.join(LOADINGS)}"
                " or a DataArray of c"
            )
        if self.diffusivity is not None:
            values = np.atleast_1d(np.asarray(self.diffusivity, float))
            if not np.all(np.isfinite(values)) or np.any(values < 0):
                faults.append(f"diffusivity = {self.diffusivity!r}: needs finite values >= 0")
        if faults:
            raise ValueError("; ".join(faults))
        if self.k2 is None:
            self.k2 = 1.9 * self.k1

    def fingerprint(self) -> str:
        """A hash of the settings that change the answer (for safe resumption)."""
        keep = asdict(self)
        for name in (
            "progress",
            "checkpoint",
            "checkpoint_every",
            "resume",
            "wall_time",
            "max_steps",
            "memory_budget_mb",
            "callback",
            "stop_rsd",
            "stop_intensity",
            "extra",
        ):
            keep.pop(name)
        if isinstance(self.initial, xr.DataArray):
            c0 = np.ascontiguousarray(self.initial.values)
            keep["initial"] = hashlib.sha1(c0.tobytes()).hexdigest()
        elif not isinstance(self.initial, str):
            keep["initial"] = getattr(self.initial, "__qualname__", repr(self.initial))
        return hashlib.sha1(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()


def _settings_from(scene: Scene | None, overrides: dict) -> MixSettings:
    values: dict = {}
    if scene is not None:
        mixing, numerics, material = scene["mixing"], scene["numerics"], scene["material"]
        values.update(
            scheme=numerics["scheme"],
            initial=mixing["loading"],
            k1=mixing["k1"],
            k2=mixing.get("k2"),
            d=material["particle_diameter"],
            revolutions=mixing["revolutions"],
            cells=numerics["cells"],
            output_every=mixing["output_every"],
            snapshots=tuple(mixing["snapshots"]) if "snapshots" in mixing else None,
            sampling_cell=mixing.get("sampling_cell"),
            packing=material["packing_fraction"],
            safety=numerics["safety"],
            steady_divergence=numerics["steady_divergence"],
            memory_budget_mb=numerics["memory_budget_mb"],
            stop_rsd=mixing.get("stop_rsd"),
            stop_intensity=mixing.get("stop_intensity"),
            min_intensity_cells=mixing["min_intensity_cells"],
        )
    known = set(MixSettings.__dataclass_fields__) - {"extra"}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TypeError(f"mix() got unknown keyword(s) {unknown}; known: {sorted(known)}")
    values.update(overrides)
    if "revolutions" in overrides and "snapshots" not in overrides and values.get("snapshots"):
        values["snapshots"] = tuple(fit_snapshots(values["snapshots"], overrides["revolutions"]))
    return MixSettings(**values)


# ----------------------------------------------------------------------------- set-up


def _initial_from_dataarray(c0: xr.DataArray, grid: AdeGrid, fill0: np.ndarray) -> np.ndarray:
    """c at t = 0 from a DataArray over (x, y[, z]) in metres, interpolated onto the grid.

    Refused: a missing dimension or coordinate, NaN or infinite values, values outside
    [0, 1], and an array that does not reach over the bed (nearest values would fill it
    silently).
    """
    missing = [d for d in grid.dims if d not in c0.dims]
    if missing:
        raise ValueError(f"initial: the DataArray lacks dims {missing}")
    no_coords = [d for d in grid.dims if d not in c0.coords]
    if no_coords:
        raise ValueError(
            f"initial: the DataArray has no coordinates on {no_coords}: give them in metres "
            "(its values would otherwise be placed by index)"
        )
    for d in grid.dims:
        units = c0[d].attrs.get("units", "m")
        if units != "m":
            raise ValueError(f"initial: coordinate {d} in {units!r}; give it in metres ('m')")
    values = np.asarray(c0.values, float)
    bad = ~np.isfinite(values)
    if bad.any():
        first = np.argwhere(bad)[0]
        where = ", ".join(
            f"{d}={float(c0[d].values[i]):.4g} m" for d, i in zip(c0.dims, first, strict=True)
        )
        raise ValueError(
            f"initial: c is not finite at {int(bad.sum())} of {values.size} points (first at "
            f"{where}); give c in [0, 1] everywhere"
        )
    if values.min() < -BOUND_TOLERANCE or values.max() > 1 + BOUND_TOLERANCE:
        raise ValueError("initial: c must lie in [0, 1]")
    bed = fill0 > 0
    for axis, d in enumerate(grid.dims):
        coord = np.asarray(c0[d].values, float)
        step = float(np.max(np.abs(np.diff(coord)))) if len(coord) > 1 else 0.0
        others = tuple(a for a in range(grid.ndim) if a != axis)
        reach = grid.coords[axis][np.any(bed, axis=others)] if bed.any() else []
        if len(reach) and (
            reach.min() < coord.min() - step - grid.spacing[axis]
            or reach.max() > coord.max() + step + grid.spacing[axis]
        ):
            raise ValueError(
                f"initial: the DataArray covers {d} from {coord.min():.4g} to "
                f"{coord.max():.4g} m, the bed reaches {reach.min():.4g} to {reach.max():.4g} m"
            )
    target = {d: xr.DataArray(c, dims=d) for d, c in zip(grid.dims, grid.coords, strict=True)}
    linear = c0.interp(target, method="linear")
    # within a cell or so of the array's edge (checked above) the nearest value holds
    nearest = c0.interp(target, method="nearest", kwargs={"fill_value": "extrapolate"})
    out = linear.fillna(nearest).transpose(*grid.dims).values
    # cells without material carry no c (the value is never read)
    return np.clip(np.where(np.isfinite(out), out, 0.0), 0.0, 1.0)


def _initial_concentration(settings: MixSettings, grid: AdeGrid, fill0: np.ndarray) -> np.ndarray:
    """c at t = 0 from a loading name or a user DataArray (DESIGN §2 loadings)."""
    if callable(settings.initial) and not isinstance(settings.initial, xr.DataArray):
        points = np.meshgrid(*grid.coords, indexing="ij")
        values = np.asarray(settings.initial(*points), float)
        if values.shape != grid.shape or not np.all(np.isfinite(values)):
            raise ValueError("initial: the callable must return finite values of c on the grid")
        if values.min() < -BOUND_TOLERANCE or values.max() > 1 + BOUND_TOLERANCE:
            raise ValueError("initial: c must lie in [0, 1]")
        return np.clip(values, 0.0, 1.0)
    if not isinstance(settings.initial, str):
        c0 = settings.initial
        if not isinstance(c0, xr.DataArray):
            raise TypeError("initial must be a loading name, a DataArray of c or a callable")
        return _initial_from_dataarray(c0, grid, fill0)
    loading = _ALIASES.get(settings.initial, settings.initial)
    if loading == "axial" and grid.ndim == 2:
        raise ValueError("initial 'axial' splits along z: a 2-D scene has no z; use 'transverse'")
    axis = {"top-bottom": 1, "transverse": 0, "axial": 2}[loading]
    centres = grid.coords[axis]
    h = grid.spacing[axis]
    # Every loading splits the material into equal volumes, as a loaded blender holds
    # equal amounts of the two colours: the plane is the volume median along the axis
    # (x = 0 or z = 0 for a bed symmetric about that plane, as DESIGN §2 states).
    profile = fill0.sum(axis=tuple(a for a in range(grid.ndim) if a != axis))
    cumulative = np.cumsum(profile) / profile.sum()
    j = int(np.searchsorted(cumulative, 0.5))
    below = cumulative[j - 1] if j > 0 else 0.0
    frac = (0.5 - below) / max(profile[j] / profile.sum(), 1e-300)
    split = centres[j] - 0.5 * h + frac * h
    # the share of each cell beyond the plane
    beyond = np.clip((centres + 0.5 * h - split) / h, 0.0, 1.0)
    # species A on top (top-bottom), at low x (transverse) or low z (axial)
    line = beyond if loading == "top-bottom" else 1.0 - beyond
    shape = [1] * grid.ndim
    shape[axis] = len(line)
    return np.broadcast_to(line.reshape(shape), grid.shape).astype(float)


def _event_times(settings: MixSettings, period: float):
    total = settings.revolutions
    outputs = np.arange(0.0, total + 1e-9, settings.output_every)
    if outputs[-1] < total - 1e-9:
        outputs = np.append(outputs, total)
    if settings.snapshots is None:
        whole = np.arange(0, math.floor(total + 1e-9) + 1)
        if len(whole) > 11:
            whole = np.unique(np.round(np.linspace(0, total, 11)))
        snaps = np.union1d(whole, [total])
    else:
        snaps = np.asarray(sorted(set(settings.snapshots)), float)
        if len(snaps) and snaps.max() > total + 1e-9:
            raise ValueError(f"snapshots: {snaps.max()} is beyond revolutions = {total}")
    return outputs, snaps


def plan(flow, settings: MixSettings) -> dict:
    """What a run will hold and do, estimated before anything is allocated; refused with
    the number and what to change when it cannot fit or would not end.

    Returns the grid, its cell count, the records, the bytes the run needs and the
    bytes left for the reader's cache of prepared phases.

    Raises
    ------
    ValueError
        More records than :data:`MAX_RECORDS`, more memory than
        ``numerics.memory_budget_mb`` or this machine has available, or (with a given
        ``dt``) more cell updates than :data:`MAX_PLANNED_CELL_UPDATES`.
    """
    s = settings
    ndim = 3 if "z" in flow.dims else 2
    records = math.floor(s.revolutions / s.output_every + 1e-9) + 2
    if records > MAX_RECORDS:
        raise ValueError(
            f"mixing.output_every = {s.output_every:g} gives {records:.3g} records over "
            f"{s.revolutions:g} revolutions; at most {MAX_RECORDS:,}: choose "
            f"mixing.output_every >= {s.revolutions / (MAX_RECORDS - 2):.3g}"
        )
    coords = [np.asarray(flow[d].values, float) for d in ("x", "y", "z")[:ndim]]
    for name, c in zip(("x", "y", "z"), coords, strict=False):
        if len(c) < 2:
            raise ValueError(f"flow coordinate {name} needs at least 2 cells")
    lows = [c[0] - 0.5 * (c[1] - c[0]) for c in coords]
    highs = [c[-1] + 0.5 * (c[1] - c[0]) for c in coords]
    shape = AdeGrid.covering_shape(lows, highs, s.cells)  # counted before it is built
    n_cells = math.prod(shape)
    snapshots = len(s.snapshots) + 1 if s.snapshots is not None else 12
    need = n_cells * (BYTES_PER_CELL[ndim] + 8 * snapshots)
    limit, what = memory_limit(s.memory_budget_mb)
    if need > limit:
        scale = (limit / need) ** (1.0 / ndim)
        cells = s.cells if np.ndim(s.cells) == 0 else max(s.cells)
        raise ValueError(
            f"numerics.cells = {s.cells} gives {n_cells:.3g} ADE cells "
            f"({' x '.join(map(str, shape))}), which need about {need / 2**20:.4g} MiB, "
            f"above {what}: choose about numerics.cells <= {max(int(cells * scale), 1)} or "
            "raise numerics.memory_budget_mb"
        )
    if s.dt is not None:
        rpm = float(flow.attrs.get("rpm", 0.0))
        period = 60.0 / rpm if rpm > 0 else math.inf
        updates = s.revolutions * period / s.dt * n_cells
        if updates > MAX_PLANNED_CELL_UPDATES or s.revolutions * period / s.dt > MAX_PLANNED_STEPS:
            raise ValueError(
                f"dt = {s.dt:g} s asks for {s.revolutions * period / s.dt:.3g} steps of "
                f"{n_cells:.3g} cells ({updates:.3g} cell updates; at most "
                f"{MAX_PLANNED_STEPS:.0e} steps and {MAX_PLANNED_CELL_UPDATES:.0e} cell "
                "updates): give a larger dt, or none (the scheme's own stable dt)"
            )
    return {
        "grid": AdeGrid.covering(lows, highs, s.cells),
        "cells": n_cells,
        "records": records,
        "bytes": need,
        "cache_bytes": max(limit - need, 0.0),
    }


#: A dask-backed flow up to this many bytes is read into memory before a run. Its
#: validation reads every value anyway; for a small flow, dask's overhead per phase read
#: (and per check) is many times the reading itself.
SMALL_FLOW_BYTES = 64 * 2**20


def _read_if_small(flow: xr.Dataset) -> xr.Dataset:
    lazy = any(var.chunks is not None for var in flow.variables.values())
    return flow.compute() if lazy and flow.nbytes <= SMALL_FLOW_BYTES else flow


def _resolve_flow(flow, scene):
    from ..io import open_flow

    if isinstance(flow, str | os.PathLike):
        # by the file's size (compressed variables may take more in memory)
        small = os.path.isfile(flow) and os.path.getsize(flow) <= SMALL_FLOW_BYTES
        flow = open_flow(flow, chunks=None if small else "phase")
    elif isinstance(flow, xr.Dataset):
        flow = validate(_read_if_small(conform_flow(flow)))
    else:
        raise TypeError("flow must be a flow dataset or a path to a netCDF flow file")
    if scene is None and flow.attrs.get("scene"):
        try:
            scene = load_scene(flow.attrs["scene"])
        except ValueError:
            scene = None
    elif scene is not None:
        scene = load_scene(scene)
    return flow, scene


# ----------------------------------------------------------------------------- run


class _Run:
    """One ADE run: grid, reader, state, clocks, recorded outputs."""

    def __init__(self, flow, scene, settings: MixSettings, planned: dict | None = None):
        self.flow = flow
        self.scene = scene
        self.settings = s = settings
        self.ndim = 3 if "z" in flow.dims else 2
        rpm = float(flow.attrs["rpm"])
        if rpm <= 0:
            raise ValueError("the flow's rpm must be > 0 to define a revolution for mixing")
        self.period = 60.0 / rpm
        planned = plan(flow, s) if planned is None else planned
        self.grid = planned["grid"]
        self.with_diffusion = s.diffusivity is not None or s.k1 > 0 or s.k2 > 0
        if s.diffusivity is not None:
            diffusion = tuple(np.broadcast_to(np.asarray(s.diffusivity, float), (self.ndim,)))
            if not any(diffusion):
                diffusion, self.with_diffusion = None, False
        elif self.with_diffusion:
            k1, k2, d = s.k1, s.k2, s.d

            def diffusion(velocities, fill, spacing):
                return shear_diffusivity(velocities, fill, spacing, k1, k2, d)
        else:
            diffusion = None
        self.reader = CyclicPhaseReader(
            flow,
            self.grid,
            diffusion,
            memory_budget=planned["cache_bytes"],
            steady_divergence=s.steady_divergence,
        )
        self.vessel = self.reader.vessel.astype(np.uint8)
        self.scheme = schemes.make(s.scheme, self.grid, self.vessel, self.with_diffusion)
        self._limits: dict = {}
        self.t = 0.0
        self.steps = 0
        self.cell_updates = 0
        self.dt_used = [math.inf, 0.0]
        self.max_substeps = 0
        self.records: dict[str, list] = {
            "time": [],
            "rsd": [],
            "intensity": [],
            "intensity_cells": [],
            "mass_a": [],
            "fill_mismatch": [],
        }
        self.snapshots: dict[float, np.ndarray] = {}
        # a stored-phase interval a stop left unfinished: (start, end, steps done)
        self.interval: tuple[float, float, int] | None = None
        self.stops = StopRules()  # max_steps and wall_time, set by the caller
        # sampling cells: their width in grid cells (None: none) and in metres
        self.sampling_cells = self._sampling_cells()
        self.sampling_cell = (
            None if self.sampling_cells is None else self.sampling_cells * self.grid.spacing[0]
        )
        self.recorder = self._recorder()
        self.mean_c = None  # the mean of c, from the first record (it is conserved)

    # --- random-mixture floors and the stop rule ----------------------------
    def floors(self) -> tuple[float, float]:
        """(I_R, RSD_R) of a random mixture on the sampling cells (NaN when undefined)."""
        s = self.settings
        cell = self.sampling_cell
        if cell is None or cell < s.d or self.mean_c is None or not 0 < self.mean_c < 1:
            return math.nan, math.nan
        intensity = metrics.random_mixture_intensity(s.d, cell, ndim=self.ndim, packing=s.packing)
        spread = metrics.random_mixture_rsd(
            s.d, cell, self.mean_c, ndim=self.ndim, packing=s.packing
        )
        return intensity, spread

    def stop_reason(self) -> str | None:
        """Why the run may stop now (a stop rule met at the last record), or None."""
        floor_i, floor_rsd = self.floors()
        rules = (
            ("rsd", self.settings.stop_rsd, floor_rsd),
            ("intensity", self.settings.stop_intensity, floor_i),
        )
        for name, level, floor in rules:
            if level is None:
                continue
            target = floor if level == "floor" else float(level)
            value = self.records[name][-1]
            if math.isfinite(target) and math.isfinite(value) and value <= target:
                what = "the random-mixture floor " if level == "floor" else ""
                return f"{name} {value:.4g} <= {what}{target:.4g}"
        return None

    # --- initial state ----------------------------------------------------
    def initialise(self) -> None:
        phase0 = self.reader.get(0)
        # the least fill the scheme counts as material (below it c is undefined)
        least = self.scheme.least_fill
        if not (phase0.fill[self.vessel > 0] > least).any():
            raise ValueError(
                f"the flow has no material at rev_phase 0 (no cell in the vessel with fill "
                f"above {least:g}, the least the {self.settings.scheme} scheme counts): "
                "nothing to mix"
            )
        c0 = _initial_concentration(self.settings, self.grid, phase0.fill)
        self.scheme.initialise(phase0.fill, c0)

    # --- concentration and metrics ----------------------------------------
    def concentration_and_weight(self, fill=None):
        """c (NaN where no material) and its weight; ``fill``: the flow's fill now, if
        the caller has it already."""
        return self.scheme.concentration(self.current_fill() if fill is None else fill)

    def current_fill(self) -> np.ndarray:
        a, b, w = self.reader.bracket(self._phase_position(self.t))
        return a.fill + w * (b.fill - a.fill)

    def _sampling_cells(self) -> int | None:
        """Grid cells across a sampling cell (None: the ADE cells are not cubes)."""
        cell = self.settings.sampling_cell
        if cell is None:
            cell = 5 * self.settings.d
        extent = max(len(c) * h for c, h in zip(self.grid.coords, self.grid.spacing, strict=True))
        if cell > extent:
            raise ValueError(
                f"mixing.sampling_cell = {cell:g} m is larger than the flow's domain "
                f"({extent:.4g} m across): no sampling cell fits"
            )
        h = self.grid.spacing
        if max(h) - min(h) > 1e-9 * max(h):
            return None  # anisotropic ADE cells: sampling cells cannot be whole cubes
        return max(1, round(cell / h[0]))

    def _recorder(self) -> metrics.ArrayRecorder:
        """The records' metrics on this grid's arrays, with its sampling cells (none when
        a sampling cell does not fit the grid)."""
        k = self.sampling_cells
        fits = k is not None and all(k <= n for n in self.grid.shape)
        factors = (k,) * self.ndim if fits else None
        return metrics.ArrayRecorder(self.grid.shape, factors)

    def record(self) -> None:
        fill = self.current_fill()  # blended once: the metrics below all need it
        c, weight = self.concentration_and_weight(fill)
        metric = self.recorder
        rec = self.records
        rec["time"].append(self.t)
        rec["rsd"].append(metric.rsd(c, metric.weights(c, weight)))
        value, count = math.nan, 0
        if metric.factors is not None:
            # Sampling cells qualify by the flow's fill (the paper's EVF), not by the
            # carried material, which the scheme smears at the free surface over many
            # revolutions until few cells hold 95 % of it.
            samples = metric.sample_means(c, metric.weights(c, fill))
            count = int(np.count_nonzero(~np.isnan(samples)))
            if count >= self.settings.min_intensity_cells:
                value = metric.intensity(samples)
        rec["intensity"].append(value)
        rec["intensity_cells"].append(float(count))
        if self.mean_c is None:
            total = float(weight.sum())
            self.mean_c = float(np.nansum(c * weight)) / total if total > 0 else math.nan
        rec["mass_a"].append(self.scheme.species(c, weight) * self.grid.cell_volume)
        rec["fill_mismatch"].append(self.scheme.fill_mismatch(fill))
        rev = self.t / self.period
        for r in self.snapshot_revs:
            if abs(r - rev) < 1e-9 and r not in self.snapshots:
                self.snapshots[r] = c.copy()

    def keep_snapshot(self) -> None:
        """Keep c now as a snapshot (a run stopped early ends with its last state)."""
        rev = self.t / self.period
        # a stop at a planned snapshot has it already (keyed by the planned revolution)
        if all(abs(rev - r) > 1e-9 for r in self.snapshots):
            self.snapshots[rev] = self.concentration_and_weight()[0]

    # --- stepping ---------------------------------------------------------
    def _phase_position(self, t: float) -> float:
        return (t / self.period) * self.reader.n_phases

    def advance_to(self, t_end: float) -> None:
        """Step from self.t to t_end (no stored-phase boundary inside).

        The interval's steps are planned from where it started: a run stopped inside it
        (max_steps, wall_time) and resumed from its checkpoint finishes the same plan,
        step for step, so that the resumed answer is bit-identical.
        """
        t0, done = self.t, 0
        if self.interval is not None:
            start, end, steps = self.interval
            if abs(end - t_end) <= 1e-12 * self.period:
                t0, done = start, steps
        span = t_end - t0
        if span <= 1e-15 * self.period:
            self.t = t_end
            return
        mid = self._phase_position(t0 + 0.5 * span)
        k = math.floor(mid)
        a, b = self.reader.pair(k)
        # The stored revolution repeats, so an interval's limit is computed once per run.
        key = (a.index, b.index)
        limit = self._limits.get(key)
        if limit is None:
            limit = self._limits[key] = self.scheme.max_dt(a, b)
        s = self.settings
        if s.dt is not None:
            if s.dt > limit:
                raise ValueError(
                    f"dt = {s.dt:.6g} s exceeds the stability limit of the {s.scheme} scheme, "
                    f"{limit:.6g} s, for this flow and grid (see docs/numerics.md)"
                )
            dt_target = s.dt
        else:
            dt_target = s.safety * limit
        n = max(1, math.ceil(span / dt_target - 1e-9)) if math.isfinite(dt_target) else 1
        dt = span / n
        self.dt_used[0] = min(self.dt_used[0], dt)
        self.dt_used[1] = max(self.dt_used[1], dt)
        n_sub = self.scheme.begin_interval(a, b, dt)
        self.max_substeps = max(self.max_substeps, n_sub)
        # Flow fields (and the scheme's per-cell coefficients) are refreshed in blocks of
        # steps, each at its block's midpoint time: piecewise-constant coefficients in time,
        # second-order in the block length (docs/numerics.md).
        steady = a is b
        blocks = (
            1 if steady else (n if s.refresh_per_phase is None else min(n, s.refresh_per_phase))
        )
        for block in range(blocks):
            first, last = (block * n) // blocks, ((block + 1) * n) // blocks
            if last <= done:
                continue  # stepped before the stop this run resumes from
            t_mid = t0 + 0.5 * (first + last) * dt
            w = 0.0 if steady else min(max(self._phase_position(t_mid) - k, 0.0), 1.0)
            self.scheme.prepare(a, b, w, dt, limit)
            for i in range(max(first, done), last):
                self.scheme.step()
                self.cell_updates += self.scheme.active_cells(self.steps)
                self.t += dt
                self.steps += 1
                if self.steps % s.check_every == 0:
                    self.check()
                reason = self.stops.reason(self.steps)
                if reason is not None and i + 1 < n:
                    self.interval = (t0, t_end, i + 1)
                    raise _StopRun(reason)
        self.interval = None
        self.t = t_end

    def check(self) -> None:
        """Stop with the step and cell if c is non-finite or far outside [0, 1]."""
        bad, values = self.scheme.faults()
        if bad.any():
            cell = tuple(int(i) for i in np.argwhere(bad)[0])
            where = ", ".join(
                f"{d}={self.grid.coords[i][j]:.4g} m"
                for i, (d, j) in enumerate(zip(self.grid.dims, cell, strict=True))
            )
            raise BlowUpError(
                f"{self.settings.scheme}: concentration {values[cell]!r} at step {self.steps}, "
                f"t = {self.t:.6g} s, cell {cell} ({where}); dt was {self.dt_used[1]:.3g} s"
            )

    @property
    def snapshot_revs(self):
        return self._snapshot_revs

    # --- checkpoints --------------------------------------------------------
    def save_checkpoint(self, path: Path) -> None:
        from ..io import write_checkpoint

        state, scheme_meta = self.scheme.state()
        arrays = dict(state)
        for name, values in self.records.items():
            arrays[f"record_{name}"] = np.asarray(values, float)
        for r, snap in self.snapshots.items():
            arrays[f"snapshot_{r!r}"] = snap.astype(float)
        meta = {
            "t": self.t,
            "steps": self.steps,
            "cell_updates": self.cell_updates,
            **scheme_meta,
            "fingerprint": self.settings.fingerprint(),
            "dt_min": self.dt_used[0],
            "dt_max": self.dt_used[1],
            "max_substeps": self.max_substeps,
            "interval": json.dumps(self.interval),
            "blendxr_version": __version__,
        }
        write_checkpoint(path, arrays, meta)

    def load_checkpoint(self, path: Path) -> bool:
        from ..io import read_checkpoint

        arrays, meta = read_checkpoint(path)
        if meta.get("fingerprint") != self.settings.fingerprint():
            raise ValueError(
                f"checkpoint {path} belongs to a run with other settings; "
                "remove it, pass resume=False, or give --no-resume on the shell"
            )
        self.scheme.load_state(arrays, meta)
        for name in self.records:
            self.records[name] = list(np.atleast_1d(arrays.get(f"record_{name}", [])))
        for key, values in arrays.items():
            if key.startswith("snapshot_"):
                self.snapshots[float(key[len("snapshot_") :])] = values
        self.t = float(meta["t"])
        self.steps = int(meta["steps"])
        self.cell_updates = int(meta["cell_updates"])
        self.dt_used = [float(meta["dt_min"]), float(meta["dt_max"])]
        self.max_substeps = int(meta["max_substeps"])
        interval = json.loads(meta.get("interval", "null"))
        self.interval = (
            None if interval is None else (float(interval[0]), float(interval[1]), int(interval[2]))
        )
        return True


def _notify(callback, run: _Run) -> None:
    """Call a user's callback at a record with what the record holds (read only)."""
    if callback is None:
        return
    r = run.records
    callback(
        SimpleNamespace(
            revolution=r["time"][-1] / run.period,
            rsd=r["rsd"][-1],
            intensity=r["intensity"][-1],
            steps=run.steps,
            dt=run.dt_used[1],
        )
    )


def mix(flow, scene=None, **overrides) -> xr.Dataset:
    """Run the advection-diffusion model of mixing through a flow.

    Solves eq. (1)/(4) of the paper for the concentration c of species A, with the
    shear-rate diffusivity of eq. (5), through the stored revolution of ``flow``
    repeated cyclically for as many revolutions as asked.

    Parameters
    ----------
    flow : xarray.Dataset or path
        A flow dataset (``flow/1``) or a netCDF file holding one (opened lazily).
    scene : Scene, str or None
        Mixing and numerics settings; defaults to the scene stored in the flow's
        attributes, else built-in defaults.
    **overrides
        Any of: ``scheme`` ("finite-volume" default, "lax-wendroff" or "semi-lagrangian"),
        ``initial`` (a
        loading name — top-bottom, axial, transverse, side-side, left-right — or a
        DataArray of c at t = 0), ``k1``, ``k2`` (default 1.9·k1), ``d`` (particle
        diameter, m), ``diffusivity`` (constant diagonal D in m2/s instead of eq. 5),
        ``revolutions``, ``cells`` (ADE cells along the longest axis, or per axis),
        ``output_every`` (revolutions), ``snapshots`` (revolutions), ``sampling_cell``
        (m, scale of scrutiny), ``safety`` (fraction of the stable dt), ``dt`` (s; refused
        above the stability limit), ``memory_budget_mb``, ``progress``, ``checkpoint``
        (path), ``checkpoint_every`` (revolutions), ``resume``, ``wall_time`` (s),
        ``max_steps``, ``refresh_per_phase`` (flow-field updates per stored-phase
        interval, default 2; None updates them every step), ``callback`` (called at
        every record with its revolution, rsd, intensity, steps and dt).

    Returns
    -------
    xarray.Dataset
        The mixing dataset (``mixing/1``): rsd, intensity, mass_a against time, c at the
        snapshot revolutions, and attributes giving the scheme, dt, grid, k1, k2, d,
        steps, wall time and cell updates per second.

    Raises
    ------
    ValueError
        Bad arguments (naming the argument and what is allowed), or a dt above the limit.
    BlowUpError
        The solution became non-finite or left [0, 1]; the message gives step and cell.
    """
    flow, scene = _resolve_flow(flow, scene)
    settings = _settings_from(scene, overrides)
    started = wallclock.perf_counter()
    run = _Run(flow, scene, settings, plan(flow, settings))
    run.stops = StopRules(settings.max_steps, settings.wall_time, started)
    outputs, snaps = _event_times(settings, run.period)
    run._snapshot_revs = [float(r) for r in snaps]
    events = np.union1d(outputs, snaps)
    checkpoint = Path(settings.checkpoint) if settings.checkpoint else None
    if checkpoint is not None and settings.resume and checkpoint.exists():
        run.load_checkpoint(checkpoint)
    else:
        run.initialise()
        run.record()
    saves = CheckpointSchedule(settings.checkpoint_every)  # in revolutions
    saves.resume_at(run.t / run.period)
    stopped_by = "revolutions"
    bar = progress_bar(settings.progress, settings.revolutions, "rev")
    bar.update(run.t / run.period)
    try:
        for rev in events:
            t_event = rev * run.period
            if t_event <= run.t + 1e-12 * run.period:
                continue
            # march through the stored-phase boundaries up to the event
            while run.t < t_event - 1e-12 * run.period:
                pos = run._phase_position(run.t)
                boundary = (math.floor(pos + 1e-9) + 1) / run.reader.n_phases * run.period
                run.advance_to(min(boundary, t_event))  # raises _StopRun
            run.check()
            done = rev
            if rev in outputs or rev in snaps:
                run.record()
                _notify(settings.callback, run)
                reason = run.stop_reason()
                if reason is not None:
                    stopped_by = reason
                    run.keep_snapshot()
                    break
            bar.update(done - bar.n)
            bar.set_postfix_str(f"rsd {run.records['rsd'][-1]:.3f}")
            if checkpoint is not None and saves.due(rev):
                run.save_checkpoint(checkpoint)
            reason = run.stops.reason(run.steps)
            if reason is not None:
                stopped_by = reason
                break
    except _StopRun as stop:
        stopped_by = stop.reason
    finally:
        bar.close()
        run.reader.close()
    if checkpoint is not None:
        run.save_checkpoint(checkpoint)
    wall = wallclock.perf_counter() - started
    return _mixing_result(run, scene, wall, stopped_by)


def _mixing_result(run: _Run, scene, wall: float, stopped_by: str) -> xr.Dataset:
    s = run.settings
    rec = run.records
    times = np.asarray(rec["time"])
    revs = sorted(run.snapshots)
    snap = np.stack([run.snapshots[r] for r in revs]) if revs else np.zeros((0, *run.grid.shape))
    coords = dict(zip(("x", "y", "z"), run.grid.coords, strict=False))
    mass = np.asarray(rec["mass_a"])
    drift = float(np.max(np.abs(mass - mass[0])) / mass[0]) if mass[0] > 0 else 0.0
    attrs = {
        "scheme": s.scheme,
        "dt_min": run.dt_used[0] if math.isfinite(run.dt_used[0]) else 0.0,
        "dt_max": run.dt_used[1],
        "safety": s.safety,
        "steps": run.steps,
        "grid_cells": list(run.grid.shape),
        "grid_spacing": list(run.grid.spacing),
        "k1": s.k1,
        "k2": s.k2,
        "d": s.d,
        "diffusivity": "eq. (5) shear-rate"
        if s.diffusivity is None
        else f"constant {s.diffusivity}",
        "initial": s.initial if isinstance(s.initial, str) else "user DataArray",
        "revolutions": float(times[-1] / run.period) if len(times) else 0.0,
        "revolutions_requested": s.revolutions,
        "stopped_by": stopped_by,
        "wall_time_s": wall,
        "cell_updates": run.cell_updates,
        "cell_updates_per_s": run.cell_updates / wall if wall > 0 else 0.0,
        "phases_read": run.reader.phases_read,
        "steady_divergence": run.reader.divergence_treatment,
        **{f"flow_{k}": v for k, v in run.reader.divergence.items()},
        "diffusion_substeps_max": run.max_substeps,
        "mass_a_relative_drift": drift,
        "fill_mismatch_max": float(np.max(rec["fill_mismatch"])) if rec["fill_mismatch"] else 0.0,
        "sampling_cell": run.sampling_cell if run.sampling_cell is not None else 0.0,
        "period_s": run.period,
        "min_intensity_cells": s.min_intensity_cells,
    }
    floor_i, floor_rsd = run.floors()
    attrs["random_mixture_intensity"] = floor_i
    attrs["random_mixture_rsd"] = floor_rsd
    attrs["mean_c"] = run.mean_c if run.mean_c is not None else math.nan
    if run.flow.attrs.get("conformed"):
        attrs["flow_conformed"] = run.flow.attrs["conformed"]
        attrs["history"] = f"flow read leniently; it lacked: {run.flow.attrs['conformed']}"
    kwargs = {}
    if run.ndim == 3:
        kwargs["z"] = coords["z"]
    result = mixing_dataset(
        coords["x"],
        coords["y"],
        time=times,
        revolution=times / run.period,
        rsd=np.asarray(rec["rsd"]),
        intensity=np.asarray(rec["intensity"]),
        mass_a=mass,
        snapshot_time=np.asarray(revs) * run.period,
        snapshot_revolution=np.asarray(revs, float),
        c=snap,
        scene=scene.to_toml() if scene is not None else "",
        attrs=attrs,
        **kwargs,
    )
    result["intensity_cells"] = xr.DataArray(
        np.asarray(rec["intensity_cells"], np.int32),
        dims="time",
        attrs={
            "units": "1",
            "long_name": "qualified sampling cells of the segregation intensity",
            "comment": f"intensity is NaN where fewer than {s.min_intensity_cells} qualify",
        },
    )
    return result
