"""Vessel shapes as signed distance functions in the vessel frame, and the initial bed.

The vessel frame (DESIGN §2) has y up when the vessel is upright and the rotation axis
along z through the origin; 2-D vessels live in (x, y). A signed distance function (SDF)
is negative inside, positive outside, in metres.

Two faces of one geometry:

- for the MPM kernels, which take plain arrays only, a vessel is a pair
  ``(kind, params)`` (an integer code and a float64 array) read by the compiled,
  allocation-free :func:`sdf_point` and :func:`sdf_normal`;
- for Python, the frozen dataclasses :class:`Drum`, :class:`Tote`, :class:`Box` and
  :class:`Silo` (a box parted by a floor with a slot, for the discharge benchmark) carry
  the dimensions, validate them, and give ``kind``, ``params``, vectorised ``sdf``,
  exact ``volume``, ``bounds`` and ``contains``.

The bed at phase 0 (vessel upright, vessel frame = lab frame) is seeded on a regular
lattice by :func:`seed_particles`, filled to a volume fraction (level from the exact
:func:`volume_below`), to a depth, or into a box.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.optimize import brentq

__all__ = [
    "DRUM_2D",
    "DRUM_3D",
    "TOTE_2D",
    "TOTE_3D",
    "BOX_2D",
    "BOX_3D",
    "SILO_2D",
    "SILO_3D",
    "Drum",
    "Tote",
    "Box",
    "Silo",
    "sdf_point",
    "sdf_normal",
    "vessel_from_scene",
    "volume_below",
    "fill_level",
    "seed_particles",
    "fill_from_scene",
]

#: Integer codes of the vessel kinds, as read by :func:`sdf_point` and :func:`sdf_normal`.
DRUM_2D = 1
DRUM_3D = 2
TOTE_2D = 3
TOTE_3D = 4
BOX_2D = 5
BOX_3D = 6
SILO_2D = 7
SILO_3D = 8

# ---------------------------------------------------------------------------------------
# Compiled SDFs. Each shape returns (value, nx, ny, nz) as a tuple: tuples live in
# registers, so the kernels stay allocation-free, and one function serves both the value
# and the normal (one compiled body instead of two).
# ---------------------------------------------------------------------------------------


@njit(cache=True)
def _sign(v):
    # +1 at 0: any side is a valid choice on a symmetry plane
    return 1.0 if v >= 0.0 else -1.0


@njit(cache=True)
def _drum(params, x, y, z, is3d):
    radius = params[0]
    r = math.sqrt(x * x + y * y)
    if r > 0.0:
        ex, ey = x / r, y / r
    else:  # on the axis the radial direction is undefined; any unit vector serves
        ex, ey = 0.0, 1.0
    dr = r - radius
    if not is3d:
        return dr, ex, ey, 0.0
    sz = _sign(z)
    dz = abs(z) - params[1]
    if dr <= 0.0 and dz <= 0.0:  # inside: the nearer of the mantle and the end walls
        if dr > dz:
            return dr, ex, ey, 0.0
        return dz, 0.0, 0.0, sz
    a = max(dr, 0.0)
    b = max(dz, 0.0)
    d = math.sqrt(a * a + b * b)
    return d, a * ex / d, a * ey / d, b * sz / d


@njit(cache=True)
def _box(params, x, y, z, is3d):
    if is3d:
        qx, qy, qz = x - params[0], y - params[1], z - params[2]
        hx, hy, hz = params[3], params[4], params[5]
    else:
        qx, qy, qz = x - params[0], y - params[1], 0.0
        hx, hy, hz = params[2], params[3], math.inf
    sx, sy, sz = _sign(qx), _sign(qy), _sign(qz)
    dx, dy, dz = abs(qx) - hx, abs(qy) - hy, abs(qz) - hz
    if dx <= 0.0 and dy <= 0.0 and dz <= 0.0:  # inside: the nearest face binds
        if dx >= dy and dx >= dz:
            return dx, sx, 0.0, 0.0
        if dy >= dz:
            return dy, 0.0, sy, 0.0
        return dz, 0.0, 0.0, sz
    ax, ay, az = max(dx, 0.0), max(dy, 0.0), max(dz, 0.0)
    d = math.sqrt(ax * ax + ay * ay + az * az)
    return d, ax * sx / d, ay * sy / d, az * sz / d


@njit(cache=True)
def _slab(qx, qy, hx, hy):
    # exact SDF and outward normal of an axis-aligned rectangle (q from its centre), 2-D
    sx, sy = _sign(qx), _sign(qy)
    dx, dy = abs(qx) - hx, abs(qy) - hy
    if dx <= 0.0 and dy <= 0.0:
        if dx >= dy:
            return dx, sx, 0.0
        return dy, 0.0, sy
    ax, ay = max(dx, 0.0), max(dy, 0.0)
    d = math.sqrt(ax * ax + ay * ay)
    return d, ax * sx / d, ay * sy / d


@njit(cache=True)
def _silo(params, x, y, z, is3d):
    # the box minus the two halves of its floor plate (solids spanning z): the interior
    # distance max(d_box, -d_left, -d_right) is exact inside, where the kernels need it
    d, nx, ny, nz = _box(params, x, y, z, is3d)
    k = 6 if is3d else 4  # the slot's values follow the box's centre and half edges
    cx, hx = params[0], params[3] if is3d else params[2]
    half_slot, top, thick = params[k], params[k + 1], params[k + 2]
    # each half reaches a plate's thickness past the side wall, so it joins the wall
    wx = 0.5 * (hx + thick - half_slot)
    qy = y - (top - 0.5 * thick)
    for side in (-1.0, 1.0):
        qx = x - (cx + side * (half_slot + wx))
        dp, px, py = _slab(qx, qy, wx, 0.5 * thick)
        if -dp > d:
            d, nx, ny, nz = -dp, -px, -py, 0.0
    return d, nx, ny, nz


@njit(cache=True)
def _binding(v, d, tie):
    # weight of a face plane in the normal: 1 if it binds (within the tie tolerance)
    return 1.0 if v >= d - tie else 0.0


@njit(cache=True)
def _face_mean(lid, outlet, side_x, hopper_x, side_z, hopper_z, d, tie, sx, sz, ch, sh):
    # the sum of the normals of the tote's face planes that bind (sx, sz: the sides)
    w = _binding(lid, d, tie)
    nx, ny, nz = 0.0, w, 0.0
    w = _binding(outlet, d, tie)
    ny -= w
    w = _binding(side_x, d, tie)
    nx += w * sx
    w = _binding(hopper_x, d, tie)
    nx += w * sx * ch
    ny -= w * sh
    w = _binding(side_z, d, tie)
    nz += w * sz
    w = _binding(hopper_z, d, tie)
    ny -= w * sh
    nz += w * sz * ch
    return nx, ny, nz


@njit(cache=True)
def _tote(params, x, y, z, is3d):
    # params: half width, half straight height, bottom y (body frame), cos and sin of the
    # hopper angle, half outlet, axis offset, cos and sin of the tilt.
    hw, hs2, yb = params[0], params[1], params[2]
    ch, sh, ho = params[3], params[4], params[5]
    off, ct, st = params[6], params[7], params[8]
    # vessel frame -> body frame (upright, origin at mid-height of the straight section)
    qx = x
    qy = ct * y + st * z + off
    qz = -st * y + ct * z if is3d else 0.0
    ax, az = abs(qx), abs(qz)
    sx, sz = _sign(qx), _sign(qz)
    # the maximum over the face planes: lid, outlet, side walls x, hopper walls x, side
    # walls z, hopper walls z
    lid = qy - hs2
    outlet = yb - qy
    side_x = ax - hw
    hopper_x = (ax - ho) * ch - (qy - yb) * sh
    side_z = az - hw if is3d else -math.inf
    hopper_z = (az - ho) * ch - (qy - yb) * sh if is3d else -math.inf
    d = max(lid, outlet, side_x, hopper_x, side_z, hopper_z)
    # the normal: the binding plane's, or the mean of the planes that tie. A tie decided
    # by round-off (a point on a diagonal, whose coordinates carry a last-bit error)
    # would pick a face by that error and break the vessel's mirror symmetries.
    tie = 1e-12 * (hw + hs2)
    # on a plane x = 0 or z = 0 the two opposite walls tie: their mean has no x (z) part
    mx = 0.0 if qx == 0.0 else sx
    mz = 0.0 if qz == 0.0 else sz
    nx, ny, nz = _face_mean(lid, outlet, side_x, hopper_x, side_z, hopper_z, d, tie, mx, mz, ch, sh)
    norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    if norm == 0.0:  # on the axis of the straight section: any of the walls serves
        nx, ny, nz = _face_mean(
            lid, outlet, side_x, hopper_x, side_z, hopper_z, d, tie, sx, sz, ch, sh
        )
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
    nx, ny, nz = nx / norm, ny / norm, nz / norm
    # body-frame normal -> vessel frame
    return d, nx, ct * ny - st * nz, st * ny + ct * nz


@njit(cache=True)
def _sdf_grad(kind, params, x, y, z):
    if kind == DRUM_2D:
        return _drum(params, x, y, z, False)
    if kind == DRUM_3D:
        return _drum(params, x, y, z, True)
    if kind == TOTE_2D:
        return _tote(params, x, y, z, False)
    if kind == TOTE_3D:
        return _tote(params, x, y, z, True)
    if kind == BOX_2D:
        return _box(params, x, y, z, False)
    if kind == BOX_3D:
        return _box(params, x, y, z, True)
    if kind == SILO_2D:
        return _silo(params, x, y, z, False)
    if kind == SILO_3D:
        return _silo(params, x, y, z, True)
    return math.nan, 0.0, 0.0, 0.0  # an unknown kind shows up as NaN, never as a wall


@njit(cache=True)
def sdf_point(kind, params, x, y, z):
    """Signed distance of one point to the vessel wall (compiled).

    Parameters
    ----------
    kind : int
        Vessel code (``DRUM_2D`` ... ``BOX_3D``).
    params : ndarray of float64
        The vessel's ``params``.
    x, y, z : float
        The point in the vessel frame, m; z is ignored by 2-D kinds.

    Returns
    -------
    float
        Negative inside, positive outside, m; NaN for an unknown kind.
    """
    return _sdf_grad(kind, params, x, y, z)[0]


@njit(cache=True)
def sdf_normal(kind, params, x, y, z, out):
    """Signed distance and outward unit normal (the SDF's gradient) at one point (compiled).

    The normal is analytic: the radial or axial direction for drums, the binding face or
    the direction from the nearest edge or corner for boxes, the binding face plane for
    totes (the normalised mean of the planes that tie, within 1e-12 of the vessel's
    size: a tie that round-off decides would break the vessel's mirror symmetry). Where
    the gradient is undefined otherwise (a drum's axis, a box's inside diagonal) one of
    the one-sided gradients is written.

    Parameters
    ----------
    kind, params, x, y, z
        As for :func:`sdf_point`.
    out : ndarray of float64, length 3
        Receives (nx, ny, nz); nz = 0 for 2-D kinds.

    Returns
    -------
    float
        The signed distance, m.
    """
    d, nx, ny, nz = _sdf_grad(kind, params, x, y, z)
    out[0] = nx
    out[1] = ny
    out[2] = nz
    return d


@njit(cache=True)
def _sdf_many(kind, params, points, out):
    three = points.shape[1] == 3
    for i in range(points.shape[0]):
        z = points[i, 2] if three else 0.0
        out[i] = _sdf_grad(kind, params, points[i, 0], points[i, 1], z)[0]


@njit(cache=True)
def _normal_many(kind, params, points, out):
    three = points.shape[1] == 3
    for i in range(points.shape[0]):
        z = points[i, 2] if three else 0.0
        _, nx, ny, nz = _sdf_grad(kind, params, points[i, 0], points[i, 1], z)
        out[i, 0] = nx
        out[i, 1] = ny
        if three:
            out[i, 2] = nz


# ---------------------------------------------------------------------------------------
# Validation helpers: every message names the parameter and the allowed range.
# ---------------------------------------------------------------------------------------


def _number(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {value!r} is not a number") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} = {value!r} is not finite")
    return v


def _positive(name: str, value) -> float:
    v = _number(name, value)
    if v <= 0.0:
        raise ValueError(f"{name} = {value!r} is out of range; allowed: > 0")
    return v


def _ndim(value) -> int:
    if value not in (2, 3):
        raise ValueError(f"ndim = {value!r} is not one of [2, 3]")
    return int(value)


class _Shape:
    """Vectorised methods shared by the vessel classes (they need ndim, kind, params)."""

    def _flat(self, points) -> tuple[np.ndarray, tuple]:
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim == 0 or pts.shape[-1] != self.ndim:
            raise ValueError(
                f"points: last axis has {pts.shape[-1:] or 'no'} entries; a {self.ndim}-D "
                f"vessel needs {self.ndim}"
            )
        return np.ascontiguousarray(pts.reshape(-1, self.ndim)), pts.shape[:-1]

    def sdf(self, points) -> np.ndarray:
        """Signed distance at points of shape (..., ndim); result of shape (...), m."""
        flat, shape = self._flat(points)
        out = np.empty(flat.shape[0])
        _sdf_many(self.kind, self.params, flat, out)
        return out.reshape(shape)

    def normal(self, points) -> np.ndarray:
        """Outward unit normal (SDF gradient) at points of shape (..., ndim); same shape."""
        flat, shape = self._flat(points)
        out = np.empty_like(flat)
        _normal_many(self.kind, self.params, flat, out)
        return out.reshape(shape + (self.ndim,))

    def contains(self, points) -> np.ndarray:
        """True where points of shape (..., ndim) lie strictly inside the vessel."""
        return self.sdf(points) < 0.0


# ---------------------------------------------------------------------------------------
# The vessels
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Drum(_Shape):
    """A drum: a circle (2-D) or a capped cylinder about the z axis (3-D), exact SDF.

    Parameters
    ----------
    diameter : float
        m, centred on the origin.
    ndim : {2, 3}
        2-D: the circle in (x, y); 3-D: the cylinder with flat end walls at z = ±length/2.
    length : float, optional
        Axial length, m; required in 3-D. In 2-D it is only recorded (the axial width of
        the plane-strain slab) and plays no part in the shape.
    """

    diameter: float
    ndim: int = 2
    length: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "diameter", _positive("diameter", self.diameter))
        object.__setattr__(self, "ndim", _ndim(self.ndim))
        if self.length is not None:
            object.__setattr__(self, "length", _positive("length", self.length))
        elif self.ndim == 3:
            raise ValueError("length: required for a 3-D drum (axial length, > 0)")

    @property
    def radius(self) -> float:
        """Radius, m."""
        return 0.5 * self.diameter

    @property
    def kind(self) -> int:
        """Vessel code for the compiled SDF."""
        return DRUM_3D if self.ndim == 3 else DRUM_2D

    @property
    def params(self) -> np.ndarray:
        """(radius, half length) in 3-D, (radius,) in 2-D."""
        if self.ndim == 3:
            return np.array([self.radius, 0.5 * self.length])
        return np.array([self.radius])

    @property
    def volume(self) -> float:
        """πR² in 2-D (m²), πR²L in 3-D (m³)."""
        area = math.pi * self.radius**2
        return area * self.length if self.ndim == 3 else area

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners of the bounding box in the vessel frame, m."""
        r = self.radius
        hi = np.array([r, r, 0.5 * self.length] if self.ndim == 3 else [r, r])
        return -hi, hi

    def describe(self) -> str:
        """One line: the drum's dimensions."""
        text = f"{self.ndim}-D drum, {1e3 * self.diameter:g} mm across"
        if self.length is not None:
            word = "long" if self.ndim == 3 else "wide (axial width, not part of the shape)"
            text += f", {1e3 * self.length:g} mm {word}"
        return text

    def _volume_below(self, y: float) -> float:
        r = self.radius
        h = min(max(y + r, 0.0), 2.0 * r)  # height of the circular segment
        area = r * r * math.acos(1.0 - h / r) - (r - h) * math.sqrt(max(2.0 * r * h - h * h, 0.0))
        return area * self.length if self.ndim == 3 else area


@dataclass(frozen=True)
class Tote(_Shape):
    """A Tote bin: square straight section over a pyramidal hopper, flat lid, flat outlet.

    In the body frame (upright, origin at mid-height of the straight section) the straight
    section spans |x|, |z| ≤ width/2 and |y| ≤ straight_height/2; the hopper walls, at
    ``hopper_angle_deg`` from vertical, run down to a square outlet ``outlet_width``
    across, closed flat. The vessel frame puts the rotation axis (z) ``axis_offset``
    above that mid-height (the bin is shifted down by ``axis_offset``) and then tilts the
    bin's symmetry axis from +y towards +z by ``tilt_deg`` about the x axis (3-D only).
    Defaults are DESIGN §7's labelled assumption: 14.0 L, 0.374 m tall.

    The SDF is the maximum of the signed face-plane distances (lid, side walls, hopper
    walls, bottom) of this convex polytope: exact inside and on the wall; outside it is a
    lower bound of the distance (exact where the nearest wall point is inside a face, too
    small beyond edges and corners). Its gradient, the binding plane's normal, is a unit
    vector everywhere. 2-D: the x–y cross-section (rectangle over a trapezoid).

    Parameters
    ----------
    ndim : {2, 3}
    width, straight_height : float
        m, > 0.
    hopper_angle_deg : float
        Hopper wall angle from vertical, in (0, 90).
    outlet_width : float
        m, in [0, width].
    axis_offset : float
        m, height of the rotation axis above mid-height of the straight section.
    tilt_deg : float
        In (-90, 90); must be 0 in 2-D.
    """

    ndim: int = 3
    width: float = 0.22
    straight_height: float = 0.227
    hopper_angle_deg: float = 30.0
    outlet_width: float = 0.05
    axis_offset: float = 0.0
    tilt_deg: float = 0.0

    def __post_init__(self):
        set_ = object.__setattr__
        set_(self, "ndim", _ndim(self.ndim))
        set_(self, "width", _positive("width", self.width))
        set_(self, "straight_height", _positive("straight_height", self.straight_height))
        angle = _number("hopper_angle_deg", self.hopper_angle_deg)
        if not 0.0 < angle < 90.0:
            raise ValueError(
                f"hopper_angle_deg = {self.hopper_angle_deg!r} is out of range; allowed: > 0 "
                "and < 90"
            )
        set_(self, "hopper_angle_deg", angle)
        outlet = _number("outlet_width", self.outlet_width)
        if not 0.0 <= outlet <= self.width:
            raise ValueError(
                f"outlet_width = {self.outlet_width!r} is out of range; allowed: >= 0 and "
                f"<= width ({self.width:g})"
            )
        set_(self, "outlet_width", outlet)
        set_(self, "axis_offset", _number("axis_offset", self.axis_offset))
        tilt = _number("tilt_deg", self.tilt_deg)
        if not -90.0 < tilt < 90.0:
            raise ValueError(
                f"tilt_deg = {self.tilt_deg!r} is out of range; allowed: > -90 and < 90"
            )
        if self.ndim == 2 and tilt != 0.0:
            raise ValueError(f"tilt_deg = {self.tilt_deg!r}: a 2-D tote cannot tilt; allowed: 0")
        set_(self, "tilt_deg", tilt)

    @property
    def hopper_height(self) -> float:
        """Height of the hopper, (width − outlet_width) / (2 tan θ), m."""
        tan = math.tan(math.radians(self.hopper_angle_deg))
        return 0.5 * (self.width - self.outlet_width) / tan

    @property
    def height(self) -> float:
        """Total height, straight section plus hopper, m."""
        return self.straight_height + self.hopper_height

    @property
    def kind(self) -> int:
        """Vessel code for the compiled SDF."""
        return TOTE_3D if self.ndim == 3 else TOTE_2D

    @property
    def params(self) -> np.ndarray:
        """Half width, half straight height, bottom y (body frame), cos θ, sin θ, half
        outlet, axis offset, cos and sin of the tilt."""
        th = math.radians(self.hopper_angle_deg)
        tilt = math.radians(self.tilt_deg)
        hs2 = 0.5 * self.straight_height
        return np.array(
            [
                0.5 * self.width,
                hs2,
                -hs2 - self.hopper_height,
                math.cos(th),
                math.sin(th),
                0.5 * self.outlet_width,
                self.axis_offset,
                math.cos(tilt),
                math.sin(tilt),
            ]
        )

    @property
    def volume(self) -> float:
        """Exact: box plus frustum (3-D, m³) or rectangle plus trapezoid (2-D, m²)."""
        w, wo, hh = self.width, self.outlet_width, self.hopper_height
        if self.ndim == 3:
            return w * w * self.straight_height + hh / 3.0 * (w * w + wo * wo + w * wo)
        return w * self.straight_height + 0.5 * (w + wo) * hh

    def vertices(self) -> np.ndarray:
        """Corners of the polytope in the vessel frame, shape (n, ndim), m."""
        hw, hs2, ho = 0.5 * self.width, 0.5 * self.straight_height, 0.5 * self.outlet_width
        yb = -hs2 - self.hopper_height
        rings = ((hw, hs2), (hw, -hs2), (ho, yb))
        if self.ndim == 2:
            return np.array([(s * r, y - self.axis_offset) for r, y in rings for s in (-1, 1)])
        body = np.array([(sx * r, y, sz * r) for r, y in rings for sx in (-1, 1) for sz in (-1, 1)])
        body[:, 1] -= self.axis_offset
        t = math.radians(self.tilt_deg)
        c, s = math.cos(t), math.sin(t)
        out = body.copy()
        out[:, 1] = c * body[:, 1] - s * body[:, 2]
        out[:, 2] = s * body[:, 1] + c * body[:, 2]
        return out

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners of the bounding box in the vessel frame, m (from the
        vertices: exact for a convex polytope)."""
        v = self.vertices()
        return v.min(axis=0), v.max(axis=0)

    def describe(self) -> str:
        """One line: the tote's dimensions, volume, axis offset and tilt."""
        unit = "L" if self.ndim == 3 else "m²"
        size = 1e3 * self.volume if self.ndim == 3 else self.volume
        return (
            f"{self.ndim}-D tote, {1e3 * self.width:g} mm square bin, "
            f"{1e3 * self.straight_height:g} mm straight, hopper {self.hopper_angle_deg:g}° "
            f"from vertical to a {1e3 * self.outlet_width:g} mm outlet, "
            f"{1e3 * self.height:.1f} mm tall, {size:.4g} {unit}; axis "
            f"{1e3 * self.axis_offset:g} mm above mid-height, tilt {self.tilt_deg:g}°"
        )

    def _volume_below(self, y: float) -> float:
        hs2, ho, hh = 0.5 * self.straight_height, 0.5 * self.outlet_width, self.hopper_height
        yb, tan = -hs2 - hh, math.tan(math.radians(self.hopper_angle_deg))
        if self.ndim == 2:  # trapezoid then rectangle, exact
            t = min(max(y + self.axis_offset - yb, 0.0), hh)
            s = min(max(y + self.axis_offset + hs2, 0.0), self.straight_height)
            return 2.0 * ho * t + tan * t * t + self.width * s
        # (bottom, top, half width at bottom, its slope) of the hopper and straight pieces
        pieces = ((yb, -hs2, ho, tan), (-hs2, hs2, 0.5 * self.width, 0.0))
        return sum(_tilted_slab_volume(*p, self, y) for p in pieces)


# Gauss–Legendre with 3 nodes integrates cubics exactly; the slab integrands are quadratic.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(3)


def _tilted_slab_volume(q0, q1, r0, k, tote: Tote, y: float) -> float:
    """Volume of the tote piece q0 < q_y < q1 (half width r0 + k (q_y − q0)) below y.

    The cut {y_vessel < y} reads s·q_z > c·(q_y − a) − y = u in the body frame (c, s the
    tilt's cosine and sine, a the axis offset) and does not involve x, so the volume is
    ∫ 2r(q_y) L(q_y) dq_y, L the length of [−r, r] where s·q_z > u. L is piecewise linear
    with kinks where u = ±s·r: between kinks the integrand is quadratic, and Gauss–
    Legendre is exact.
    """
    if q1 <= q0:
        return 0.0
    t = math.radians(tote.tilt_deg)
    c, s, a = math.cos(t), math.sin(t), tote.axis_offset
    cuts = [q0, q1]
    for sigma in (s, -s):
        den = c - sigma * k
        if den != 0.0:
            q = (y + c * a + sigma * (r0 - k * q0)) / den
            if q0 < q < q1:
                cuts.append(q)
    cuts.sort()
    total = 0.0
    for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
        q = 0.5 * (lo + hi) + 0.5 * (hi - lo) * _GL_X
        r = r0 + k * (q - q0)
        u = c * (q - a) - y
        if s > 0.0:
            length = np.clip(r - u / s, 0.0, 2.0 * r)
        elif s < 0.0:
            length = np.clip(r + u / s, 0.0, 2.0 * r)
        else:
            length = np.where(u < 0.0, 2.0 * r, 0.0)
        total += 0.5 * (hi - lo) * float(np.dot(_GL_W, 2.0 * r * length))
    return total


@dataclass(frozen=True)
class Box(_Shape):
    """An axis-aligned box, exact SDF.

    Parameters
    ----------
    size : sequence of 2 or 3 floats
        Edge lengths along x, y(, z), m, > 0; their number sets ndim.
    center : sequence of floats, optional
        Centre in the vessel frame, m (default the origin).
    """

    size: tuple
    center: tuple | None = None

    def __post_init__(self):
        size = np.atleast_1d(np.asarray(self.size, dtype=object))
        if size.ndim != 1 or len(size) not in (2, 3):
            raise ValueError(f"size = {self.size!r}: give 2 or 3 edge lengths, each > 0")
        size = tuple(_positive(f"size[{i}]", v) for i, v in enumerate(size))
        center = (0.0,) * len(size) if self.center is None else tuple(self.center)
        if len(center) != len(size):
            raise ValueError(
                f"center = {self.center!r}: give {len(size)} coordinates, as many as size"
            )
        object.__setattr__(self, "size", size)
        object.__setattr__(
            self, "center", tuple(_number(f"center[{i}]", v) for i, v in enumerate(center))
        )

    @property
    def ndim(self) -> int:
        """2 or 3, the number of edge lengths."""
        return len(self.size)

    @property
    def kind(self) -> int:
        """Vessel code for the compiled SDF."""
        return BOX_3D if self.ndim == 3 else BOX_2D

    @property
    def params(self) -> np.ndarray:
        """Centre then half edge lengths."""
        return np.array(self.center + tuple(0.5 * s for s in self.size))

    @property
    def volume(self) -> float:
        """Product of the edge lengths (m² in 2-D, m³ in 3-D)."""
        return float(np.prod(self.size))

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) corners, m."""
        c, h = np.array(self.center), 0.5 * np.array(self.size)
        return c - h, c + h

    def describe(self) -> str:
        """One line: the box's edges and centre."""
        edges = " x ".join(f"{1e3 * s:g}" for s in self.size)
        centre = ", ".join(f"{1e3 * c:g}" for c in self.center)
        return f"{self.ndim}-D box, {edges} mm, centred at ({centre}) mm"

    def _volume_below(self, y: float) -> float:
        # the box's own cross-section, not ``self.volume``: a subclass that takes volume
        # out of the box (the silo's floor) subtracts its own share from this
        lo = self.center[1] - 0.5 * self.size[1]
        section = float(np.prod(self.size)) / self.size[1]
        return section * min(max(y - lo, 0.0), self.size[1])


@dataclass(frozen=True)
class Silo(Box):
    """A flat-bottomed silo over a bin: a box parted by a horizontal floor plate with a
    centred slot, through which the bed discharges into the bin below.

    The slot spans the whole box along z (a plane slot in 3-D). The SDF is exact inside
    the vessel; the plate's two halves join the side walls.

    Parameters
    ----------
    size, center
        As for :class:`Box`: the outer box, m.
    orifice : float
        Width of the slot along x, m, > 0 and < the box's width.
    floor_height : float
        Height of the plate's top face above the box's bottom, m.
    floor_thickness : float
        Thickness of the plate, m, > 0; the plate must fit inside the box, and should be
        a few background cells thick so that no cell straddles both of its faces.
    """

    orifice: float = 0.0
    floor_height: float = 0.0
    floor_thickness: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        width, height = self.size[0], self.size[1]
        orifice = _positive("orifice", self.orifice)
        if orifice >= width:
            raise ValueError(
                f"orifice = {self.orifice!r} is out of range; allowed: > 0 and < the box's "
                f"width {width!r}"
            )
        thick = _positive("floor_thickness", self.floor_thickness)
        top = _number("floor_height", self.floor_height)
        if not thick < top < height:
            raise ValueError(
                f"floor_height = {self.floor_height!r} is out of range; allowed: > "
                f"floor_thickness ({thick!r}) and < the box's height ({height!r})"
            )
        object.__setattr__(self, "orifice", orifice)
        object.__setattr__(self, "floor_height", top)
        object.__setattr__(self, "floor_thickness", thick)

    @property
    def kind(self) -> int:
        """Vessel code for the compiled SDF."""
        return SILO_3D if self.ndim == 3 else SILO_2D

    @property
    def floor_top(self) -> float:
        """y of the plate's top face in the vessel frame, m."""
        return self.center[1] - 0.5 * self.size[1] + self.floor_height

    @property
    def params(self) -> np.ndarray:
        """The box's centre and half edges, then half the slot, the plate's top y and its
        thickness."""
        extra = (0.5 * self.orifice, self.floor_top, self.floor_thickness)
        return np.array(self.center + tuple(0.5 * s for s in self.size) + extra)

    @property
    def _plate_section(self) -> float:
        """The plate's horizontal cross-section (a length in 2-D, an area in 3-D): the
        volume it takes per unit height."""
        depth = self.size[2] if self.ndim == 3 else 1.0
        return (self.size[0] - self.orifice) * depth

    @property
    def volume(self) -> float:
        """The box's volume less the plate's (m² in 2-D, m³ in 3-D)."""
        return float(np.prod(self.size)) - self._plate_section * self.floor_thickness

    def describe(self) -> str:
        """One line: the box, the slot and the floor."""
        return (
            f"{super().describe()}, parted by a {1e3 * self.floor_thickness:g} mm floor "
            f"{1e3 * self.floor_height:g} mm above its bottom with a "
            f"{1e3 * self.orifice:g} mm slot"
        )

    def _volume_below(self, y: float) -> float:
        bottom = self.floor_top - self.floor_thickness
        plate_below = min(max(y - bottom, 0.0), self.floor_thickness)
        return super()._volume_below(y) - self._plate_section * plate_below


Vessel = Drum | Tote | Box | Silo

# ---------------------------------------------------------------------------------------
# From a scene
# ---------------------------------------------------------------------------------------

_TOTE_KEYS = (
    "width",
    "straight_height",
    "hopper_angle_deg",
    "outlet_width",
    "axis_offset",
    "tilt_deg",
)
_SILO_KEYS = ("orifice", "floor_height", "floor_thickness")


def _require(section: Mapping, key: str, kind: str):
    if key not in section:
        raise ValueError(f"vessel.{key}: required for a {kind}")
    return section[key]


def vessel_from_scene(scene: Mapping) -> Vessel:
    """Build the vessel described by a scene's ``vessel`` section.

    Parameters
    ----------
    scene : Scene or mapping
        A scene (its ``vessel`` section is read) or a vessel section itself. Keys:
        ``kind`` (drum, tote, box; default tote), ``ndim`` (2, 3; default 3); drum:
        ``diameter``, ``length`` (3-D; ``width`` when absent); tote: ``width``,
        ``straight_height``, ``hopper_angle_deg``, ``outlet_width``, ``axis_offset``,
        ``tilt_deg`` (each defaulting to DESIGN §7); box: ``size``, ``center``; silo: a
        box's keys and ``orifice``, ``floor_height``, ``floor_thickness``.

    Returns
    -------
    Drum, Tote, Box or Silo

    Raises
    ------
    ValueError
        Naming the missing or faulty key and what is allowed.
    """
    section = scene["vessel"] if "vessel" in scene else scene
    kind = section.get("kind", "tote")
    ndim = _ndim(section.get("ndim", 3))
    if kind == "drum":
        length = section.get("length", section.get("width"))
        if ndim == 3 and length is None:
            raise ValueError("vessel.length: required for a 3-D drum (or give vessel.width)")
        return Drum(_require(section, "diameter", "drum"), ndim=ndim, length=length)
    if kind == "tote":
        return Tote(ndim=ndim, **{k: section[k] for k in _TOTE_KEYS if k in section})
    if kind in ("box", "silo"):
        size = _require(section, "size", kind)
        if kind == "box":
            box = Box(size, section.get("center"))
        else:
            floor = {key: _require(section, key, kind) for key in _SILO_KEYS}
            box = Silo(size, section.get("center"), **floor)
        if box.ndim != ndim:
            raise ValueError(f"vessel.size: {box.ndim} edge lengths given for ndim = {ndim}")
        return box
    raise ValueError(f"vessel.kind = {kind!r} is not one of ['drum', 'tote', 'box', 'silo']")


# ---------------------------------------------------------------------------------------
# Fill: level of a volume fraction, and the particle lattice
# ---------------------------------------------------------------------------------------


def volume_below(vessel: Vessel, y):
    """Volume (3-D, m³) or area (2-D, m²) of the vessel below the level y.

    Exact: circular segments for drums, rectangles and trapezoids or boxes and frusta for
    upright totes, piecewise-quadratic slab integrals (Gauss–Legendre, exact) for tilted
    totes.

    Parameters
    ----------
    vessel : Drum, Tote or Box
    y : float or array of float
        Level in the vessel frame, m.

    Returns
    -------
    float or ndarray
        0 below the lowest point, ``vessel.volume`` above the highest.
    """
    if np.ndim(y) == 0:
        return vessel._volume_below(float(y))
    return np.array([vessel._volume_below(float(v)) for v in np.ravel(y)]).reshape(np.shape(y))


def fill_level(vessel: Vessel, fraction: float) -> float:
    """The level y (vessel frame, m) below which lies ``fraction`` of the vessel's volume.

    Parameters
    ----------
    vessel : Drum, Tote or Box
    fraction : float
        In (0, 1].

    Returns
    -------
    float
    """
    f = _number("fraction", fraction)
    if not 0.0 < f <= 1.0:
        raise ValueError(f"fraction = {fraction!r} is out of range; allowed: > 0 and <= 1")
    lo, hi = (float(b[1]) for b in vessel.bounds)
    if f == 1.0:  # the root sits on the bracket's end, where round-off may hide the sign
        return hi
    target = f * vessel.volume
    return brentq(lambda y: vessel._volume_below(y) - target, lo, hi, xtol=1e-13)


def _region(vessel: Vessel, fraction, depth, box) -> tuple[np.ndarray, np.ndarray]:
    """[lower, upper) corners of the material region, clipped to the vessel's bounds."""
    if fraction is not None and depth is not None:
        raise ValueError("fill: give one of fraction or depth, not both (a box may join either)")
    if fraction is None and depth is None and box is None:
        raise ValueError("fill: give fraction, depth or box")
    lo, hi = (b.astype(float) for b in vessel.bounds)
    if fraction is not None:
        hi[1] = min(hi[1], fill_level(vessel, fraction))
    if depth is not None:
        hi[1] = min(hi[1], lo[1] + _positive("depth", depth))
    if box is not None:
        pairs = np.asarray(box, dtype=float)
        if pairs.shape != (vessel.ndim, 2):
            raise ValueError(
                f"box = {box!r}: give {vessel.ndim} [lo, hi] pairs, one per axis of the vessel"
            )
        if not np.all(np.isfinite(pairs)) or np.any(pairs[:, 0] >= pairs[:, 1]):
            raise ValueError(f"box = {box!r}: each pair must be finite with lo < hi")
        lo, hi = np.maximum(lo, pairs[:, 0]), np.minimum(hi, pairs[:, 1])
    return lo, hi


def _sites(lo: float, hi: float, cell: float, per_cell: int) -> np.ndarray:
    """Lattice coordinates (i + (k + 0.5)/per_cell)·cell in [lo, hi)."""
    spacing = cell / per_cell
    j = np.arange(math.floor(lo / spacing) - 1, math.ceil(hi / spacing) + 1)
    i, k = np.divmod(j, per_cell)
    x = (i + (k + 0.5) / per_cell) * cell
    return x[(x >= lo) & (x < hi)]


def _in_region(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.all((points >= lo) & (points < hi), axis=-1)


def seed_particles(
    vessel: Vessel,
    cell: float,
    per_cell: int = 2,
    fraction: float | None = None,
    depth: float | None = None,
    box: Sequence[Sequence[float]] | None = None,
    jitter: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, float]:
    """Material points of the bed at phase 0 (vessel upright), on a regular lattice.

    Sites sit at the sub-cell centres (i + (k + 0.5)/per_cell)·cell of a background grid
    whose nodes are the integer multiples of ``cell``, and are kept when strictly inside
    the vessel (sdf < 0) and inside the material region [lo, hi) per axis.

    Parameters
    ----------
    vessel : Drum, Tote or Box
    cell : float
        Background-grid cell, m.
    per_cell : int
        Particles per cell along each axis, >= 1.
    fraction : float, optional
        Fill the vessel from the bottom to this volume fraction (level from
        :func:`fill_level`).
    depth : float, optional
        Bed depth above the vessel's lowest point, m.
    box : sequence of [lo, hi] pairs, optional
        Axis-aligned region in the vessel frame, one pair per axis. With fraction or
        depth the region is the intersection (the fraction is still of the whole vessel).
    jitter : float
        Uniform random displacement per coordinate, as a fraction of the sub-cell
        spacing, in [0, 1] (1: anywhere in its sub-cell). A displaced particle that would
        leave the vessel or the region stays on its site, so N does not depend on jitter.
    seed : int
        Seed of the jitter.

    Returns
    -------
    positions : ndarray, shape (N, ndim)
        m, vessel frame.
    volume_per_particle : float
        (cell / per_cell)**ndim.

    Raises
    ------
    ValueError
        When none of fraction, depth and box is given, both fraction and depth are, or a
        value is out of range (the message names it).
    """
    cell = _positive("cell", cell)
    if isinstance(per_cell, bool) or int(per_cell) != per_cell or per_cell < 1:
        raise ValueError(f"per_cell = {per_cell!r} is out of range; allowed: an integer >= 1")
    per_cell = int(per_cell)
    jitter = _number("jitter", jitter)
    if not 0.0 <= jitter <= 1.0:
        raise ValueError(f"jitter = {jitter!r} is out of range; allowed: >= 0 and <= 1")
    lo, hi = _region(vessel, fraction, depth, box)
    spacing = cell / per_cell
    axes = [_sites(a, b, cell, per_cell) for a, b in zip(lo, hi, strict=True)]
    kept = []
    # one horizontal layer at a time keeps the memory to one layer of sites in 3-D
    for y in axes[1]:
        grids = np.meshgrid(axes[0], [y], *axes[2:], indexing="ij")
        layer = np.stack([g.ravel() for g in grids], axis=-1)
        kept.append(layer[vessel.sdf(layer) < 0.0])
    if not kept:
        return np.empty((0, vessel.ndim)), spacing**vessel.ndim
    positions = np.concatenate(kept)
    if jitter > 0.0 and len(positions):
        rng = np.random.default_rng(seed)
        moved = positions + (rng.random(positions.shape) - 0.5) * (jitter * spacing)
        ok = (vessel.sdf(moved) < 0.0) & _in_region(moved, lo, hi)
        positions[ok] = moved[ok]
    return positions, spacing**vessel.ndim


def fill_from_scene(
    vessel: Vessel, scene: Mapping, cell: float, jitter: float = 0.0
) -> tuple[np.ndarray, float]:
    """:func:`seed_particles` from a scene's ``fill`` and ``solver`` sections.

    Parameters
    ----------
    vessel : Drum, Tote or Box
    scene : Scene or mapping
        ``fill``: ``fraction``, ``depth``, ``box``; ``solver``: ``particles_per_cell``
        (default 2) and ``seed`` (default 0).
    cell : float
        Background-grid cell, m.
    jitter : float
        As for :func:`seed_particles` (the scene does not carry it).

    Returns
    -------
    positions, volume_per_particle
        As for :func:`seed_particles`.
    """
    fill = scene.get("fill") or {}
    solver = scene.get("solver") or {}
    if not any(k in fill for k in ("fraction", "depth", "box")):
        raise ValueError("fill: give fill.fraction, fill.depth or fill.box")
    return seed_particles(
        vessel,
        cell,
        per_cell=solver.get("particles_per_cell", 2),
        fraction=fill.get("fraction"),
        depth=fill.get("depth"),
        box=fill.get("box"),
        jitter=jitter,
        seed=solver.get("seed", 0),
    )
