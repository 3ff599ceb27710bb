"""The built-in Mohr-Coulomb flow solver: fill, settle, rotate, phase-average (DESIGN §4).

A material point method (MLS-MPM/APIC, quadratic B-splines) in the vessel frame, where
the walls stand still and gravity turns backwards once per revolution:

1. **Fill**: particles on a lattice (``blendxr.vessels.seed_particles``), at rest, no stress.
2. **Settle** (``solver.settle_time``): gravity ramped from zero over the first 60 % of the
   settling time with grid damping, then held for the rest undamped, so that the bed
   comes to rest under a Mohr-Coulomb stress state (an elastic K0 of this material
   violates the yield criterion, DESIGN §7).
3. **Turn** at ``operation.rpm`` for ``solver.revolutions`` revolutions: gravity rotates
   backwards in the vessel frame and the centrifugal and Coriolis accelerations act.
4. **Average** particle velocity and volume into ``flow.phases`` phase bins of the last
   revolution, on the output grid of cell ``flow.cell``: the flow dataset of DESIGN §3.
   Drums are axisymmetric: their flow is averaged in the lab frame into one phase.
   Every revolution is averaged in turn and the last two are kept: eq. (30) between
   each revolution and the one before goes into ``periodicity_history_*`` (the
   paper's Table 3), and the last pair into ``periodicity_*``.

Non-rotating scenes (``rpm = 0``) run for ``operation.duration`` and average over the
final ``solver.average_window``.

Stability: explicit, ``dt = courant * cell / (c_p + |v|max)`` with the P-wave speed
``c_p = sqrt((K + 4G/3) / rho)`` (CFL for elastic waves); ``courant <= 1`` is required
and the default 0.4 leaves room for the quadratic B-spline's wider stencil. A run whose
particles reach a speed far beyond any the scene can produce, or a non-finite value,
stops with the step, the time and the place, after keeping its last checkpoint.
"""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numba
import numpy as np
import xarray as xr

from .. import __version__
from ..scene import Scene, SceneError, load_scene
from ..schema import flow_dataset
from ..vessels import Drum, vessel_from_scene
from . import kernels as mpm
from . import mohr_coulomb as mc
from .projection import DensityProjection
from .walls import project_into_vessel, reflect_across_mirror

__all__ = ["FlowBlowUpError", "FlowSimulation", "Material", "solve_flow"]

SORT_EVERY = 20  # steps between re-sorting particles by cell (keeps P2G chunks coherent)
SPEED_CHECK_EVERY = 10  # steps between updates of |v|max for dt (cheap; v changes slowly)
RAMP_SHARE = 0.6  # share of the settling time over which gravity ramps up (damped)
PARALLEL_MIN_PARTICLES = 20_000  # smaller beds run on one thread (see _threads)
GRID_PADDING = 3  # empty nodes around the vessel's bounding box (B-spline support + margin)
DEFAULT_PHASES = 36
WALL_BAND = 0.5  # nodes closer to the wall than this many cells get the wall law (docs/flow.md)
WALL_SKIN = 1e-3  # projected particles land this many cells inside the wall


class FlowBlowUpError(RuntimeError):
    """The flow solver went unstable; the message gives the step, time and place."""


@dataclass(frozen=True)
class Material:
    """Material constants of the Mohr-Coulomb model (paper Table 1 by default).

    Parameters
    ----------
    density : float
        kg/m³.
    youngs_modulus : float
        Pa, before stiffness scaling.
    poisson_ratio : float
        Dimensionless, in [0, 0.5).
    friction_angle_deg, dilation_angle_deg : float
        Degrees.
    cohesion : float
        Pa.
    wall_friction : float
        Coulomb coefficient between material and walls.
    stiffness_scaling : float
        E is divided by this factor (>= 1) for a larger stable dt.
    tension_cutoff : bool
        Cap the largest principal stress at c cot(phi).
    lost_contact : bool
        Keep the volume gained at the apex or cap as a gap that compaction closes
        stress-free (``mohr_coulomb.close_gap``), bounded by what the material around
        the particle lacks of its seeded packing (``kernels._bounded_gap``); on by
        default.
    friction_angle_limit_deg : float, optional
        The μ(I) rheology's limit angle, atan(μ2) > φ (``mohr_coulomb.rate_friction``);
        None (default): rate-independent Mohr-Coulomb, the paper's model.
    inertial_number_i0 : float
        The μ(I) rheology's I0.
    particle_diameter : float
        Grain diameter d, m (the μ(I) rheology's length).
    packing_fraction : float
        Solid fraction: the grain density is density / packing_fraction.
    """

    # no defaults here: every value comes from the scene, whose schema holds them
    density: float
    youngs_modulus: float
    poisson_ratio: float
    friction_angle_deg: float
    cohesion: float
    dilation_angle_deg: float
    wall_friction: float
    stiffness_scaling: float
    tension_cutoff: bool
    lost_contact: bool
    friction_angle_limit_deg: float | None
    inertial_number_i0: float
    particle_diameter: float
    packing_fraction: float
    bulk_viscosity_linear: float
    bulk_viscosity_quadratic: float

    @classmethod
    def from_scene(cls, scene: Scene) -> Material:
        m, s = scene["material"], scene["solver"]
        limit = m.get("friction_angle_limit_deg")
        if limit is not None and not limit > m["friction_angle_deg"]:
            raise SceneError(
                [
                    f"material.friction_angle_limit_deg = {limit!r} is out of range; allowed: "
                    f"> material.friction_angle_deg ({m['friction_angle_deg']!r}) and < 90"
                ]
            )
        return cls(
            density=m["density"],
            youngs_modulus=m["youngs_modulus"],
            poisson_ratio=m["poisson_ratio"],
            friction_angle_deg=m["friction_angle_deg"],
            cohesion=m["cohesion"],
            dilation_angle_deg=m["dilation_angle_deg"],
            wall_friction=m["wall_friction"],
            stiffness_scaling=s["stiffness_scaling"],
            tension_cutoff=s["tension_cutoff"],
            lost_contact=s["lost_contact"],
            friction_angle_limit_deg=None if limit is None else float(limit),
            inertial_number_i0=m["inertial_number_i0"],
            particle_diameter=m["particle_diameter"],
            packing_fraction=m["packing_fraction"],
            bulk_viscosity_linear=s["bulk_viscosity_linear"],
            bulk_viscosity_quadratic=s["bulk_viscosity_quadratic"],
        )

    def bulk_viscosity(self, h: float) -> tuple[float, float]:
        """(rho h b1 c_p, rho (b2 h)**2) for a cell h."""
        rho = self.density
        return (
            float(rho * h * self.bulk_viscosity_linear * self.p_wave_speed),
            float(rho * (self.bulk_viscosity_quadratic * h) ** 2),
        )

    @property
    def effective_modulus(self) -> float:
        return self.youngs_modulus / self.stiffness_scaling

    @property
    def bulk_shear(self) -> tuple[float, float]:
        k, g, _ = mc.elastic_constants(self.effective_modulus, self.poisson_ratio)
        return float(k), float(g)

    @property
    def p_wave_speed(self) -> float:
        return float(mc.p_wave_speed(self.effective_modulus, self.poisson_ratio, self.density))

    def return_arguments(self) -> tuple:
        """(K, G, sin phi, cos phi, c, sin psi, tension cutoff) for the stress update."""
        k, g = self.bulk_shear
        phi = math.radians(self.friction_angle_deg)
        psi = math.radians(self.dilation_angle_deg)
        if self.tension_cutoff and phi > 0:
            cutoff = self.cohesion / math.tan(phi)
        else:
            cutoff = 0.0
        values = (k, g, math.sin(phi), math.cos(phi), self.cohesion, math.sin(psi), cutoff)
        return tuple(float(a) for a in values)  # one compiled signature: all float64

    def rate_arguments(self) -> tuple[float, float, float]:
        """(μ2 − μs, I0, d sqrt(ρs)) of the μ(I) friction; rise 0 when rate-independent."""
        if self.friction_angle_limit_deg is None:
            return 0.0, 1.0, 0.0
        rise = math.tan(math.radians(self.friction_angle_limit_deg)) - math.tan(
            math.radians(self.friction_angle_deg)
        )
        grain_density = self.density / self.packing_fraction
        scale = self.particle_diameter * math.sqrt(grain_density)
        return float(rise), float(self.inertial_number_i0), float(scale)


# ----------------------------------------------------------------------------- state


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
        for name in self.fields:
            setattr(self, name, np.ascontiguousarray(getattr(self, name)[order]))

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
        self.g2p_work = mc.batch_work(threads, mpm.G2P_BLOCK if self.ndim == 3 else 1)

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.thread_grids, self.mass, self.momentum, self.velocity))


_MIRROR = np.array([1.0, 1.0, -1.0])  # z -> -z


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


def _rotation(theta: float, ndim: int) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    r = np.eye(ndim)
    r[0, 0], r[0, 1], r[1, 0], r[1, 1] = c, -s, s, c
    return r


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SolverSettings:
    cell: float
    output_cell: float
    per_cell: int
    courant: float
    rpm: float
    gravity: float
    settle_time: float
    damping: float
    revolutions: int
    phases: int
    duration: float | None
    average_window: float | None
    checkpoint_every: float
    seed: int
    # no defaults here: every value comes from the scene, whose schema holds them
    symmetry: str
    average_revolutions: int
    density_projection: int

    @classmethod
    def from_scene(cls, scene: Scene, vessel) -> SolverSettings:
        s, op, fl = scene["solver"], scene["operation"], scene["flow"]
        size = float(np.min(np.asarray(vessel.bounds[1]) - np.asarray(vessel.bounds[0])))
        output_cell = fl.get("cell")
        cell = s.get("cell", output_cell)
        if cell is None:
            cell = output_cell = size / 24.0
        output_cell = cell if output_cell is None else output_cell
        faults = []
        for key, value in (("solver.cell", cell), ("flow.cell", output_cell)):
            if value > 0.5 * size:
                faults.append(
                    f"{key} = {value!r} is out of range; allowed: <= half the vessel's "
                    f"smallest extent, {0.5 * size:.4g} m"
                )
        rpm = float(op["rpm"])
        average = int(s["average_revolutions"])
        if rpm > 0 and int(s["revolutions"]) < 2 * average:
            faults.append(
                f"solver.average_revolutions = {average} is out of range; allowed: <= "
                f"solver.revolutions / 2 = {int(s['revolutions']) / 2:g} (the average of the "
                "last revolutions is compared with the average of as many before)"
            )
        critical = critical_rpm(vessel, float(op["gravity"]))
        if rpm > critical:
            faults.append(
                f"operation.rpm = {rpm:g} is out of range; allowed: <= {critical:.4g}, this "
                "vessel's critical speed (the wall farthest from the axis feels the "
                "centripetal acceleration of gravity there: the bed centrifuges instead "
                "of tumbling, a flow this solver does not model)"
            )
        duration = op.get("duration")
        if rpm == 0 and duration is None:
            faults.append("operation.duration: needed when operation.rpm = 0")
        if faults:
            raise SceneError(faults)
        phases = int(fl.get("phases", DEFAULT_PHASES))
        if isinstance(vessel, Drum) or rpm == 0:
            phases = 1
        return cls(
            cell=float(cell),
            output_cell=float(output_cell),
            per_cell=int(s["particles_per_cell"]),
            courant=float(s["courant"]),
            rpm=rpm,
            gravity=float(op["gravity"]),
            settle_time=float(s["settle_time"]),
            damping=float(s["damping"]),
            revolutions=int(s["revolutions"]),
            phases=phases,
            duration=None if duration is None else float(duration),
            average_window=s.get("average_window"),
            checkpoint_every=float(s["checkpoint_every"]),
            seed=int(s["seed"]),
            symmetry=s["symmetry"],
            average_revolutions=average,
            density_projection=int(s["density_projection"]),
        )


def critical_rpm(vessel, gravity: float) -> float:
    """The speed at which the wall farthest from the rotation axis (the z axis through
    the origin) moves on a circle whose centripetal acceleration equals gravity:
    Froude number omega^2 R / g = 1, where a bed centrifuges."""
    lower, upper = (np.asarray(b, float) for b in vessel.bounds)
    axes = [np.linspace(lo, hi, 49) for lo, hi in zip(lower, upper, strict=True)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(axes))
    inside = points[vessel.sdf(points) <= 0.0]
    reach = float(np.hypot(inside[:, 0], inside[:, 1]).max()) if len(inside) else 0.0
    return 60.0 / (2.0 * math.pi) * math.sqrt(gravity / max(reach, 1e-12))


# ----------------------------------------------------------------------------- phases


class PhaseAverager:
    """Accumulates particle volume and volume-weighted velocity in phase bins.

    Bin k collects the samples whose phase lies within half a bin of ``k / n``; the fill
    of a bin is its mean particle volume per cell over its samples, the velocity its
    volume-weighted mean, each particle spread over the cells around it by the solver's
    quadratic B-splines (:func:`kernels.deposit_3d`), renormalised over the cells of
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
        self.vol = np.zeros((parts, phases, *self.shape))
        self.mom = np.zeros((parts, phases, *self.shape, self.ndim))
        self.samples = np.zeros(phases, np.int64)

    @property
    def nbytes(self) -> int:
        return self.vol.nbytes + self.mom.nbytes

    def bin_of(self, phase: float) -> int:
        return int(math.floor(phase * self.phases + 0.5)) % self.phases

    def add(self, k: int, x: np.ndarray, v: np.ndarray, vol: np.ndarray) -> None:
        parts = self.vol.shape[0]
        for half in range(parts):
            pick = slice(half, None, parts)
            out = (self.vol[half, k], self.mom[half, k])
            if self.ndim == 3:
                mpm.deposit_3d(x[pick], v[pick], vol[pick], self.origin, 1.0 / self.h,
                               self.inside, self.mirror, *out)  # fmt: skip
            else:
                mpm.deposit_2d(x[pick], v[pick], vol[pick], self.origin, 1.0 / self.h,
                               self.inside, *out)  # fmt: skip
        self.samples[k] += 1

    def take(self, other: PhaseAverager) -> None:
        """Hold ``other``'s averages (its halves summed when this one has none)."""
        if self.vol.shape[0] == other.vol.shape[0]:
            self.vol[...] = other.vol
            self.mom[...] = other.mom
        else:
            self.vol[0] = other.vol.sum(axis=0)
            self.mom[0] = other.mom.sum(axis=0)
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
        return self._fields(self.vol.sum(axis=0), self.mom.sum(axis=0))

    def half_fields(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:meth:`fields` of each half of the particles (each fill about half the total)."""
        return [self._fields(2.0 * v, 2.0 * m) for v, m in zip(self.vol, self.mom, strict=True)]

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
        return {f"{prefix}_vol": self.vol, f"{prefix}_mom": self.mom, f"{prefix}_n": self.samples}

    def load(self, prefix: str, arrays: dict) -> None:
        self.vol[...] = arrays[f"{prefix}_vol"]
        self.mom[...] = arrays[f"{prefix}_mom"]
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


# ----------------------------------------------------------------------------- simulation


#: Revolutions after which a dilating bed's flow has been seen to drift (docs/flow.md).
DILATION_DRIFT_AFTER = 3


def _warn_of_dilation(settings: SolverSettings, material: Material) -> None:
    """Warn when a rotating run records revolutions over which a dilating bed drifts.

    With ψ > 0 every yielding particle dilates by sin ψ per unit of plastic shear strain,
    with no end, and a tumbling bed yields all the time: in the 40 % Tote (ψ = 0.1°,
    Table 1) the particles' spacing grows 1.5 % a revolution and the mixing answer on
    revolutions 5 and 6 differs by a quarter from that on revolutions 2 to 4
    (benchmarks/results/flow_tote_drift.md); with ψ = 0 it holds.
    """
    if (
        settings.rpm > 0
        and settings.revolutions > DILATION_DRIFT_AFTER
        and material.dilation_angle_deg > 0
    ):
        warnings.warn(
            f"material.dilation_angle_deg = {material.dilation_angle_deg:g} dilates a "
            "tumbling bed without end, and flows recorded past revolution "
            f"{DILATION_DRIFT_AFTER} drift with it (docs/flow.md); set it to 0 for a "
            "flow that settles into a periodic state",
            UserWarning,
            stacklevel=3,
        )


#: Share of the bed's material the clipped fill may lose before the solver warns.
FILL_LOSS_WARN = 0.03


def _warn_of_clipped_fill(attrs) -> None:
    """Warn when clipping the fill at 1 drops more than FILL_LOSS_WARN of the material.

    The fill is the seeded particle volume per cell as the grid's B-splines see it, so
    a cell the particles pack denser than they were seeded reads above 1 and is
    clipped: what it held beyond a full cell is missing from the stored flow, whose bed
    is then smaller than the scene's. Particles crowd so where no stress sees it (they
    move with the grid velocity, their volumes with the affine matrix), the more the
    softer the material and the more steps a run takes, unless the density projection
    (``solver.density_projection``, on by default) moves them apart
    (benchmarks/results/flow_crowding.md).
    """
    carried = attrs["fill_volume_m3"] / attrs["material_volume_m3"]
    if carried < 1.0 - FILL_LOSS_WARN:
        warnings.warn(
            f"the flow's fill holds {carried:.1%} of the bed's material: particles packed "
            f"up to {attrs['fill_clipped_max']:.2f} times their seeded packing were clipped "
            f"at a full cell (stiffness scaling {attrs['stiffness_scaling']:g}; a stiffer "
            "material crowds less, docs/flow.md)",
            UserWarning,
            stacklevel=3,
        )


def _threads(particles: int) -> int:
    """Threads for a run: one below PARALLEL_MIN_PARTICLES.

    A parallel loop costs a wake-up of every thread per call (ten calls a step); on small
    beds that is most of the step, and on a shared machine a descheduled thread holds up
    every call (measured, 2 900 particles: 2.5 ms a step on one thread, 56 ms on two
    while another process ran).
    """
    if particles < PARALLEL_MIN_PARTICLES:
        return 1
    return max(1, numba.get_num_threads())


class FlowSimulation:
    """One run of the flow solver: particles, background grid, clock and phase averages.

    Parameters
    ----------
    scene : Scene, mapping, str or path
        The scene (vessel, operation, material, fill, flow and solver sections).
    gravity_direction : array_like, optional
        Lab-frame unit vector of gravity (default (0, -1[, 0])); tests of the wall law
        tilt it instead of the vessel.
    """

    def __init__(self, scene, *, gravity_direction=None):
        self.scene = load_scene(scene)
        self.vessel = vessel_from_scene(self.scene)
        self.settings = s = SolverSettings.from_scene(self.scene, self.vessel)
        self.material = Material.from_scene(self.scene)
        _warn_of_dilation(s, self.material)
        self.ndim = self.vessel.ndim
        direction = np.zeros(self.ndim)
        direction[1] = -1.0
        if gravity_direction is not None:
            direction = np.asarray(gravity_direction, float)[: self.ndim]
            direction = direction / np.linalg.norm(direction)
        self.gravity_direction = direction
        self._output_grid()
        positions, volume = self._seed()
        self.mirror = self._mirror_symmetric(positions)
        self.copies = 2 if self.mirror else 1  # bed particles per solved particle
        if self.mirror:
            positions = np.ascontiguousarray(positions[positions[:, 2] > 0.0])
        self.particles = Particles(positions, volume, self.material.density, self.mirror)
        self.particles.colour[:] = self._colour(positions)
        if self.mirror:
            self.particles.image_colour[:] = self._colour(positions * _MIRROR)
        self.grid = BackgroundGrid(
            self.vessel, s.cell, _threads(self.particles.count), mirror=self.mirror
        )
        self.bulk = self.material.bulk_viscosity(s.cell)
        # the G2P kernels' material tuple: the return's constants, with lost contact the
        # inverse of a node's mass at the seeded packing (kernels.g2p_2d), the mu(I)
        # friction's constants
        packed_node = self.material.density * s.cell**self.ndim
        self.stress_arguments = (
            self.material.return_arguments()
            + (1.0 / packed_node if self.material.lost_contact else 0.0,)
            + self.material.rate_arguments()
        )
        self.starts = mpm.chunk_starts(self.particles.count, self.grid.threads)
        self.projection = None
        if s.density_projection > 0:
            self.projection = DensityProjection(
                self.grid.node_sdf, s.cell, len(self.starts) - 1, self.grid.mirror_index
            )
        self.reflected = 0
        self.omega = 2.0 * math.pi * s.rpm / 60.0
        self.period = 60.0 / s.rpm if s.rpm > 0 else math.inf
        self.t = 0.0
        self.steps = 0
        self.vmax = 0.0
        self.projected = 0
        self.wall_seconds = 0.0
        self.particle_updates = 0
        self.lab_frame = isinstance(self.vessel, Drum) and s.rpm > 0
        grid = (self.out_origin, self.out_shape, s.output_cell, s.phases)
        keep = {"mirror": self.mirror, "inside": self.out_vessel}
        self.last = PhaseAverager(*grid, halves=True, **keep)
        self.previous = PhaseAverager(*grid, **keep)
        # rotating scenes record every revolution in turn, keeping the last two: the
        # revolution ``last`` holds (0: none yet) and eq. (30) between each completed
        # revolution and the one before, as (revolution, vx, vy[, vz]) on lab velocities
        self.recording = 0
        self.history: list[tuple] = []
        # fixed at the start (material at rest), so that a resumed run samples the same steps
        self.sample_every = self.samples_every()
        self._check_range()

    # --- set-up -----------------------------------------------------------------------
    def _seed(self):
        from ..vessels import fill_from_scene

        try:
            return fill_from_scene(self.vessel, self.scene, self.settings.cell)
        except ValueError as err:
            raise SceneError([f"fill: {err}"]) from None

    def _mirror_symmetric(self, positions: np.ndarray) -> bool:
        """Whether to solve one half of a bed that is mirror-symmetric about z = 0.

        The vessel frame's rotation axis is z, so gravity, centrifugal and Coriolis
        accelerations have no z part: when the vessel, the seeded bed and gravity are
        all symmetric under z -> -z, so is the exact flow, and the solver keeps the
        particles at z > 0 only (half the work and memory), with the plane z = 0 as an
        exact mirror (:func:`blendxr.flow.kernels.fold_mirror_3d`). ``solver.symmetry``
        = "none" solves the whole bed; "mirror-z" insists on the half (an error when the
        scene is not symmetric); "auto" takes the half when it can.
        """
        mode = self.settings.symmetry
        if mode == "none":
            return False
        reason = self._asymmetry(positions)
        if reason and mode == "mirror-z":
            raise SceneError([f"solver.symmetry = 'mirror-z': {reason}; allowed: 'auto' or 'none'"])
        return reason is None

    def _asymmetry(self, positions: np.ndarray) -> str | None:
        """Why the scene is not mirror-symmetric about z = 0 (None when it is)."""
        if self.ndim != 3:
            return "the scene is 2-D"
        if self.gravity_direction[2] != 0.0:
            return "gravity has a z component"
        lower, upper = (np.asarray(b, float) for b in self.vessel.bounds)
        h = self.settings.cell
        axes = [np.arange(lower[a] - h, upper[a] + 1.5 * h, h) for a in range(3)]
        axes[2] = np.concatenate([-axes[2][::-1], axes[2]])
        nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
        tol = 1e-9 * float(np.max(upper - lower))
        if not np.allclose(self.vessel.sdf(nodes), self.vessel.sdf(nodes * _MIRROR), atol=tol):
            return "the vessel is not symmetric about z = 0 (tilted or off-centre)"
        if not _centred_in_z(self.out_origin, self.settings.output_cell, self.out_shape):
            return "the output grid is not symmetric about z = 0"
        above = positions[positions[:, 2] > 0.0]
        below = positions[positions[:, 2] < 0.0] * _MIRROR
        if len(above) + len(below) != len(positions) or len(above) != len(below):
            return "the seeded bed is not symmetric about z = 0"
        order_a = np.lexsort(above.T[::-1])
        order_b = np.lexsort(below.T[::-1])
        if not np.allclose(above[order_a], below[order_b], rtol=0.0, atol=tol):
            return "the seeded bed is not symmetric about z = 0"
        return None

    def _colour(self, x: np.ndarray) -> np.ndarray:
        """Colour 1 for species A by the scene's loading at phase 0 (DESIGN §2)."""
        loading = self.scene["mixing"]["loading"]
        if loading in ("axial", "side-side", "left-right") and self.ndim == 3:
            return (x[:, 2] < 0).astype(float)
        if loading == "transverse" or loading in ("axial", "side-side", "left-right"):
            return (x[:, 0] < 0).astype(float)
        return (x[:, 1] >= np.median(x[:, 1])).astype(float)

    def dataset(
        self, revolution: str = "last", *, wall: float | None = None, stopped: str = "time"
    ) -> xr.Dataset:
        """The flow dataset (``flow/1``) of the run so far: the phase averages of its last
        recorded revolution (or with ``revolution="previous"`` of the one before), with
        the solver's attributes (periodicity, packing, cost; ``wall``: the wall time to
        report, default the stepping loop's)."""
        return _flow_from(self, self.wall_seconds if wall is None else wall, stopped, revolution)

    def _output_grid(self) -> None:
        grid = output_grid(self.vessel, self.settings.output_cell)
        self.out_origin, self.out_shape, self.out_axes, self.out_vessel = grid

    def _check_range(self) -> None:
        p, g = self.particles, self.grid
        bad = mpm.particles_in_range(p.x, g.origin, 1.0 / g.h, np.asarray(g.shape, np.int64))
        if bad >= 0:
            where = ", ".join(f"{c:.4g}" for c in p.x[bad])
            raise FlowBlowUpError(
                f"step {self.steps}, t = {self.t:.6g} s: particle {bad} at ({where}) m left "
                "the background grid (the run went unstable)"
            )

    # --- time step --------------------------------------------------------------------
    def stable_dt(self) -> float:
        """dt = courant * cell / (c_p + |v|max) (DESIGN §4)."""
        return self.settings.courant * self.grid.h / (self.material.p_wave_speed + self.vmax)

    def _body(self, t: float) -> tuple[np.ndarray, float, float]:
        """Gravity in the vessel frame, omega and damping at time t."""
        s = self.settings
        g = s.gravity
        if t < s.settle_time:
            ramp = RAMP_SHARE * s.settle_time
            scale = min(1.0, t / ramp) if ramp > 0 else 1.0
            damping = s.damping if t < ramp else 0.0
            return self.gravity_direction * g * scale, 0.0, damping
        # the vessel has turned by theta about +z: lab vectors appear turned by -theta
        theta = self.omega * (t - s.settle_time)
        return _rotation(-theta, self.ndim) @ (self.gravity_direction * g), self.omega, 0.0

    def step(self, dt: float) -> None:
        """One MPM step: P2G, grid update, G2P, stress update."""
        p, g = self.particles, self.grid
        if self.steps % SORT_EVERY == 0:
            order = mpm.sort_by_cell(p.x, g.origin, 1.0 / g.h, np.asarray(g.shape, np.int64))
            p.permute(order)
        gravity, omega, damping = self._body(self.t + 0.5 * dt)
        three = self.ndim == 3
        inv_h = 1.0 / g.h
        (mpm.p2g_3d if three else mpm.p2g_2d)(
            p.x, p.v, p.C, p.mass, p.vol, p.stress, g.origin, inv_h, dt, self.bulk,
            g.thread_grids, self.starts,
        )  # fmt: skip
        (mpm.reduce_grids_3d if three else mpm.reduce_grids_2d)(g.thread_grids, g.mass, g.momentum)
        if self.mirror:
            mpm.fold_mirror_3d(g.mass, g.momentum, g.mirror_index)
        (mpm.grid_update_3d if three else mpm.grid_update_2d)(
            g.mass, g.momentum, g.velocity, g.origin, g.h, dt, gravity, omega, damping,
            g.node_sdf, g.node_normal, self.material.wall_friction, WALL_BAND * g.h,
        )  # fmt: skip
        # G2P updates the stress too; walls: exact distances below, not interpolated ones
        # (biased at convex walls)
        (mpm.g2p_3d if three else mpm.g2p_2d)(
            p.x, p.v, p.C, p.vol, p.J, p.gap, p.stress, p.codes, g.velocity, g.mass, g.origin,
            inv_h, dt, self.stress_arguments, self.starts, g.g2p_work,
        )  # fmt: skip
        if self.projection is not None and self.steps % self.settings.density_projection == 0:
            self.projection(p.x, p.vol, g.origin, self.starts)
        if self.mirror:
            self.reflected += reflect_across_mirror(
                p.x, p.v, p.C, p.stress, 0.0, self.starts, g.scratch
            )
        self.projected += project_into_vessel(
            self.vessel.kind, self.vessel.params, p.x, p.v, WALL_SKIN * g.h, self.starts,
            g.scratch, g.node_sdf.reshape(-1), g.origin, g.h, g.shape_array,
        )  # fmt: skip
        self.t += dt
        self.steps += 1
        self.particle_updates += p.count
        if self.steps % SPEED_CHECK_EVERY == 0:
            self._check_state()

    def _check_state(self) -> None:
        p = self.particles
        speed = np.sqrt(np.einsum("ij,ij->i", p.v, p.v))
        worst = int(np.argmax(np.where(np.isfinite(speed), speed, np.inf)))
        vmax = float(speed[worst])
        limit = self.speed_limit()
        if not math.isfinite(vmax) or vmax > limit:
            where = ", ".join(f"{c:.4g}" for c in p.x[worst])
            raise FlowBlowUpError(
                f"step {self.steps}, t = {self.t:.6g} s: particle {worst} at ({where}) m "
                f"has speed {vmax:.4g} m/s, beyond {limit:.4g} m/s (free fall from the "
                "vessel's height plus its wall speed, times 10): the run went unstable"
            )
        self.vmax = vmax
        self._check_range()

    def speed_limit(self) -> float:
        lower, upper = (np.asarray(b, float) for b in self.vessel.bounds)
        size = float(np.linalg.norm(upper - lower))
        radius = float(np.max(np.abs(np.concatenate([lower, upper]))))
        return 10.0 * (math.sqrt(2.0 * self.settings.gravity * size) + self.omega * radius) + 1.0

    # --- recording --------------------------------------------------------------------
    def revolution(self) -> float:
        """Revolutions turned so far (0 while settling)."""
        if not math.isfinite(self.period):
            return 0.0
        return max(0.0, (self.t - self.settings.settle_time) / self.period)

    def end_time(self) -> float:
        s = self.settings
        if s.rpm > 0:
            return s.settle_time + s.revolutions * self.period
        return s.settle_time + s.duration

    def _window(self) -> tuple[float, float, float]:
        """(start of the previous averaging window, start of the last, end) in seconds
        of a non-rotating scene (rotating ones record revolution by revolution)."""
        s = self.settings
        end = self.end_time()
        w = s.average_window or 0.25 * s.duration
        return end - 2 * w, end - w, end

    def record(self) -> None:
        """Deposit the current particle state into its phase bin (when in a window).

        Particles count with their seeded volume (mass over density): the fill is the
        material's volume at the packing it was filled at, so the fill the mixing model
        carries is conserved like mass. The current volume (J times it) would count the
        dilation of the hypoelastic model at the stress-free apex, which accumulates in
        a cohesionless flowing layer (+8 to +12 % over two revolutions of a 2-D drum,
        measured) where the real material, with a dilation angle of 0.1 degrees, keeps
        its volume.
        """
        s = self.settings
        if s.rpm > 0:
            turning = self.turning_revolution()
            if turning < 1:
                return
            # the first sample starts a block whatever _block(0) says; within a block
            # ``recording`` follows the revolution, so a block is labelled by its last
            if self.recording == 0 or self._block(turning) != self._block(self.recording):
                self._roll()
            self.recording = turning
            target = self.last
            phase = (self.t - s.settle_time) / self.period % 1.0
        else:
            start_prev, start_last, _ = self._window()
            if self.t < start_prev:
                return
            target = self.last if self.t >= start_last else self.previous
            phase = 0.0
        p = self.particles
        if self.lab_frame:
            theta = self.omega * (self.t - self.settings.settle_time)
            r = _rotation(theta, self.ndim)
            x = p.x @ r.T
            vel = p.v.copy()
            vel[:, 0] -= self.omega * p.x[:, 1]
            vel[:, 1] += self.omega * p.x[:, 0]
            target.add(0, np.ascontiguousarray(x), np.ascontiguousarray(vel @ r.T), p.vol0)
        else:
            target.add(target.bin_of(phase), p.x, p.v, p.vol0)

    def turning_revolution(self) -> int:
        """The revolution being turned (1 from the end of settling; a sample at a
        revolution's end belongs to it), 0 while settling."""
        turned = (self.t - self.settings.settle_time) / self.period
        return max(0, math.ceil(turned - 1e-9))

    def _block(self, revolution: int) -> int:
        """The block of ``solver.average_revolutions`` revolutions that ``revolution``
        belongs to, counted back from the last revolution of the run (block 0): the flow
        averages the last block, eq. (30) compares it with block 1. One revolution a
        block by default, as the paper."""
        s = self.settings
        return (s.revolutions - revolution) // s.average_revolutions

    def _roll(self) -> None:
        """Start recording a new block: eq. (30) between the block just completed and
        the one before goes into the history (labelled with the completed block's last
        revolution, ``recording``), then the last becomes the previous."""
        if self.recording > 0 and self.both_recorded():
            change = revolution_change(self, self.previous, self.last)
            self.history.append(self._history_row(change))
        self.previous.take(self.last)
        self.last.clear()

    def both_recorded(self) -> bool:
        """Whether the last two averaging windows (revolutions) are both complete."""
        return self.previous.complete() and self.last.complete()

    def _history_row(self, change: dict) -> tuple:
        return (self.recording, *(change[f"v{c}"] for c in "xyz"[: self.ndim]))

    def periodicity_history(self, change: dict | None = None) -> list[tuple]:
        """Eq. (30) between every two successive revolutions recorded, the last two
        included: ``(revolution j + 1, vx, vy[, vz])`` on lab-frame velocities, as the
        paper's Table 3 gives it. ``change``: the last two's
        :func:`revolution_change`, when the caller has it already."""
        rows = list(self.history)
        if self.recording > 0 and self.both_recorded():
            if change is None:
                change = revolution_change(self, self.previous, self.last)
            rows.append(self._history_row(change))
        return rows

    # --- checkpoints ------------------------------------------------------------------
    def fingerprint(self) -> str:
        import hashlib

        return hashlib.sha256(self.scene.to_toml().encode()).hexdigest()[:16]

    def save_checkpoint(self, path: Path) -> None:
        from ..io import write_checkpoint

        arrays = dict(self.particles.arrays())
        arrays.update(self.last.arrays("last"))
        arrays.update(self.previous.arrays("previous"))
        meta = {
            "t": self.t,
            "steps": self.steps,
            "vmax": self.vmax,
            "projected": self.projected,
            "reflected": self.reflected,
            "particle_updates": self.particle_updates,
            "wall_seconds": self.wall_seconds,
            "recording": self.recording,
            "history": [list(row) for row in self.history],
            "fingerprint": self.fingerprint(),
            "blendxr_version": __version__,
        }
        write_checkpoint(path, arrays, meta)

    def load_checkpoint(self, path: Path) -> None:
        from ..io import read_checkpoint

        arrays, meta = read_checkpoint(path)
        if meta.get("fingerprint") != self.fingerprint():
            raise ValueError(
                f"checkpoint {path} belongs to another scene; remove it or pass resume=False"
            )
        self.particles.load(arrays)
        self.starts = mpm.chunk_starts(self.particles.count, self.grid.threads)
        self.last.load("last", arrays)
        self.previous.load("previous", arrays)
        self.t = float(meta["t"])
        self.steps = int(meta["steps"])
        self.vmax = float(meta["vmax"])
        self.projected = int(meta["projected"])
        self.reflected = int(meta.get("reflected", 0))
        self.particle_updates = int(meta["particle_updates"])
        self.wall_seconds = float(meta["wall_seconds"])
        self.recording = int(meta.get("recording", 0))
        self.history = [tuple(row) for row in meta.get("history", [])]

    # --- driving ----------------------------------------------------------------------
    def samples_every(self) -> int:
        """Steps between deposits: about 12 samples per phase bin and window."""
        s = self.settings
        dt = self.stable_dt()
        if s.rpm > 0:
            window = self.period
        else:
            window = s.average_window or 0.25 * s.duration
        # at least 200 samples per phase bin: the averages of an intermittent granular
        # flow need many (a B-spline deposit costs about as much a particle as a P2G)
        per_window = window / dt
        return max(1, int(per_window / max(s.phases, 1) / 200))

    def run(
        self,
        *,
        until: float | None = None,
        wall_time: float | None = None,
        max_steps: int | None = None,
        checkpoint: Path | None = None,
        progress: bool | None = None,
        callback=None,
    ) -> str:
        """Step until simulated time ``until`` (default: the scene's end), a wall-clock
        budget or a step count; returns what stopped the run."""
        end = self.end_time() if until is None else float(until)
        every = self.sample_every
        bar = _progress_bar(progress, end, self)
        threads_before = numba.get_num_threads()
        numba.set_num_threads(min(self.grid.threads, threads_before))
        started = time.perf_counter()
        last_save = started
        stopped = "time"
        try:
            while self.t < end - 1e-12:
                dt = min(self.stable_dt(), end - self.t)
                try:
                    self.step(dt)
                except FlowBlowUpError:
                    if checkpoint is not None:
                        bar.write(f"last checkpoint kept: {checkpoint}")
                    raise
                if self.steps % every == 0:
                    self.record()
                if callback is not None:
                    callback(self)
                now = time.perf_counter()
                if self.steps % 50 == 0:
                    _update_bar(bar, self, now - started)
                if checkpoint is not None and now - last_save >= self.settings.checkpoint_every:
                    self.save_checkpoint(checkpoint)
                    last_save = now
                if wall_time is not None and now - started >= wall_time:
                    stopped = "wall_time"
                    break
                if max_steps is not None and self.steps >= max_steps:
                    stopped = "max_steps"
                    break
        finally:
            self.wall_seconds += time.perf_counter() - started
            numba.set_num_threads(threads_before)
            bar.close()
        if checkpoint is not None:
            self.save_checkpoint(checkpoint)
        return stopped


def _progress_bar(progress, end: float, sim: FlowSimulation):
    from tqdm.auto import tqdm

    show = os.isatty(2) if progress is None else progress
    bar = tqdm(
        total=round(end, 6),
        unit="s",
        disable=not show,
        leave=False,
        bar_format="{l_bar}{bar}| {n:.3f}/{total:.3f} s simulated [{elapsed}<{remaining}{postfix}]",
    )
    bar.n = round(sim.t, 6)
    return bar


def _update_bar(bar, sim: FlowSimulation, elapsed: float) -> None:
    bar.n = round(min(sim.t, bar.total), 6)
    rate = sim.particle_updates / max(elapsed + sim.wall_seconds, 1e-9)
    bar.set_postfix_str(f"rev {sim.revolution():.2f}, {rate / 1e6:.2f} M particle-steps/s")


# ----------------------------------------------------------------------------- public


def _whole_bed(sim: FlowSimulation) -> dict[str, np.ndarray]:
    """The particle arrays of the whole bed: a mirror-symmetric run adds the images."""
    p = sim.particles
    arrays = {name: getattr(p, name) for name in Particles.FIELDS}
    if not sim.mirror:
        return arrays
    flip = np.outer(_MIRROR, _MIRROR)  # R A R for R = diag(_MIRROR)
    images = dict(arrays, x=p.x * _MIRROR, v=p.v * _MIRROR, C=p.C * flip,
                  stress=p.stress * flip, colour=p.image_colour)  # fmt: skip
    return {name: np.concatenate([arrays[name], images[name]]) for name in arrays}


def _particle_dataset(sim: FlowSimulation) -> xr.Dataset:
    p = SimpleNamespace(**_whole_bed(sim))
    axes = "xyz"[: sim.ndim]
    data = {
        "position": (("particle", "component"), p.x, {"units": "m", "long_name": "position"}),
        "velocity": (
            ("particle", "component"),
            p.v,
            {"units": "m s-1", "long_name": "velocity relative to the vessel frame"},
        ),
        "stress": (
            ("particle", "row", "column"),
            p.stress,
            {"units": "Pa", "long_name": "Cauchy stress, tension positive"},
        ),
        "affine": (
            ("particle", "component", "column2"),
            p.C,
            {"units": "s-1", "long_name": "APIC affine velocity matrix"},
        ),
        "volume": (("particle",), p.vol, {"units": "m3", "long_name": "current volume"}),
        "contact_gap": (
            ("particle",),
            p.gap,
            {"units": "1", "long_name": "volume lost to contact per unit volume (closes first)"},
        ),
        "volume0": (("particle",), p.vol0, {"units": "m3", "long_name": "initial volume"}),
        "mass": (("particle",), p.mass, {"units": "kg", "long_name": "mass"}),
        "colour": (("particle",), p.colour, {"units": "1", "long_name": "species A at phase 0"}),
    }
    ds = xr.Dataset(
        data,
        coords={"component": list(axes), "row": list("xyz"), "column": list("xyz"),
                "column2": list(axes)},
        attrs={
            "title": "blendxr particle state",
            "source": f"blendxr {__version__}",
            "Conventions": "CF-1.11",
            "scene": sim.scene.to_toml(),
            "time_s": sim.t,
            "steps": sim.steps,
            "frame": "vessel",
        },
    )  # fmt: skip
    if sim.mirror:
        n = sim.particles.count
        ds.attrs["mirror_plane"] = (
            f"z = 0: particles {n} to {2 * n - 1} are the mirror images of particles 0 to "
            f"{n - 1}, which the solver computed (solver.symmetry)"
        )
    return ds


def lab_velocities(sim: FlowSimulation, vel: np.ndarray) -> np.ndarray:
    """Phase-binned vessel-frame velocities seen from the lab: R(theta_k) (v + w x r).

    Parameters
    ----------
    sim : FlowSimulation
        The run whose output grid and rotation rate the fields have.
    vel : ndarray, shape (n, *cells, d)
        Vessel-frame velocities of the n phase bins on the output cells.

    Returns
    -------
    ndarray, same shape
        The velocities in the lab frame, the vessel turned by 2 pi k / n in bin k.
    """
    out = np.empty_like(vel)
    centres = np.stack(np.meshgrid(*sim.out_axes, indexing="ij"), axis=-1)
    for k in range(vel.shape[0]):
        u = vel[k].copy()
        u[..., 0] -= sim.omega * centres[..., 1]
        u[..., 1] += sim.omega * centres[..., 0]
        rotation = _rotation(2.0 * math.pi * k / vel.shape[0], sim.ndim)
        out[k] = u @ rotation.T
    return out


def revolution_change(
    sim: FlowSimulation, before: PhaseAverager, after: PhaseAverager, *, vessel_frame=False
) -> dict:
    """Eq. (30) (:func:`periodicity`) between two recorded revolutions of a run, as
    :func:`fields_change` of their phase-binned fields."""
    return fields_change(sim, before.fields()[:2], after.fields()[:2], vessel_frame=vessel_frame)


def fields_change(sim: FlowSimulation, before: tuple, after: tuple, *, vessel_frame=False) -> dict:
    """Eq. (30) (:func:`periodicity`) from one set of phase-binned fields of a run to
    another, on lab-frame velocities (the frame of the paper's fixed mesh); with
    ``vessel_frame`` also on the stored vessel-frame ones of a rotating vessel, as
    ``vessel_frame_*`` (stricter: they lack the rigid rotation).

    Parameters
    ----------
    sim : FlowSimulation
        The run the fields come from (its output grid, frame and rotation rate).
    before, after : tuple of ndarray
        ``(fill, velocity)`` as :meth:`PhaseAverager.fields` gives them: one revolution's
        averages, or any fill-weighted combination of them.
    """
    (fill_b, vel_b), (fill_a, vel_a) = before, after
    out = {}
    if not (sim.lab_frame or sim.settings.rpm == 0):
        if vessel_frame:
            vessel = periodicity(vel_b, vel_a, fill_b, fill_a)
            out.update({f"vessel_frame_{name}": value for name, value in vessel.items()})
        vel_b, vel_a = lab_velocities(sim, vel_b), lab_velocities(sim, vel_a)
    return {**periodicity(vel_b, vel_a, fill_b, fill_a), **out}


def _projection_attrs(sim: FlowSimulation) -> dict:
    """What the density projection did and cost (nothing when it is off)."""
    pr = sim.projection
    if pr is None:
        return {}
    return {
        "density_projection_every": sim.settings.density_projection,
        "density_projection_calls": pr.calls,
        "density_projection_cg_iterations": pr.iterations,
        "density_projection_wall_s": pr.wall_seconds,
        "density_projection_last_fill_max": pr.worst_fill,
    }


def node_packing(sim: FlowSimulation, quantiles=(0.5, 0.99, 1.0)) -> dict:
    """Quantiles of the particles' packing on the nodes inside the bed, over the seeded
    packing: the seeded volumes scattered with the B-splines over each node's capacity
    (:func:`projection.node_capacity`), on the nodes filled to at least half of it.

    Independent of the output cells' counts, which with a few particles a cell are
    dominated by the particles' sampling noise.
    """
    from .projection import MATERIAL, DensityProjection, classify_2d, classify_3d

    g, p = sim.grid, sim.particles
    probe = sim.projection or DensityProjection(
        g.node_sdf, g.h, len(sim.starts) - 1, g.mirror_index
    )
    fill = probe.node_fill(p.x, p.vol0, g.origin, sim.starts).copy()
    code = np.zeros(fill.shape, np.int8)
    (classify_3d if sim.ndim == 3 else classify_2d)(fill, probe.capacity, probe.air, code)
    inside = code == MATERIAL
    if sim.mirror:
        inside[:, :, : g.mirror_index] = False  # images
    if not inside.any():
        return {}
    ratio = fill[inside] / probe.capacity[inside]
    return {f"node_packing_q{round(100 * q):g}": float(np.quantile(ratio, q)) for q in quantiles}


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
        "open; _wall: the cells within 2 cells of the first cell outside the vessel, "
        "_interior: the rest"
    )
    return out


def occupied_volume_over_seeded(sim: FlowSimulation) -> float:
    """The volume the particles occupy, from their spacing, over their seeded volume.

    The seeded particles per solver cell (``per_cell ** d``) over the mean count in the
    cells inside the bed, those whose neighbours (3^d block) all hold particles, so that
    the bed's surface, its walls and a mirror plane leave no partly filled cell in the
    mean. It is 1 exactly for a freshly seeded bed and measures a dilation from where the
    particles are, independent of the J the solver integrates
    (:attr:`Particles.volume_over_seeded`), which drifts from it in a flowing bed (the
    particles move with the interpolated grid velocity, J with the affine matrix).
    NaN when no cell lies inside the bed.
    """
    from scipy.ndimage import binary_erosion

    g = sim.grid
    shape = tuple(int(n) for n in g.shape)
    cells = np.floor((sim.particles.x - g.origin) / g.h).astype(np.int64)
    cells = np.clip(cells, 0, np.asarray(shape) - 1)
    counts = np.bincount(np.ravel_multi_index(tuple(cells.T), shape), minlength=math.prod(shape))
    counts = counts.reshape(shape)
    inside = binary_erosion(counts > 0, structure=np.ones((3,) * sim.ndim, bool))
    if not inside.any():
        return float("nan")
    return float(sim.settings.per_cell**sim.ndim / counts[inside].mean())


def sampling_noise(sim: FlowSimulation, *, vessel_frame=False) -> dict:
    """The part of eq. (30) that the sampling noise of the phase averages alone accounts
    for: :func:`periodicity` between the averages of the even- and odd-numbered
    particles of the last revolution, over sqrt 2 (each half has twice the variance of
    the whole, so two independent whole-sample averages would differ by 1/sqrt 2 of
    it). Lab-frame velocities as :func:`revolution_change`, or with ``vessel_frame`` the
    stored ones."""
    (fill_a, vel_a, _), (fill_b, vel_b, _) = sim.last.half_fields()
    if not (vessel_frame or sim.lab_frame or sim.settings.rpm == 0):
        vel_a, vel_b = (lab_velocities(sim, v) for v in (vel_a, vel_b))
    return {
        name: value / math.sqrt(2.0)
        for name, value in periodicity(vel_a, vel_b, fill_a, fill_b).items()
    }


def _flow_from(
    sim: FlowSimulation, wall: float, stopped: str, revolution: str = "last"
) -> xr.Dataset:
    """The flow dataset of a run: the phase averages of its last recorded revolution, or
    with ``revolution="previous"`` of the one before (to see what the choice of
    revolution does downstream, e.g. to the mixing); the periodicity attributes compare
    the two either way."""
    s = sim.settings
    if revolution not in ("last", "previous"):
        raise ValueError(f"revolution: 'last' or 'previous', not {revolution!r}")
    recorded = sim.last if revolution == "last" else sim.previous
    fill, vel, raw = recorded.fields()
    attrs = {
        "solver": "MLS-MPM/APIC, quadratic B-splines, Mohr-Coulomb (blendxr.flow.solver)",
        "solver_cell_m": s.cell,
        "particles": sim.particles.count * sim.copies,
        "particles_solved": sim.particles.count,
        "mirror_plane": "z = 0 (half the bed solved)" if sim.mirror else "none",
        "particles_per_cell": s.per_cell,
        "steps": sim.steps,
        "simulated_time_s": sim.t,
        "wall_time_s": wall,
        "particle_updates_per_s": sim.particle_updates / max(sim.wall_seconds, 1e-9),
        "stopped_by": stopped,
        "stiffness_scaling": sim.material.stiffness_scaling,
        "p_wave_speed_m_s": sim.material.p_wave_speed,
        "courant": s.courant,
        "dt_last_s": sim.stable_dt(),
        "material_volume_m3": float(sim.particles.vol0.sum()) * sim.copies,
        "fill_volume_before_clipping_m3": float(raw.mean(axis=0).sum() * s.output_cell**sim.ndim),
        "fill_volume_m3": float(fill.mean(axis=0).sum() * s.output_cell**sim.ndim),
        "current_volume_over_seeded": sim.particles.volume_over_seeded,
        "occupied_volume_over_seeded": occupied_volume_over_seeded(sim),
        "fill_clipped_max": float(raw.max()),
        **fill_histogram(raw, sim.out_vessel),
        "projected_particles": sim.projected,
        "reflected_particles": sim.reflected,
        **_projection_attrs(sim),
        **node_packing(sim),
        "revolutions_turned": sim.revolution(),
        "recorded_revolution": revolution,
        "averaged_revolutions": s.average_revolutions if s.rpm > 0 else 0,
        "samples_per_phase": recorded.samples.tolist(),
    }
    change = None
    if sim.both_recorded():
        change = revolution_change(sim, sim.previous, sim.last, vessel_frame=True)
        for name, value in change.items():
            attrs[f"periodicity_{name}"] = value
        for name, value in sampling_noise(sim).items():
            attrs[f"periodicity_noise_{name}"] = value
        attrs["periodicity_definition"] = (
            "eq. (30) between the last two recorded revolutions (averaged_revolutions > "
            "1: between the averages of the last so many revolutions and of as many "
            "before; rpm = 0: the last two "
            "averaging windows) on lab-frame velocities (the frame of the paper's fixed "
            "Eulerian mesh; periodicity_vessel_frame_*: the same on the stored "
            "vessel-frame velocities, which lack the rigid rotation and are stricter), "
            "cells with fill > 0.5 in both and |v| above 5 % of the component's largest; "
            "*_norm: sum |dv| / sum |v| over the same cells; periodicity_noise_*: the "
            "part sampling noise alone accounts for, eq. (30) between the averages of the "
            "even- and odd-numbered particles of the last revolution, over sqrt(2)"
        )
    history = sim.periodicity_history(change) if s.rpm > 0 else []
    if history:
        rows = np.asarray(history, float)
        attrs["periodicity_history_revolution"] = rows[:, 0].astype(np.int64)
        for a, c in enumerate("xyz"[: sim.ndim]):
            attrs[f"periodicity_history_v{c}"] = rows[:, a + 1]
        attrs["periodicity_history_definition"] = (
            "eq. (30) on lab-frame velocities as periodicity_v*, between each recorded "
            "revolution j + 1 = periodicity_history_revolution and the one before "
            "(the paper's Table 3; averaged_revolutions > 1: between each block of so "
            "many revolutions, labelled with its last revolution, and the block before); "
            "the last entry is periodicity_v*"
        )
    axes = dict(zip("xyz", sim.out_axes, strict=False))
    phases = np.arange(s.phases) / s.phases
    comps = [vel[..., a] for a in range(sim.ndim)]
    return flow_dataset(
        axes["x"],
        axes["y"],
        phases,
        comps[0],
        comps[1],
        fill,
        sim.out_vessel,
        z=axes.get("z"),
        vz=comps[2] if sim.ndim == 3 else None,
        frame="lab" if sim.lab_frame else "vessel",
        rpm=s.rpm,
        gravity=s.gravity,
        scene=sim.scene,
        title=f"blendxr flow: {sim.scene.name}",
        attrs=attrs,
    )


def solve_flow(
    scene,
    *,
    particles: bool = False,
    checkpoint: str | os.PathLike | None = None,
    resume: bool = True,
    progress: bool | None = None,
    wall_time: float | None = None,
    **solver_overrides,
):
    """Compute a scene's flow with the built-in Mohr-Coulomb solver (DESIGN §4).

    Parameters
    ----------
    scene : Scene, mapping, str or path
        A scene or the name of a built-in one.
    particles : bool
        Also return the final particle state (positions, velocities, stress, colour) as
        a Dataset with a ``particle`` dimension.
    checkpoint : path, optional
        File kept up to date every ``solver.checkpoint_every`` wall-clock seconds and at
        the end; with ``resume`` an existing one for the same scene is continued.
    resume : bool
        Continue from ``checkpoint`` when it exists.
    progress : bool, optional
        Show a progress bar (default: when standard error is a terminal).
    wall_time : float, optional
        Stop after this many wall-clock seconds (the checkpoint allows a resume).
    **solver_overrides
        Keys of the scene's ``solver`` section (``cell``, ``revolutions``,
        ``stiffness_scaling``, ...), applied before validation.

    Returns
    -------
    xarray.Dataset or (xarray.Dataset, xarray.Dataset)
        The flow dataset (schema ``flow/1``), and the particle state if asked for.

    Raises
    ------
    SceneError
        A scene value out of its physical range, named with its allowed range.
    FlowBlowUpError
        The run went unstable; the message gives the step, time and place.
    """
    scene = load_scene(scene)
    if solver_overrides:
        section = dict(scene["solver"])
        section.update(solver_overrides)
        scene = scene.replace(solver=section)
    started = time.perf_counter()
    sim = FlowSimulation(scene)
    path = Path(checkpoint) if checkpoint is not None else None
    if path is not None and resume and path.exists():
        sim.load_checkpoint(path)
    stopped = sim.run(checkpoint=path, progress=progress, wall_time=wall_time)
    if stopped != "time":
        raise RuntimeError(
            f"the flow run stopped early ({stopped}) at t = {sim.t:.4g} s of "
            f"{sim.end_time():.4g} s; call again with the same checkpoint to resume"
        )
    flow = _flow_from(sim, time.perf_counter() - started, stopped)
    _warn_of_clipped_fill(flow.attrs)
    if particles:
        return flow, _particle_dataset(sim)
    return flow
