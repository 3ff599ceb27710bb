"""The flow dataset a run writes: its phase averages labelled, with what the run did
and cost (periodicity, packing, projection, clipped fill) as attributes."""

from __future__ import annotations

import math
import warnings
from types import SimpleNamespace
from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from .. import __version__
from ..schema import flow_dataset
from .averaging import (
    PhaseAverager,
    fields_change,
    fill_histogram,
    lab_velocities,
    periodicity,
)
from .state import _MIRROR, Particles

if TYPE_CHECKING:
    from .solver import FlowSimulation


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


def revolution_change(
    sim: FlowSimulation, before: PhaseAverager, after: PhaseAverager, *, vessel_frame=False
) -> dict:
    """Eq. (30) (:func:`periodicity`) between two recorded revolutions of a run, as
    :func:`fields_change` of their phase-binned fields."""
    return fields_change(
        sim.output, before.fields()[:2], after.fields()[:2], vessel_frame=vessel_frame
    )


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
        vel_a, vel_b = (lab_velocities(sim.output, v) for v in (vel_a, vel_b))
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
        "spin_up_courant": s.spin_up_courant,
        "spin_up_end_s": sim.spin_up_end(),
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
