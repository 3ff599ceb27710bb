"""Analytic flow datasets for tests and teaching.

Each function returns a schema-valid flow dataset (``flow/1``) built with
`blendxr.schema.flow_dataset`: velocities sampled at cell centres, a vessel mask, the
material region (``fill``) and one revolution of ``rev_phase`` bins. Their exact properties
(constant, rigid rotation, divergence-free, time-reversing) make them reference cases for
the advection-diffusion stepper: a blob carried by `swirl` must come back after each
revolution, a solid-body rotation must keep its shape, a moving bed in a closed vessel
must keep its species mass.

The attribute ``analytic`` holds the flow's name and parameters as JSON text, so a dataset
can be rebuilt from its own file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence

import numpy as np
import xarray as xr
from scipy.optimize import brentq

from ..schema import flow_dataset

__all__ = ["solid_body_rotation", "swirl", "uniform"]

_FRAMES = ("vessel", "lab")


# --------------------------------------------------------------------------------------
# Argument checks and grids
# --------------------------------------------------------------------------------------


def _positive_int(name: str, value, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


def _positive(name: str, value, *, allow_zero: bool = False) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(number) or number < 0 or (number == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return number


def _frame(frame: str) -> str:
    if frame not in _FRAMES:
        raise ValueError(f"frame must be one of {', '.join(_FRAMES)}, got {frame!r}")
    return frame


def _cells_per_axis(cells, ndim: int, minimum: int = 2) -> tuple[int, ...]:
    if isinstance(cells, (int, np.integer)) and not isinstance(cells, bool):
        cells = (cells,) * ndim
    if not isinstance(cells, Sequence) or len(cells) != ndim:
        raise ValueError(f"cells must be an integer or {ndim} integers, got {cells!r}")
    return tuple(_positive_int("cells", n, minimum) for n in cells)


def _extent_per_axis(extent, ndim: int) -> tuple[tuple[float, float], ...]:
    if isinstance(extent, (int, float, np.number)):
        length = _positive("extent", extent)
        return ((0.0, length),) * ndim
    if not isinstance(extent, Sequence) or len(extent) != ndim:
        raise ValueError(f"extent must be a length or {ndim} (lo, hi) pairs, got {extent!r}")
    pairs = []
    for pair in extent:
        if not isinstance(pair, Sequence) or len(pair) != 2:
            raise ValueError(f"extent must be a length or {ndim} (lo, hi) pairs, got {extent!r}")
        lo, hi = float(pair[0]), float(pair[1])
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(f"each extent pair needs finite lo < hi, got {pair!r}")
        pairs.append((lo, hi))
    return tuple(pairs)


def _centres(lo: float, hi: float, n: int) -> np.ndarray:
    return lo + (np.arange(n) + 0.5) * ((hi - lo) / n)


def _phases(n_phases: int) -> np.ndarray:
    return np.arange(n_phases) / n_phases


def _build(name: str, params: dict, axes: dict, velocity, fill, vessel, *, frame, rpm, gravity):
    """Hand the arrays to flow_dataset with the attributes every analytic flow carries."""
    # Name and every parameter, so that the dataset can be rebuilt from its own file.
    recipe = {"flow": name, **params, "frame": frame, "gravity": float(gravity)}
    zkw = {}
    if "z" in axes:
        zkw = {"z": axes["z"], "vz": velocity[2]}
    return flow_dataset(
        axes["x"],
        axes["y"],
        _phases(params["n_phases"]),
        velocity[0],
        velocity[1],
        fill,
        vessel,
        frame=frame,
        rpm=rpm,
        gravity=gravity,
        scene=None,
        title=f"blendxr analytic flow: {name}",
        attrs={"analytic": json.dumps(recipe)},
        **zkw,
    )


# --------------------------------------------------------------------------------------
# Uniform flow
# --------------------------------------------------------------------------------------


def uniform(
    velocity: Sequence[float] = (1.0, 0.0),
    *,
    cells=32,
    extent=1.0,
    n_phases: int = 1,
    rpm: float = 60.0,
    frame: str = "vessel",
    gravity: float = 9.81,
) -> xr.Dataset:
    """A constant velocity in a box vessel full of material.

    Parameters
    ----------
    velocity : sequence of 2 or 3 floats
        ``(u, v)`` for a 2-D dataset, ``(u, v, w)`` for 3-D, in m/s.
    cells : int or sequence of int
        Cells per axis (at least 2).
    extent : float or sequence of (lo, hi)
        Domain: ``[0, extent]`` on every axis, or one ``(lo, hi)`` pair per axis, in m.
        The vessel fills the whole domain.
    n_phases : int
        Number of (identical) phases stored.
    rpm : float
        Rotation speed stored with the flow (>= 0); it sets the period ``60 / rpm`` s.
    frame : {"vessel", "lab"}
        Frame attribute of the dataset.
    gravity : float
        Gravity attribute in m/s².

    Returns
    -------
    xarray.Dataset
        A ``flow/1`` dataset, steady, with ``fill = 1`` and ``vessel = 1`` everywhere.
    """
    try:
        velocity = tuple(float(v) for v in velocity)
    except (TypeError, ValueError):
        raise ValueError(f"velocity must be 2 or 3 numbers, got {velocity!r}") from None
    ndim = len(velocity)
    if ndim not in (2, 3) or not all(math.isfinite(v) for v in velocity):
        raise ValueError(f"velocity must be 2 or 3 finite numbers, got {velocity!r}")
    counts = _cells_per_axis(cells, ndim)
    bounds = _extent_per_axis(extent, ndim)
    n_phases = _positive_int("n_phases", n_phases)
    rpm = _positive("rpm", rpm, allow_zero=True)
    names = ("x", "y", "z")[:ndim]
    axes = {k: _centres(lo, hi, n) for k, (lo, hi), n in zip(names, bounds, counts, strict=True)}
    ones = np.ones(counts)
    params = {
        "velocity": list(velocity),
        "cells": list(counts),
        "extent": [list(b) for b in bounds],
        "n_phases": n_phases,
        "rpm": rpm,
    }
    return _build(
        "uniform",
        params,
        axes,
        [v * ones for v in velocity],
        ones,
        np.ones(counts, dtype=np.int8),
        frame=_frame(frame),
        rpm=rpm,
        gravity=gravity,
    )


# --------------------------------------------------------------------------------------
# Solid-body rotation
# --------------------------------------------------------------------------------------

# Below this size of a normal component the half-plane cut of a cell is taken as parallel
# to the other axis; the closed form divides by both components and loses digits there.
_AXIS_ALIGNED = 1.5e-8


def _ramp2(t: np.ndarray) -> np.ndarray:
    return 0.5 * np.square(np.maximum(t, 0.0))


def _slab(lo: np.ndarray, hi: np.ndarray, b: float, s: float) -> np.ndarray:
    """Length of [lo, hi] where b * t < s (b != 0)."""
    cut = s / b
    inside = (cut - lo) if b > 0 else (hi - cut)
    return np.clip(inside, 0.0, hi - lo)


def _below_fraction(xc, yc, h: float, normal: tuple[float, float], s: float) -> np.ndarray:
    """Exact area fraction of the square cells (centres xc, yc, side h) with n·p < s.

    Uses the closed form of the double integral of the step function: with
    G(t) = max(t, 0)²/2, area = [G(s-n·c11) - G(s-n·c01) - G(s-n·c10) + G(s-n·c00)] / (a b).
    """
    a, b = normal
    x0, x1 = xc - h / 2, xc + h / 2
    y0, y1 = yc - h / 2, yc + h / 2
    if abs(a) < _AXIS_ALIGNED:
        fraction = _slab(y0, y1, b, s) / h
    elif abs(b) < _AXIS_ALIGNED:
        fraction = _slab(x0, x1, a, s) / h
    else:
        area = (
            _ramp2(s - a * x1 - b * y1)
            - _ramp2(s - a * x0 - b * y1)
            - _ramp2(s - a * x1 - b * y0)
            + _ramp2(s - a * x0 - b * y0)
        ) / (a * b)
        fraction = area / (h * h)
    # Round-off may step just outside [0, 1]; fill must not.
    return np.clip(fraction, 0.0, 1.0)


def _bed_fraction(xc, yc, inside, h: float, angle: float, fraction: float) -> np.ndarray:
    """Fill of the cells of a circular cross-section holding a flat-topped bed.

    At angle 0 the bed lies at the bottom (below a horizontal chord); it is turned by
    `angle` counter-clockwise. The chord position is solved for so that the bed takes
    exactly `fraction` of the discrete cross-section, which makes the stored fill conserve
    material to round-off at every phase.
    """
    normal = (-math.sin(angle), math.cos(angle))
    xs, ys = xc[inside], yc[inside]
    target = fraction * xs.size
    reach = float(np.max(np.abs(xs)) + np.max(np.abs(ys)) + h)

    def excess(s: float) -> float:
        return float(_below_fraction(xs, ys, h, normal, s).sum()) - target

    # The bed area is a continuous, increasing, piecewise-quadratic function of the chord
    # position: Brent's method finds it to round-off in a few dozen evaluations.
    chord = brentq(excess, -reach, reach, xtol=1e-15 * reach, rtol=4 * np.finfo(float).eps)
    fill = np.zeros(xc.shape)
    fill[inside] = _below_fraction(xs, ys, h, normal, chord)
    return fill


def solid_body_rotation(
    *,
    ndim: int = 3,
    radius: float = 0.1,
    length: float | None = None,
    cells: int = 32,
    rpm: float = 10.0,
    fill_fraction: float = 1.0,
    n_phases: int | None = None,
    frame: str = "lab",
    gravity: float = 9.81,
    margin: int = 2,
) -> xr.Dataset:
    """Rigid rotation about the z axis in a circular (2-D) or cylindrical (3-D) vessel.

    The velocity is ``ω × r`` with ``ω = 2π rpm / 60`` about +z (counter-clockwise seen from
    +z), i.e. ``(vx, vy) = ω (-y, x)``, in every cell holding material and zero elsewhere;
    ``vz = 0`` in 3-D.

    With ``fill_fraction = 1`` the vessel is full and the flow is steady. With a smaller
    fraction the material is a circular segment: at phase 0 the bed lies at the bottom under
    a horizontal free surface and takes `fill_fraction` of the vessel by volume; it turns
    rigidly with the velocity, so at ``rev_phase = p`` it is the phase-0 bed rotated by
    ``2π p``. The chord is placed per phase so that the fill sums to exactly
    ``fill_fraction`` of the discrete vessel: a closed vessel with a moving material region
    whose material volume is constant, the case used to test conservation.

    Parameters
    ----------
    ndim : {2, 3}
        2: circle in (x, y), no z. 3: cylinder along z with flat end walls.
    radius : float
        Vessel radius in m.
    length : float, optional
        Cylinder length in m (3-D only); default ``2 * radius``.
    cells : int
        Cells across the vessel diameter (at least 4); the spacing is ``2 radius / cells``
        on every axis.
    rpm : float
        Rotation speed (> 0).
    fill_fraction : float
        Fraction of the vessel volume holding material, in (0, 1].
    n_phases : int, optional
        Phases stored; default 1 for a full vessel and 36 for a partial one, which needs at
        least 2 because its material region moves.
    frame : {"lab", "vessel"}
        Frame attribute. ``ω × r`` is the lab-frame velocity of material turning with the
        vessel; a circular wall is the same in both frames, so either label is consistent.
    gravity : float
        Gravity attribute in m/s².
    margin : int
        Cells outside the vessel on every side of the grid (at least 1).

    Returns
    -------
    xarray.Dataset
        A ``flow/1`` dataset centred on the origin.
    """
    if ndim not in (2, 3):
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    radius = _positive("radius", radius)
    cells = _positive_int("cells", cells, 4)
    margin = _positive_int("margin", margin, 1)
    rpm = _positive("rpm", rpm)
    fill_fraction = float(fill_fraction)
    if not 0.0 < fill_fraction <= 1.0:
        raise ValueError(f"fill_fraction must be in (0, 1], got {fill_fraction!r}")
    partial = fill_fraction < 1.0
    if n_phases is None:
        n_phases = 36 if partial else 1
    n_phases = _positive_int("n_phases", n_phases)
    if partial and n_phases < 2:
        raise ValueError(
            "a partly filled vessel (fill_fraction < 1) has a moving bed: n_phases must be >= 2"
        )
    if ndim == 2 and length is not None:
        raise ValueError("length is the cylinder length of a 3-D vessel; a 2-D vessel has none")
    length = 2.0 * radius if length is None else _positive("length", length)
    frame = _frame(frame)

    h = 2.0 * radius / cells
    n_xy = cells + 2 * margin
    centres_xy = _centres(-n_xy * h / 2, n_xy * h / 2, n_xy)
    axes = {"x": centres_xy, "y": centres_xy.copy()}
    xc, yc = np.meshgrid(centres_xy, centres_xy, indexing="ij")
    section = np.hypot(xc, yc) < radius
    if ndim == 3:
        n_z = math.ceil(length / h - 1e-9) + 2 * margin
        axes["z"] = _centres(-n_z * h / 2, n_z * h / 2, n_z)
        along = np.abs(axes["z"]) < length / 2
        vessel = section[:, :, None] & along[None, None, :]
    else:
        vessel = section

    phases = _phases(n_phases)
    if partial:
        fill_xy = np.stack(
            [_bed_fraction(xc, yc, section, h, 2 * math.pi * p, fill_fraction) for p in phases]
        )
    else:
        fill_xy = np.broadcast_to(section.astype(np.float64), (n_phases,) + section.shape)
    fill = fill_xy[..., None] * vessel[None] if ndim == 3 else fill_xy.copy()

    omega = 2.0 * math.pi * rpm / 60.0
    material = fill > 0
    grid_x = xc[..., None] if ndim == 3 else xc
    grid_y = yc[..., None] if ndim == 3 else yc
    velocity = [
        np.where(material, -omega * grid_y, 0.0),
        np.where(material, omega * grid_x, 0.0),
    ]
    if ndim == 3:
        velocity.append(np.zeros(fill.shape))
    params = {
        "ndim": ndim,
        "radius": radius,
        "length": length if ndim == 3 else None,
        "cells": cells,
        "rpm": rpm,
        "fill_fraction": fill_fraction,
        "n_phases": n_phases,
        "margin": margin,
    }
    return _build(
        "solid_body_rotation",
        params,
        axes,
        velocity,
        fill,
        vessel.astype(np.int8),
        frame=frame,
        rpm=rpm,
        gravity=gravity,
    )


# --------------------------------------------------------------------------------------
# LeVeque's time-reversing swirl
# --------------------------------------------------------------------------------------


def swirl(
    *,
    ndim: int = 2,
    cells=32,
    n_phases: int = 72,
    rpm: float = 60.0,
    size: float = 1.0,
    amplitude: float = 1.0,
    frame: str = "vessel",
    gravity: float = 9.81,
) -> xr.Dataset:
    """LeVeque's deforming, time-reversing flow in a box vessel full of material.

    With ``x̂ = x / size`` (likewise ŷ, ẑ) and ``g = amplitude (size / T) cos(2π rev_phase)``,
    ``T = 60 / rpm``:

    - 2-D: ``u = sin²(πx̂) sin(2πŷ) g``, ``v = -sin²(πŷ) sin(2πx̂) g``;
    - 3-D: ``u = 2 sin²(πx̂) sin(2πŷ) sin(2πẑ) g``,
      ``v = -sin(2πx̂) sin²(πŷ) sin(2πẑ) g``, ``w = -sin(2πx̂) sin(2πŷ) sin²(πẑ) g``.

    The spatial pattern is divergence-free and its normal component vanishes on the walls.
    Because the flow is a fixed pattern times ``g(t)`` and ``g`` integrates to zero over a
    period (exactly so for the piecewise-linear interpolant through equally spaced phases,
    as ``Σ cos(2πk/n) = 0``), every particle returns to its start after each revolution.

    Parameters
    ----------
    ndim : {2, 3}
        Dimension; a 2-D dataset has no z.
    cells : int or sequence of int
        Cells per axis (at least 2).
    n_phases : int
        Phases per revolution (at least 2, so that the flow reverses).
    rpm : float
        Revolutions per minute (> 0); the period is ``60 / rpm`` s.
    size : float
        Edge of the box ``[0, size]^ndim`` in m.
    amplitude : float
        Scale of the velocity (> 0); 1 is LeVeque's test.
    frame : {"vessel", "lab"}
        Frame attribute of the dataset.
    gravity : float
        Gravity attribute in m/s².

    Returns
    -------
    xarray.Dataset
        A ``flow/1`` dataset, periodic in ``rev_phase``.
    """
    if ndim not in (2, 3):
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    counts = _cells_per_axis(cells, ndim)
    n_phases = _positive_int("n_phases", n_phases, 2)
    rpm = _positive("rpm", rpm)
    size = _positive("size", size)
    amplitude = _positive("amplitude", amplitude)
    names = ("x", "y", "z")[:ndim]
    axes = {k: _centres(0.0, size, n) for k, n in zip(names, counts, strict=True)}
    hats = np.meshgrid(*(axes[k] / size for k in names), indexing="ij")
    sin2 = [np.sin(math.pi * q) ** 2 for q in hats]
    sin_2 = [np.sin(2 * math.pi * q) for q in hats]
    if ndim == 2:
        pattern = [sin2[0] * sin_2[1], -sin2[1] * sin_2[0]]
    else:
        pattern = [
            2 * sin2[0] * sin_2[1] * sin_2[2],
            -sin_2[0] * sin2[1] * sin_2[2],
            -sin_2[0] * sin_2[1] * sin2[2],
        ]
    period = 60.0 / rpm
    g = amplitude * (size / period) * np.cos(2 * math.pi * _phases(n_phases))
    g = g.reshape((n_phases,) + (1,) * ndim)
    velocity = [g * p[None] for p in pattern]
    params = {
        "ndim": ndim,
        "cells": list(counts),
        "n_phases": n_phases,
        "rpm": rpm,
        "size": size,
        "amplitude": amplitude,
    }
    return _build(
        "swirl",
        params,
        axes,
        velocity,
        np.ones(counts),
        np.ones(counts, dtype=np.int8),
        frame=_frame(frame),
        rpm=rpm,
        gravity=gravity,
    )
