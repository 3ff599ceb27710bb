"""Flows from another code's particles: DEM or MPM positions and velocities over a
revolution, phase-averaged onto a scene's cells as the built-in solver does.

The particles of each sample time are spread over the output cells by the solver's own
quadratic B-splines (:class:`blendxr.flow.averaging.PhaseAverager`), each into the phase bin
of its time, in the frame the solver stores for the vessel (the vessel frame; a drum's
flow, steady in the lab frame, as one lab-frame phase).
"""

from __future__ import annotations

import math
import os

import numpy as np
import xarray as xr

from ..scene import load_scene
from ..schema import flow_dataset
from ..vessels import Drum, vessel_from_scene
from .averaging import lab_to_vessel, vessel_to_lab

__all__ = ["from_particles"]

#: the columns of a particle table (z, vz only in 3-D; volume optional)
COLUMNS = ("t", "x", "y", "z", "vx", "vy", "vz", "volume")


def _from_table(table, ndim: int):
    """(times, positions, velocities, volumes) from a DataFrame or CSV in long form."""
    import pandas as pd

    if isinstance(table, str | os.PathLike):
        table = pd.read_csv(table)
    names = [c for c in COLUMNS if c in table.columns]
    needed = ["t", "x", "y", "vx", "vy"] + (["z", "vz"] if ndim == 3 else [])
    missing = [c for c in needed if c not in names]
    if missing:
        raise ValueError(f"particle table: columns {missing} missing; it needs {needed}")
    times, positions, velocities, volumes = [], [], [], []
    for t, rows in table.groupby("t", sort=True):
        times.append(float(t))
        positions.append(rows[["x", "y", "z"][:ndim]].to_numpy(float))
        velocities.append(rows[["vx", "vy", "vz"][:ndim]].to_numpy(float))
        volumes.append(rows["volume"].to_numpy(float) if "volume" in rows else None)
    return times, positions, velocities, volumes


def _default_volume(scene, ndim: int) -> float:
    """A grain's share of the bed: its volume over the packing (area per unit width in
    2-D), from the scene's ``material.particle_diameter`` and ``packing_fraction``."""
    d = scene["material"]["particle_diameter"]
    packing = scene["material"]["packing_fraction"]
    grain = math.pi * d**3 / 6.0 if ndim == 3 else math.pi * d**2 / 4.0
    return grain / packing


def from_particles(
    positions,
    velocities=None,
    times=None,
    scene="tote-small",
    *,
    volumes=None,
    frame: str = "lab",
    t0: float = 0.0,
) -> xr.Dataset:
    """Bin particle data from another code into a flow dataset (``flow/1``).

    Parameters
    ----------
    positions : array (samples, particles, d), list of (particles, d) arrays, DataFrame or path
        Particle positions in metres at each sample time, in the scene's axes (y up, the
        vessel turning about z through the origin). A DataFrame or CSV file in long form
        (one row per particle and time: columns ``t, x, y[, z], vx, vy[, vz]``, optional
        ``volume``) gives times, positions, velocities and volumes together.
    velocities : like positions
        Velocities in m/s at the same samples (not with a table).
    times : array (samples,)
        Sample times in seconds (not with a table); they should cover at least one
        revolution after ``t0``, so that every phase bin receives samples.
    scene : Scene, str or mapping
        The vessel, speed, cells and phase bins of the flow to make, resolved as the
        solver resolves them (``flow.cell``, ``flow.phases``; a drum: one phase).
    volumes : float or array, optional
        Each particle's share of the bed's volume at its seeded packing (m^3; m^2 in
        2-D). Default: the grain volume of ``material.particle_diameter`` over
        ``material.packing_fraction``.
    frame : "lab" or "vessel"
        The frame the data are in. Lab-frame data are turned into the vessel frame
        (a drum's flow is stored in the lab frame, as the solver stores it).
    t0 : float
        The time at which the vessel stands at rev_phase 0 (the end of the solver's
        settling).

    Returns
    -------
    xarray.Dataset
        The flow, phase-averaged like the built-in solver's (``particles_binned``,
        ``samples_per_phase`` and ``binned_from`` attributes say from what).

    Raises
    ------
    ValueError
        Data of the wrong shape, NaN, a frame other than "lab" or "vessel", or a phase
        bin that received no sample (give more samples or fewer ``flow.phases``).
    """
    from .averaging import PhaseAverager, output_grid
    from .solver import SolverSettings

    scene = load_scene(scene)
    vessel = vessel_from_scene(scene)
    ndim = vessel.ndim
    if frame not in ("lab", "vessel"):
        raise ValueError(f"frame {frame!r}: 'lab' or 'vessel'")
    if velocities is None and times is None:
        times, positions, velocities, table_volumes = _from_table(positions, ndim)
        if volumes is None and all(v is not None for v in table_volumes):
            volumes = table_volumes
    elif velocities is None or times is None:
        raise ValueError("give positions, velocities and times, or one particle table")
    times = np.asarray(times, float).reshape(-1)
    if len(positions) != len(times) or len(velocities) != len(times):
        raise ValueError(
            f"{len(times)} times but {len(positions)} position and {len(velocities)} "
            "velocity samples"
        )
    # the output cells, phase bins and speed as the solver resolves them from the scene
    settings = SolverSettings.from_scene(scene, vessel)
    rpm, phases, cell = settings.rpm, settings.phases, settings.output_cell
    if rpm <= 0:
        raise ValueError("operation.rpm must be > 0 to bin particles by rev_phase")
    omega, period = 2.0 * math.pi * rpm / 60.0, 60.0 / rpm
    lab_stored = isinstance(vessel, Drum)
    origin, shape, axes, inside = output_grid(vessel, cell)
    averager = PhaseAverager(origin, shape, cell, phases, inside=inside)
    grain = _default_volume(scene, ndim)
    count = 0
    for j, t in enumerate(times):
        x = np.ascontiguousarray(np.asarray(positions[j], float).reshape(-1, ndim))
        v = np.ascontiguousarray(np.asarray(velocities[j], float).reshape(-1, ndim))
        if x.shape != v.shape or not (np.isfinite(x).all() and np.isfinite(v).all()):
            raise ValueError(f"sample {j} (t = {t:g} s): positions and velocities must be "
                             "finite and of one shape")  # fmt: skip
        vol = _sample_volumes(volumes, j, len(x), grain)
        x, v = _to_stored_frame(x, v, omega * (t - t0), omega, frame, lab_stored)
        phase = ((t - t0) / period) % 1.0
        averager.add(averager.bin_of(phase), x, v, vol)
        count = max(count, len(x))
    try:
        fill, vel, _ = averager.fields()
    except RuntimeError as err:
        raise ValueError(f"{err} (or give samples over a whole revolution)") from None
    return flow_dataset(
        axes[0],
        axes[1],
        np.arange(phases) / phases,
        vel[..., 0],
        vel[..., 1],
        fill,
        inside,
        z=axes[2] if ndim == 3 else None,
        vz=vel[..., 2] if ndim == 3 else None,
        frame="lab" if lab_stored else "vessel",
        rpm=rpm,
        gravity=settings.gravity,
        scene=scene,
        title=f"blendxr flow binned from particles: {scene.name}",
        attrs={
            "binned_from": f"particle data in the {frame} frame, {len(times)} samples",
            "particles_binned": count,
            "samples_per_phase": averager.samples.tolist(),
        },
    )


def _sample_volumes(volumes, j: int, n: int, grain: float) -> np.ndarray:
    if volumes is None:
        return np.full(n, grain)
    if np.ndim(volumes) == 0:
        return np.full(n, float(volumes))
    values = volumes[j] if isinstance(volumes, list) else np.asarray(volumes, float)
    values = np.asarray(values, float)
    if values.ndim == 2:  # one row a sample
        values = values[j]
    if values.shape != (n,) or not np.all(values > 0):
        raise ValueError(f"volumes of sample {j}: {n} positive values needed")
    return np.ascontiguousarray(values)


def _to_stored_frame(x, v, theta: float, omega: float, frame: str, lab_stored: bool):
    """Positions and velocities in the frame the flow is stored in (the vessel frame; a
    drum's flow in the lab frame)."""
    if frame == "lab" and not lab_stored:
        x, v = lab_to_vessel(x, v, theta, omega)
    elif frame == "vessel" and lab_stored:
        x, v = vessel_to_lab(x, v, theta, omega)
    return np.ascontiguousarray(x), np.ascontiguousarray(v)
