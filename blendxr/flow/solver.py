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

import numba
import numpy as np
import xarray as xr

from .. import __version__
from ..driver import CheckpointSchedule, StopRules, memory_limit, progress_bar
from ..scene import Scene, SceneError, load_scene
from ..vessels import Drum, vessel_from_scene
from . import kernels as mpm
from .averaging import (
    OutputGrid,
    PhaseAverager,
    _centred_in_z,
    output_grid,
    rotation,
    vessel_to_lab,
)
from .material import Material
from .output import (
    _flow_from,
    _particle_dataset,
    _warn_of_clipped_fill,
    revolution_change,
)
from .projection import DensityProjection
from .state import _MIRROR, GRID_PADDING, BackgroundGrid, Particles
from .walls import project_into_vessel, reflect_across_mirror

__all__ = ["FlowBlowUpError", "FlowSimulation", "Material", "solve_flow"]

SORT_EVERY = 20  # steps between re-sorting particles by cell (keeps P2G chunks coherent)
SPEED_CHECK_EVERY = 10  # steps between updates of |v|max for dt (cheap; v changes slowly)
RAMP_SHARE = 0.6  # share of the settling time over which gravity ramps up (damped)
PARALLEL_MIN_PARTICLES = 20_000  # smaller beds run on one thread (see _threads)
DEFAULT_PHASES = 36
WALL_BAND = 0.5  # nodes closer to the wall than this many cells get the wall law (docs/flow.md)
WALL_SKIN = 1e-3  # projected particles land this many cells inside the wall
# the spin-up revolution (1, when neither kept nor compared with the kept one: only its
# change to revolution 2 is reported) is sampled every this many samples
SPIN_UP_THINNING = 4


class FlowBlowUpError(RuntimeError):
    """The flow solver went unstable; the message gives the step, time and place."""


# ----------------------------------------------------------------------------- state


# ----------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SolverSettings:
    cell: float
    output_cell: float
    per_cell: int
    courant: float
    spin_up_courant: float
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

    @property
    def end_time(self) -> float:
        """Simulated seconds of the run: settling, then the revolutions (or duration)."""
        turning = self.revolutions * 60.0 / self.rpm if self.rpm > 0 else self.duration
        return self.settle_time + turning

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
            # unset in the scene: the spin-up takes the run's courant (the schema's word)
            spin_up_courant=float(s.get("spin_up_courant", s["courant"])),
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


#: at most this many particle updates planned for one flow run (months of stepping at
#: the rate of benchmarks/results/flow_throughput.md)
MAX_PLANNED_UPDATES = 1e14


def plan_flow(scene: Scene, vessel, settings: SolverSettings, material: Material) -> dict:
    """What a flow run will hold and do, estimated before a particle is seeded; refused
    with the number and what to change when it cannot fit in ``numerics.memory_budget_mb``
    (or the machine's available memory) or would take more than
    :data:`MAX_PLANNED_UPDATES` particle updates.

    The particles are bounded by the vessel's volume at ``particles_per_cell`` a cell
    side (the bed takes less), the nodes by the vessel's box, the steps by the elastic
    CFL limit at rest (the run's dt is at most that).
    """
    d = vessel.ndim
    h = settings.cell
    particles = vessel.volume / h**d * settings.per_cell**d
    lower, upper = (np.asarray(b, float) for b in vessel.bounds)
    nodes = math.prod(float(n) / h + 2 * GRID_PADDING + 1 for n in upper - lower)
    per_particle = Particles(np.zeros((1, d)), 1.0, 1.0).nbytes
    per_node = 8 * (max(1, numba.get_num_threads()) * (d + 1) + 2 * d + 10)
    out_cells = math.prod(float(n) / settings.output_cell + 3 for n in upper - lower)
    averages = 3 * settings.phases * out_cells * (d + 1) * 8
    need = particles * per_particle + nodes * per_node + averages
    limit, what = memory_limit(scene["numerics"]["memory_budget_mb"])
    if need > limit:
        fit = h * (need / limit) ** (1.0 / d)
        raise SceneError(
            [
                f"solver.cell = {h:g} m needs about {particles:.3g} particles and "
                f"{nodes:.3g} nodes, about {need / 2**20:.4g} MiB, above {what}: choose "
                f"solver.cell >= {fit:.3g} m or raise numerics.memory_budget_mb"
            ]
        )
    steps = settings.end_time / (settings.courant * h / material.p_wave_speed)
    if steps * particles > MAX_PLANNED_UPDATES:
        raise SceneError(
            [
                f"solver.cell = {h:g} m asks for about {steps:.3g} steps of {particles:.3g} "
                f"particles ({steps * particles:.3g} updates, at most "
                f"{MAX_PLANNED_UPDATES:.0e}): a larger solver.cell, a larger "
                "solver.stiffness_scaling (a faster dt) or fewer solver.revolutions"
            ]
        )
    return {"particles": particles, "nodes": nodes, "bytes": need, "steps": steps}


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
        self.plan = plan_flow(self.scene, self.vessel, s, self.material)
        _warn_of_dilation(s, self.material)
        self.ndim = self.vessel.ndim
        self._wall = (self.vessel.kind, self.vessel.params)  # the vessel's exact SDF
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

    @property
    def output(self) -> OutputGrid:
        """The output cells and the motion the averages are taken in (eq. (30) helpers)."""
        return OutputGrid(tuple(self.out_axes), self.omega, self.lab_frame)

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
    def stable_dt(self, courant: float | None = None) -> float:
        """dt = courant * cell / (c_p + |v|max) (DESIGN §4); ``courant`` defaults to
        :meth:`courant_now`."""
        courant = self.courant_now() if courant is None else courant
        return courant * self.grid.h / (self.material.p_wave_speed + self.vmax)

    def courant_now(self) -> float:
        """``solver.spin_up_courant`` before the end of a spin-up revolution
        (:meth:`spin_up_end`), else ``solver.courant``."""
        s = self.settings
        return s.spin_up_courant if self.t < self.spin_up_end() - 1e-12 else s.courant

    def spin_up_end(self) -> float:
        """The end of the spin-up from rest: of revolution 1 when that revolution is
        neither the flow kept nor the one compared with it (it feeds only the first row
        of the eq. (30) history), else the start of the run (no spin-up)."""
        if not math.isfinite(self.period) or self._block(1) < 2:
            return 0.0
        return self.settings.settle_time + self.period

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
        return rotation(-theta, self.ndim) @ (self.gravity_direction * g), self.omega, 0.0

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
            *self._wall, p.x, p.v, WALL_SKIN * g.h, self.starts,
            g.scratch, g.node_sdf.reshape(-1), g.origin, g.h, g.shape_array,
        )  # fmt: skip
        self.t += dt
        self.steps += 1
        self.particle_updates += p.count
        if self.steps % SPEED_CHECK_EVERY == 0:
            self._check_state()

    def _check_state(self) -> None:
        p = self.particles
        worst = mpm.fastest_particle(p.v, self.starts, self.grid.scratch)
        vmax = 0.0
        if worst >= 0:
            # the speed as the per-particle einsum gives it (dt depends on its bits)
            row = p.v[worst : worst + 1]
            vmax = float(np.sqrt(np.einsum("ij,ij->i", row, row))[0])
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
        return self.settings.end_time

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
            if turning < 1 or self._thinned(turning):
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
            x, vel = vessel_to_lab(p.x, p.v, theta, self.omega)
            target.add(0, np.ascontiguousarray(x), np.ascontiguousarray(vel), p.vol0)
        else:
            target.add(target.bin_of(phase), p.x, p.v, p.vol0)

    def _thinned(self, revolution: int) -> bool:
        """Whether this sample of ``revolution`` is skipped: the spin-up from rest
        (:meth:`spin_up_end`) feeds only the history's first row of eq. (30), so it takes
        every ``SPIN_UP_THINNING``-th sample."""
        if revolution != 1 or self.spin_up_end() <= 0.0:
            return False
        return (self.steps // self.sample_every) % SPIN_UP_THINNING != 0

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
                f"checkpoint {path} belongs to another scene; remove it, pass resume=False, "
                "or give --no-resume on the shell"
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
        dt = self.stable_dt(s.courant)  # the kept revolutions' step, spin-up or not
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
        stops = StopRules(max_steps, wall_time)
        saves = CheckpointSchedule(self.settings.checkpoint_every, start=stops.started)
        started = stops.started
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
                if checkpoint is not None and saves.due(now):
                    self.save_checkpoint(checkpoint)
                reason = stops.reason(self.steps)
                if reason is not None:
                    stopped = reason
                    break
        finally:
            self.wall_seconds += time.perf_counter() - started
            numba.set_num_threads(threads_before)
            bar.close()
        if checkpoint is not None:
            self.save_checkpoint(checkpoint)
        return stopped


def _progress_bar(progress, end: float, sim: FlowSimulation):
    bar = progress_bar(progress, end, "s", precision=3, label="s simulated")
    bar.n = round(sim.t, 6)
    return bar


def _update_bar(bar, sim: FlowSimulation, elapsed: float) -> None:
    bar.n = round(min(sim.t, bar.total), 6)
    rate = sim.particle_updates / max(elapsed + sim.wall_seconds, 1e-9)
    bar.set_postfix_str(f"rev {sim.revolution():.2f}, {rate / 1e6:.2f} M particle-steps/s")


# ----------------------------------------------------------------------------- public


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
