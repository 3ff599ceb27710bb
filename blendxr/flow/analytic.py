"""Analytic flow datasets for tests and teaching.

Each function returns a schema-valid flow dataset (``flow/1``) built with
`blendxr.schema.flow_dataset`: velocities sampled at cell centres, a vessel mask, the
material region (``fill``) and one revolution of ``rev_phase`` bins. Their exact properties
(constant, rigid rotation, divergence-free, time-reversing) make them reference cases for
the advection-diffusion stepper: a blob carried by `swirl` must come back after each
revolution, a solid-body rotation must keep its shape, a moving bed in a closed vessel
must keep its species mass. `rolling_drum` is a kinematic model of a real case, the
paper's calibration drum: a rigid bed under a flowing layer whose flux tends to the
q(s) = ω (L² - s²)/2 of a thin layer.

The attribute ``analytic`` holds the flow's name and parameters as JSON text, so a dataset
can be rebuilt from its own file.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.optimize import brentq

from ..schema import flow_dataset

__all__ = ["from_particles", "rolling_drum", "solid_body_rotation", "swirl", "uniform"]

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


# --------------------------------------------------------------------------------------
# Rolling drum
# --------------------------------------------------------------------------------------

# Sub-cells per axis that resolve the curved wall in the cells it cuts. The wall is
# taken as straight within a sub-cell, so the bed's area comes out within about a
# thousandth of a cell.
_WALL_SUBCELLS = 16


def _number(name: str, value) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(number):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    return number


@dataclass(frozen=True)
class _DrumSection:
    """Cross-section of a drum rolling at steady state: geometry and stream function.

    Chord coordinates of a point p: ``s = t·p`` along the free surface, with
    ``t = (cos β, sin β)`` pointing uphill, and ``n = m·p - offset`` across it, with
    ``m = (-sin β, cos β)`` pointing out of the bed. The surface is ``n = 0``, the bed
    ``n < 0``, and ``s = 0`` at the chord's midpoint (the foot of the perpendicular
    from the axis).
    """

    radius: float
    omega: float
    angle: float  # dynamic angle of repose β, radians
    offset: float  # signed distance of the chord from the axis along m
    half_chord: float
    layer: float  # flowing-layer thickness δ0 at the chord's midpoint

    @property
    def tangent(self) -> tuple[float, float]:
        return (math.cos(self.angle), math.sin(self.angle))

    @property
    def normal(self) -> tuple[float, float]:
        return (-math.sin(self.angle), math.cos(self.angle))

    @property
    def surface_stream_function(self) -> float:
        """ψ on the wall and on the free surface: the bed's bounding streamline."""
        return -0.5 * self.omega * self.radius**2

    def chord_coordinates(self, x, y):
        """``(s, n)`` of the points ``(x, y)``."""
        (tx, ty), (mx, my) = self.tangent, self.normal
        return tx * x + ty * y, mx * x + my * y - self.offset

    def layer_thickness(self, s):
        """δ(s) = δ0 sqrt(1 - s²/L²); zero beyond the chord's ends."""
        ratio = np.clip(1.0 - np.square(np.asarray(s, float) / self.half_chord), 0.0, None)
        return self.layer * np.sqrt(ratio)

    def thin_layer_flux(self, s):
        """q(s) = ω (L² - s²) / 2, the flux of a vanishingly thin layer (DESIGN §7)."""
        s = np.asarray(s, float)
        return 0.5 * self.omega * np.clip(self.half_chord**2 - s * s, 0.0, None)

    def stream_function(self, x, y):
        """ψ at points (x, y); ψ = ψ_s above the free surface.

        Rigid rotation ``ψ_bed = -ω r²/2`` below the flowing layer and
        ``ψ_s + (ψ_bed - ψ_s) f(η)`` in it, ``f(η) = 2η - η²``, ``η = -n/δ(s)``.
        """
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        s, n = self.chord_coordinates(x, y)
        delta = self.layer_thickness(s)
        # Where there is no layer (beyond the chord's ends) a point is bed below the
        # surface line and free space above it.
        eta = np.where(n < 0, np.inf, 0.0)
        np.divide(-n, delta, out=eta, where=delta > 0)
        eta = np.clip(eta, 0.0, 1.0)
        above_bed = 0.5 * self.omega * (self.radius**2 - x * x - y * y)  # ψ_bed - ψ_s
        return self.surface_stream_function + above_bed * eta * (2.0 - eta)

    def velocity(self, x, y):
        """Exact velocity ``(∂ψ/∂y, -∂ψ/∂x)`` at points of the bed (n <= 0).

        The reference the gridded field of `rolling_drum` is checked against. Points above
        the free surface are taken onto it along its normal and get the surface velocity.
        """
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        omega, big_l, d = self.omega, self.half_chord, self.offset
        s, n = self.chord_coordinates(x, y)
        on_surface = n >= 0

        # On the surface f = 0 and f' = 2, so u_s = -2 (ψ_bed - ψ_s) / δ; written with
        # δ's definition it stays finite up to the chord's ends, where it vanishes.
        s_top = np.clip(s, -big_l, big_l)
        along_top = -omega * big_l * np.sqrt(np.clip(big_l**2 - s_top**2, 0.0, None))
        along_top /= self.layer

        n = np.minimum(n, 0.0)
        delta = self.layer_thickness(s)
        in_layer = (delta > 0) & (-n < delta)
        safe_delta = np.where(in_layer, delta, 1.0)
        # η = 1 below the layer makes f = 1, f' = 0 there: the rigid rotation of the bed.
        eta = np.where(in_layer, -n / safe_delta, 1.0)
        f, df = eta * (2.0 - eta), 2.0 - 2.0 * eta
        q = 0.5 * omega * (big_l**2 - s * s - n * n - 2.0 * n * d)  # ψ_bed - ψ_s
        dq_ds, dq_dn = -omega * s, -omega * (n + d)
        deta_dn = -1.0 / safe_delta
        # ∂η/∂s = η s / (L² - s²), since δ'/δ = -s / (L² - s²)
        deta_ds = np.where(in_layer, eta * s / np.where(in_layer, big_l**2 - s * s, 1.0), 0.0)
        along = dq_dn * f + q * df * deta_dn  # u·t = ∂ψ/∂n
        across = -(dq_ds * f + q * df * deta_ds)  # u·m = -∂ψ/∂s

        along = np.where(on_surface, along_top, along)
        across = np.where(on_surface, 0.0, across)
        (tx, ty), (mx, my) = self.tangent, self.normal
        return along * tx + across * mx, along * ty + across * my

    def grid_velocity(self, x: np.ndarray, y: np.ndarray):
        """Velocity on the grid of cell centres ``x``, ``y`` (uniform spacing h), indexed (x, y).

        Central differences of ψ sampled at the cell centres:
        ``u[i, j] = (ψ[i, j+1] - ψ[i, j-1]) / 2h``, ``v[i, j] = -(ψ[i+1, j] - ψ[i-1, j]) / 2h``.
        Their central-difference divergence is ``(ψ[i+1, j+1] - ψ[i+1, j-1] - ψ[i-1, j+1]
        + ψ[i-1, j-1]) / 4h²`` minus the same sum: zero to round-off, whatever ψ's
        smoothness. That is the divergence a finite-volume scheme sees when it takes a face
        velocity as the mean of the two cells' velocities, so a bed carried through this
        field neither gathers nor thins inside. ψ is continued past the bed as
        `stream_function` does (ψ_s above the surface, rigid rotation beyond the wall).
        """
        h = float(x[1] - x[0])
        # one more ring of centres, so that every cell has its four neighbours
        xe = np.concatenate([[x[0] - h], x, [x[-1] + h]])
        ye = np.concatenate([[y[0] - h], y, [y[-1] + h]])
        psi = self.stream_function(*np.meshgrid(xe, ye, indexing="ij"))
        u = (psi[1:-1, 2:] - psi[1:-1, :-2]) / (2.0 * h)
        v = -(psi[2:, 1:-1] - psi[:-2, 1:-1]) / (2.0 * h)
        return u, v

    def segment_area(self) -> float:
        """Exact area of the bed: the circular segment below the chord."""
        radius, d = self.radius, self.offset
        return radius**2 * math.acos(-d / radius) + d * self.half_chord


def _drum_section(radius, rpm, fill_depth, angle_deg, layer_fraction) -> _DrumSection:
    """Check the drum's arguments and derive its cross-section."""
    radius = _positive("radius", radius)
    rpm = _positive("rpm", rpm)
    fill_depth = _number("fill_depth", fill_depth)
    if not 0.0 < fill_depth < 1.0:
        raise ValueError(
            f"fill_depth is the bed depth as a fraction of the diameter, in (0, 1); "
            f"got {fill_depth!r}"
        )
    angle_deg = _number("angle_deg", angle_deg)
    if not 0.0 <= angle_deg < 90.0:
        raise ValueError(f"angle_deg must be in [0, 90), got {angle_deg!r}")
    layer_fraction = _positive("layer_fraction", layer_fraction)
    half_chord = 2.0 * radius * math.sqrt(fill_depth * (1.0 - fill_depth))
    layer = layer_fraction * half_chord
    depth = 2.0 * radius * fill_depth  # bed depth under the chord's midpoint
    if layer >= depth:
        raise ValueError(
            f"layer_fraction = {layer_fraction!r} makes the flowing layer ({layer:.4g} m) as "
            f"deep as the bed under the middle of the surface ({depth:.4g} m); it must be "
            f"thinner: layer_fraction < {depth / half_chord:.4g}"
        )
    return _DrumSection(
        radius=radius,
        omega=2.0 * math.pi * rpm / 60.0,
        angle=math.radians(angle_deg),
        offset=radius * (2.0 * fill_depth - 1.0),
        half_chord=half_chord,
        layer=layer,
    )


def _chord_fraction(xc, yc, h: float, normal: tuple[float, float], offset: float):
    """Exact area fraction of the square cells (centres xc, yc, side h) with m·p < offset.

    Cells the line misses are 0 or 1 exactly; the closed form of `_below_fraction` is
    used only on the cells the line cuts, where it has no digits to lose.
    """
    mx, my = normal
    reach = 0.5 * h * (abs(mx) + abs(my))  # largest |m·(corner - centre)|
    distance = mx * xc + my * yc - offset
    fraction = np.where(distance <= -reach, 1.0, 0.0)
    cut = np.abs(distance) < reach
    fraction[cut] = _below_fraction(xc[cut], yc[cut], h, normal, offset)
    return fraction


def _corner_distances(xc, yc, h: float):
    """Distances from the origin to the nearest and farthest points of square cells."""
    ax, ay = np.abs(xc), np.abs(yc)
    nearest = np.hypot(np.maximum(ax - h / 2, 0.0), np.maximum(ay - h / 2, 0.0))
    return nearest, np.hypot(ax + h / 2, ay + h / 2)


def _disc_fraction(xc, yc, h: float, radius: float):
    """Area fraction of small square cells inside the circle of `radius` about the origin.

    In each cell the circle cuts, the circle is taken as its tangent at the nearest
    point, whose half-plane is integrated exactly: the error is the sliver between arc
    and tangent, about ``h³ / (12 R)`` per cell.
    """
    nearest, farthest = _corner_distances(xc, yc, h)
    fraction = np.where(farthest <= radius, 1.0, 0.0)
    cut = (nearest < radius) & (farthest > radius)
    x, y = xc[cut], yc[cut]
    r = np.hypot(x, y)
    a, b = x / r, y / r
    x0, x1, y0, y1 = x - h / 2, x + h / 2, y - h / 2, y + h / 2
    # the closed form of _below_fraction, one normal per cell
    straight = (np.abs(a) < _AXIS_ALIGNED) | (np.abs(b) < _AXIS_ALIGNED)
    ab = np.where(straight, 1.0, a * b)
    area = (
        _ramp2(radius - a * x1 - b * y1)
        - _ramp2(radius - a * x0 - b * y1)
        - _ramp2(radius - a * x1 - b * y0)
        + _ramp2(radius - a * x0 - b * y0)
    ) / (ab * h * h)
    # a cut parallel to an axis is a slab; its closed form above would divide by ~0
    along_x = np.abs(a) >= np.abs(b)
    centre = np.where(along_x, x, y)
    normal = np.where(along_x, a, b)
    slab = np.clip(0.5 + (radius / np.abs(normal) - np.sign(normal) * centre) / h, 0.0, 1.0)
    fraction[cut] = np.clip(np.where(straight, slab, area), 0.0, 1.0)
    return fraction


def _segment_fraction(xc, yc, h: float, section: _DrumSection, subcells: int = _WALL_SUBCELLS):
    """Area fraction of each cell inside the bed: below the free surface, inside the drum.

    Exact in cells the wall misses. A cell the wall cuts is split into ``subcells²``
    sub-cells, in each of which the surface is integrated exactly and the wall is taken
    as its tangent (`_disc_fraction`); their product is exact in every sub-cell that
    only one of them cuts, which is all but the few at the chord's ends.
    """
    xc, yc = np.asarray(xc, float), np.asarray(yc, float)
    normal, offset, radius = section.normal, section.offset, section.radius
    fill = _chord_fraction(xc, yc, h, normal, offset)
    nearest, farthest = _corner_distances(xc, yc, h)
    fill[nearest >= radius] = 0.0
    wall = (nearest < radius) & (farthest > radius)
    steps = ((np.arange(subcells) + 0.5) / subcells - 0.5) * h
    xs, ys = np.broadcast_arrays(
        xc[wall][:, None, None] + steps[None, :, None],
        yc[wall][:, None, None] + steps[None, None, :],
    )
    hs = h / subcells
    sub = _chord_fraction(xs, ys, hs, normal, offset) * _disc_fraction(xs, ys, hs, radius)
    fill[wall] = sub.mean(axis=(1, 2))
    return fill


def rolling_drum(
    *,
    ndim: int = 2,
    radius: float = 0.075,
    width: float = 0.05,
    cells: int = 64,
    rpm: float = 3.26,
    fill_depth: float = 0.32,
    angle_deg: float = 27.1,
    layer_fraction: float = 0.15,
    n_phases: int = 1,
    frame: str = "lab",
    gravity: float = 9.81,
    margin: int = 2,
) -> xr.Dataset:
    """A drum turning in the rolling regime: a kinematic model of its steady flow.

    The drum (radius R, axis along z through the origin) turns counter-clockwise seen
    from +z at ``ω = 2π rpm / 60``. Its bed is a circular segment under a flat free
    surface inclined at the dynamic angle β (`angle_deg`), rising towards +x, the side
    where the wall drags the bed up. A drum is axisymmetric, so this flow is steady in
    the lab frame: the dataset has ``frame = "lab"`` and its phases are all the same.

    The velocity ``(u, v) = (∂ψ/∂y, -∂ψ/∂x)`` derives from a stream function ψ, so it is
    exactly incompressible. With chord coordinates ``s`` along the surface (from the
    chord's midpoint, uphill positive) and ``n`` normal to it (negative into the bed),
    L the half-chord and ``ψ_s = -ω R²/2``:

    - below the flowing layer the bed turns rigidly: ``ψ_bed = -ω (x² + y²)/2``, i.e.
      ``(u, v) = ω (-y, x)``;
    - the flowing layer has thickness ``δ(s) = δ0 sqrt(1 - s²/L²)``,
      ``δ0 = layer_fraction · L``; in it, with ``η = -n/δ(s)`` in [0, 1],
      ``ψ = ψ_s + (ψ_bed - ψ_s)(2η - η²)``. ψ and the velocity are continuous at the
      layer's bottom (``f'(1) = 0``), and the along-surface velocity is largest at the
      surface, where it points downhill: ``-ω L sqrt(L² - s²) / δ0``;
    - the wall (``ψ_bed = ψ_s``) and the surface (``η = 0``) are both the streamline
      ``ψ = ψ_s``: no material crosses them.

    The flux through the layer at ``s`` is ``ψ_bed - ψ_s`` at the layer's bottom,
    ``ω (L² - s² - δ² + 2 d δ)/2`` (d the chord's signed offset, below), which tends to
    ``q(s) = ω (L² - s²)/2`` as the layer thins (DESIGN §7).

    Conventions:

    - **fill depth**: the bed's depth along the surface normal through the axis, as a
      fraction of the diameter, so the chord lies at the signed distance
      ``d = R (2 fill_depth - 1)`` from the axis (negative: below it), its half-length is
      ``L = 2R sqrt(fill_depth (1 - fill_depth))``, and ``fill_depth = 0.5`` is a
      half-full drum. The bed's area does not depend on β: it is the segment of a
      horizontal bed of depth ``2R fill_depth``, the paper's way of stating the fill.
    - **velocity**: central differences of ψ sampled at the cell centres, 2h apart
      (``u = (ψ[i, j+1] - ψ[i, j-1]) / 2h``, ``v = -(ψ[i+1, j] - ψ[i-1, j]) / 2h``), in
      every cell holding material, zero elsewhere; ψ is ψ_s above the surface and rigid
      rotation beyond the wall. The central-difference divergence of this field is zero
      to round-off, and that is the divergence a finite-volume scheme sees when its face
      velocities are means of cell velocities. The price is an average over 2h: exact
      in the rigid bed (ψ is quadratic there), second-order accurate in the layer, and
      smoothed over a cell at the layer's bottom and at the surface.
    - **fill**: the area fraction of each cell below the surface and inside the drum;
      exact where only the surface cuts the cell, sampled on 16 × 16 sub-cells where
      the wall does, so the bed's area is the segment's to a small fraction of a cell.
      Cells cut by the wall whose centre is outside keep their sliver of material.
    - **vessel**: cells whose centre is inside the drum (and, in 3-D, between the end
      walls); a margin of empty cells surrounds it.

    The model is kinematic: the layer's shape and thickness are given, not solved for.
    It suits fills up to about half. In a fuller drum the chord lies above the axis and,
    near its ends, the layer thinning to nothing must still pass on a flux of order
    ω d δ fed by the bed beneath: its velocity across the surface grows without bound
    there, if slowly (as the inverse square root of the distance to the end).

    Parameters
    ----------
    ndim : {2, 3}
        2: the cross-section in (x, y), no z (plane strain). 3: the section extruded
        along z between flat end walls, ``vz = 0``.
    radius : float
        Drum radius R in m.
    width : float
        Drum length along z in m (3-D); a 2-D dataset records it but does not use it.
    cells : int
        Cells across the drum's diameter (at least 4); the spacing is ``2R / cells`` on
        every axis.
    rpm : float
        Rotation speed (> 0).
    fill_depth : float
        Bed depth as a fraction of the diameter, in (0, 1) (see Conventions).
    angle_deg : float
        Dynamic angle of repose β of the free surface, in [0, 90) degrees.
    layer_fraction : float
        Flowing-layer thickness at the chord's midpoint as a fraction of the half-chord
        L (> 0, and thinner than the bed there).
    n_phases : int
        Number of (identical) phases stored.
    frame : {"lab"}
        Frame attribute; only the lab frame, where the flow is steady, is offered.
    gravity : float
        Gravity attribute in m/s².
    margin : int
        Empty cells outside the vessel on every side of the grid (at least 1).

    Returns
    -------
    xarray.Dataset
        A steady ``flow/1`` dataset centred on the drum's axis.

    Examples
    --------
    The paper's calibration drum (Table 2): 150 mm across, 50 mm wide, a bed 32 % of
    the diameter deep, at 3.26 rpm.

    >>> flow = rolling_drum()  # doctest: +SKIP
    >>> flow = rolling_drum(ndim=3, cells=48)  # doctest: +SKIP
    """
    if ndim not in (2, 3):
        raise ValueError(f"ndim must be 2 or 3, got {ndim!r}")
    section = _drum_section(radius, rpm, fill_depth, angle_deg, layer_fraction)
    radius, rpm = section.radius, float(rpm)
    width = _positive("width", width)
    cells = _positive_int("cells", cells, 4)
    margin = _positive_int("margin", margin, 1)
    n_phases = _positive_int("n_phases", n_phases)
    if frame != "lab":
        raise ValueError(
            f"frame must be 'lab' for a drum, got {frame!r}: its flow is steady only in the "
            "lab frame (in the vessel frame the bed turns backwards through the drum)"
        )
    gravity = _positive("gravity", gravity, allow_zero=True)

    h = 2.0 * radius / cells
    n_xy = cells + 2 * margin
    centres_xy = _centres(-n_xy * h / 2, n_xy * h / 2, n_xy)
    axes = {"x": centres_xy, "y": centres_xy.copy()}
    xc, yc = np.meshgrid(centres_xy, centres_xy, indexing="ij")
    inside = np.hypot(xc, yc) < radius
    fill_xy = _segment_fraction(xc, yc, h, section)
    material = fill_xy > 0
    vx_xy, vy_xy = (np.where(material, v, 0.0) for v in section.grid_velocity(axes["x"], axes["y"]))

    if ndim == 3:
        n_z = math.ceil(width / h - 1e-9) + 2 * margin
        z = _centres(-n_z * h / 2, n_z * h / 2, n_z)
        axes["z"] = z
        # Fraction of each layer of cells between the end walls, so that the material's
        # volume is the segment's area times the width, as in 2-D; exactly 1 inside.
        overlap = np.minimum(z + h / 2, width / 2) - np.maximum(z - h / 2, -width / 2)
        along = np.where(np.abs(z) + h / 2 <= width / 2, 1.0, np.clip(overlap / h, 0.0, 1.0))
        fill = fill_xy[:, :, None] * along[None, None, :]
        vessel = inside[:, :, None] & (np.abs(z) < width / 2)[None, None, :]
        velocity = [
            np.where(fill > 0, vx_xy[:, :, None], 0.0),
            np.where(fill > 0, vy_xy[:, :, None], 0.0),
            np.zeros(fill.shape),
        ]
    else:
        fill, vessel, velocity = fill_xy, inside, [vx_xy, vy_xy]

    params = {
        "ndim": ndim,
        "radius": radius,
        "width": width,
        "cells": cells,
        "rpm": rpm,
        "fill_depth": float(fill_depth),
        "angle_deg": float(angle_deg),
        "layer_fraction": float(layer_fraction),
        "n_phases": n_phases,
        "margin": margin,
    }
    return _build(
        "rolling_drum",
        params,
        axes,
        velocity,
        fill,
        vessel.astype(np.int8),
        frame=frame,
        rpm=rpm,
        gravity=gravity,
    )


# flows binned from another code's particles sit beside the analytic ones (``bx.flows``)
from .binning import from_particles  # noqa: E402
