"""Diagnostics of a rolling drum's flow: free surface, flowing-layer flux, surface speed.

Plain functions on a 2-D drum flow dataset (schema ``flow/1``) stored in the lab frame
(``frame = "lab"``), where a drum's flow is steady: the dataset of the built-in solver
(:func:`blendxr.solve_flow` on a drum scene) or of :func:`blendxr.flows.rolling_drum`.
The drum's axis is the z axis through the origin and it turns counter-clockwise seen
from +z (DESIGN §2), so the wall drags the bed up on the +x side and the free surface
rises towards +x.

Chord coordinates (the same as :func:`blendxr.flows.rolling_drum`): for a surface line
inclined at β, ``t = (cos β, sin β)`` points along it uphill and ``m = (-sin β, cos β)``
out of the bed. A point p has ``s = t·p`` (0 at the chord's midpoint, the foot of the
perpendicular from the axis; uphill positive) and ``n = m·p - d`` (0 on the line,
negative in the bed), where ``d = m·c`` is the signed distance of the line from the axis.
The half-chord is ``L = sqrt(R² - d²)``. "Downslope" is ``-t``.

Fields are read between cell centres by bilinear interpolation. The flux and the surface
speed interpolate the volume-flux density ``fill · v`` (the deposited momentum per unit
density, which the averaging conserves) and the fill separately, so a cell half full of
fast material counts for half, not for a whole cell at that speed.

Functions
---------
surface_line
    The free surface: where the fill crosses a level, and the least-squares line.
layer_flux
    Downslope volume flux per unit depth through the flowing layer at chord positions.
surface_velocity
    Downslope speed along the free surface: profile and maximum.
rolling_drum_flux
    ``q(s) = ω (L² - s²) / 2``, the flux a rigid bed hands to a thin flowing layer.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass

import numpy as np
import xarray as xr

__all__ = [
    "SurfaceLine",
    "drum_radius",
    "layer_flux",
    "rolling_drum_flux",
    "surface_line",
    "surface_velocity",
]

#: Sampling step along a normal line, as a fraction of the cell.
_NORMAL_STEP = 0.05
#: How far above the surface line a normal line starts, in cells (material that stands
#: above the fitted line still counts; empty space adds nothing).
_ABOVE = 3.0
#: How far past the wall the uphill integral runs, in cells (see `layer_flux`).
_BEYOND_WALL = 1.5


# ----------------------------------------------------------------------------- fields


@dataclass(frozen=True)
class _Field2D:
    """One phase of a 2-D flow: fill, volume-flux density and grid, indexed (x, y)."""

    x0: float
    y0: float
    h: float
    fill: np.ndarray
    flux_x: np.ndarray  # fill * vx
    flux_y: np.ndarray  # fill * vy
    omega: float
    radius: float

    def sample(self, array: np.ndarray, px, py) -> np.ndarray:
        """Bilinear interpolation between cell centres; zero beyond the outer centres."""
        px, py = np.broadcast_arrays(np.asarray(px, float), np.asarray(py, float))
        fx = (px - self.x0) / self.h
        fy = (py - self.y0) / self.h
        nx, ny = array.shape
        i = np.floor(fx).astype(np.int64)
        j = np.floor(fy).astype(np.int64)
        wx, wy = fx - i, fy - j
        out = np.zeros(px.shape)
        for di, wi in ((0, 1.0 - wx), (1, wx)):
            for dj, wj in ((0, 1.0 - wy), (1, wy)):
                ii, jj = i + di, j + dj
                ok = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
                value = np.zeros(px.shape)
                value[ok] = array[ii[ok], jj[ok]]
                out += wi * wj * value
        return out


def drum_radius(flow: xr.Dataset) -> float:
    """The drum's radius in m, from the flow's own description.

    In order: the ``analytic`` attribute of an analytic flow (its ``radius``), the
    ``scene`` attribute (``vessel.diameter / 2``), else the vessel mask (the radius of
    the disc of the same area as the cells marked inside; good to a fraction of a cell).
    """
    recipe = flow.attrs.get("analytic")
    if recipe:
        params = json.loads(recipe)
        if "radius" in params:
            return float(params["radius"])
    scene = flow.attrs.get("scene")
    if scene:
        vessel = tomllib.loads(scene).get("vessel", {})
        if "diameter" in vessel:
            return 0.5 * float(vessel["diameter"])
    h = _spacing(flow)
    return math.sqrt(float(flow["vessel"].sum()) * h * h / math.pi)


def _spacing(flow: xr.Dataset) -> float:
    x = np.asarray(flow["x"].values, float)
    return float(x[1] - x[0])


def _field(flow: xr.Dataset, phase: int, radius: float | None) -> _Field2D:
    if "z" in flow.dims:
        raise ValueError("the drum diagnostics take a 2-D flow (dims x, y); this one has z")
    frame = flow.attrs.get("frame")
    if frame != "lab":
        raise ValueError(
            f"the drum diagnostics need the flow in the lab frame (frame = 'lab'), where a "
            f"drum's flow is steady; this one has frame = {frame!r}"
        )
    x = np.asarray(flow["x"].values, float)
    y = np.asarray(flow["y"].values, float)
    h = float(x[1] - x[0])
    if not math.isclose(float(y[1] - y[0]), h, rel_tol=1e-6):
        raise ValueError("the drum diagnostics need square cells (equal x and y spacing)")
    pick = {"rev_phase": phase} if "rev_phase" in flow.dims else {}
    fill = np.asarray(flow["fill"].isel(pick).transpose("x", "y").values, float)
    vx = np.asarray(flow["vx"].isel(pick).transpose("x", "y").values, float)
    vy = np.asarray(flow["vy"].isel(pick).transpose("x", "y").values, float)
    rpm = float(flow.attrs.get("rpm", 0.0))
    return _Field2D(
        x0=float(x[0]),
        y0=float(y[0]),
        h=h,
        fill=fill,
        flux_x=fill * vx,
        flux_y=fill * vy,
        omega=2.0 * math.pi * rpm / 60.0,
        radius=drum_radius(flow) if radius is None else float(radius),
    )


# ----------------------------------------------------------------------------- surface


@dataclass(frozen=True)
class SurfaceLine:
    """The free surface of a drum's bed and its least-squares line.

    Attributes
    ----------
    angle_deg : float
        Inclination of the line from horizontal, degrees; positive when it rises
        towards +x (a drum turning counter-clockwise seen from +z).
    centre : (float, float)
        The chord's midpoint (m): the foot of the perpendicular from the axis.
    offset : float
        Signed distance ``d`` of the line from the axis along the outward normal m
        (negative: the line lies below the axis, a bed less than half full).
    half_chord : float
        ``L = sqrt(R² - d²)``: half the length of the line inside the drum, m.
    radius : float
        Drum radius R used, m.
    cell : float
        Cell size of the flow, m.
    level : float
        Fill level that marks the surface.
    points : ndarray, shape (n, 2)
        The crossing points used in the fit (x, y), m.
    residuals : ndarray, shape (n,)
        Signed distance of each point from the line along m, m.
    method : str
        ``"normal"`` (crossings along lines normal to the surface) or ``"column"``
        (crossings down each column of cells).
    """

    angle_deg: float
    centre: tuple[float, float]
    offset: float
    half_chord: float
    radius: float
    cell: float
    level: float
    points: np.ndarray
    residuals: np.ndarray
    method: str

    @property
    def tangent(self) -> tuple[float, float]:
        """Unit vector along the line, uphill."""
        b = math.radians(self.angle_deg)
        return (math.cos(b), math.sin(b))

    @property
    def normal(self) -> tuple[float, float]:
        """Unit normal pointing out of the bed."""
        b = math.radians(self.angle_deg)
        return (-math.sin(b), math.cos(b))

    @property
    def rms_residual(self) -> float:
        """Root-mean-square distance of the crossing points from the line, m."""
        return float(np.sqrt(np.mean(np.square(self.residuals))))

    @property
    def max_residual(self) -> float:
        """Largest distance of a crossing point from the line, m."""
        return float(np.max(np.abs(self.residuals)))

    def chord_coordinates(self, x, y):
        """``(s, n)`` of points ``(x, y)``: along the line from its midpoint (uphill
        positive) and across it (out of the bed positive)."""
        (tx, ty), (mx, my) = self.tangent, self.normal
        x, y = np.asarray(x, float), np.asarray(y, float)
        return tx * x + ty * y, mx * x + my * y - self.offset

    def point(self, s, n=0.0):
        """``(x, y)`` of chord coordinates ``(s, n)``."""
        (tx, ty), (mx, my) = self.tangent, self.normal
        s, n = np.asarray(s, float), np.asarray(n, float)
        a = n + self.offset
        return tx * s + mx * a, ty * s + my * a

    def wall_depth(self, s):
        """``n`` at which the normal line through ``s`` meets the wall below the bed."""
        s = np.asarray(s, float)
        return -self.offset - np.sqrt(np.clip(self.radius**2 - s * s, 0.0, None))


def _line_from_points(points: np.ndarray, radius: float):
    """Total least squares line through points: (angle in degrees, offset, tangent, normal)."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    tx, ty = vt[0]
    if tx < 0:
        tx, ty = -tx, -ty
    angle = math.degrees(math.atan2(ty, tx))
    mx, my = -ty, tx
    offset = mx * centroid[0] + my * centroid[1]
    if abs(offset) >= radius:
        raise ValueError(
            f"the fitted surface line lies {abs(offset):.4g} m from the axis, outside the "
            f"drum (radius {radius:.4g} m): no free surface found"
        )
    return angle, offset


def _column_crossings(field: _Field2D, level: float, margin: float) -> np.ndarray:
    """Topmost crossing of ``level`` down each column, away from the wall."""
    fill = field.fill
    nx, ny = fill.shape
    xs = field.x0 + field.h * np.arange(nx)
    ys = field.y0 + field.h * np.arange(ny)
    points = []
    for i in range(nx):
        column = fill[i]
        above = np.flatnonzero(column >= level)
        if above.size == 0:
            continue
        j = above[-1]  # topmost cell at or above the level
        if j + 1 >= ny:
            continue
        f0, f1 = column[j], column[j + 1]
        y = ys[j] + field.h * (f0 - level) / (f0 - f1)
        if field.radius - math.hypot(xs[i], y) < margin:
            continue
        points.append((xs[i], y))
    if len(points) < 3:
        raise ValueError(f"no free surface: fewer than 3 columns cross fill = {level}")
    return np.array(points)


def _normal_crossing(field: _Field2D, line: SurfaceLine, s: np.ndarray, level: float):
    """``n`` where the fill first reaches ``level`` going down the normal line at each s
    (NaN where it never does)."""
    h = field.h
    n = np.arange(_ABOVE * h, -2.0 * field.radius, -_NORMAL_STEP * h)
    px, py = line.point(s[:, None], n[None, :])
    fill = field.sample(field.fill, px, py)
    reached = fill >= level
    first = np.where(reached.any(axis=1), reached.argmax(axis=1), -1)
    out = np.full(s.shape, np.nan)
    for k, j in enumerate(first):
        if j <= 0:
            continue
        f0, f1 = fill[k, j - 1], fill[k, j]
        out[k] = n[j - 1] + (n[j] - n[j - 1]) * (level - f0) / (f1 - f0)
    return out


def _make_line(field, angle, offset, points, level, method) -> SurfaceLine:
    b = math.radians(angle)
    mx, my = -math.sin(b), math.cos(b)
    residuals = points @ np.array([mx, my]) - offset
    return SurfaceLine(
        angle_deg=float(angle),
        centre=(float(mx * offset), float(my * offset)),
        offset=float(offset),
        half_chord=float(math.sqrt(field.radius**2 - offset**2)),
        radius=field.radius,
        cell=field.h,
        level=float(level),
        points=points,
        residuals=residuals,
        method=method,
    )


def surface_line(
    flow: xr.Dataset,
    level: float = 0.5,
    *,
    method: str = "normal",
    fit_fraction: float = 0.8,
    wall_margin: float = 2.0,
    radius: float | None = None,
    phase: int = 0,
) -> SurfaceLine:
    """Find the free surface of a drum's bed and fit a straight line to it.

    The surface is where the fill crosses ``level`` on the way down from the empty part
    of the drum. ``method="column"`` finds the crossing down each column of cells (linear
    between cell centres) and fits by least squares. ``method="normal"`` (default) starts
    from that fit and, twice, finds the crossing along lines normal to the current line
    every half cell of its chord (bilinear fill), keeping the chord's middle
    ``|s| <= fit_fraction · L``, and refits. Both fits are total least squares (distances
    normal to the line). Crossings closer than ``wall_margin`` cells to the wall are left
    out: there the cells the wall cuts hold less material and the fill drops for a reason
    other than the surface.

    Parameters
    ----------
    flow : xarray.Dataset
        A 2-D drum flow in the lab frame.
    level : float
        Fill that marks the surface (0.5: half a cell of material).
    method : {"normal", "column"}
        How the crossings are found (above).
    fit_fraction : float
        Share of the half-chord, about the midpoint, over which the normal crossings are
        fitted (``method="normal"``).
    wall_margin : float
        Crossings nearer than this many cells to the wall are left out.
    radius : float, optional
        Drum radius in m (default: :func:`drum_radius`).
    phase : int
        Index of the phase to read when the flow stores several.

    Returns
    -------
    SurfaceLine
        Angle, chord midpoint, offset, half-chord, the crossing points and their
        residuals (``rms_residual``, ``max_residual`` measure flatness).

    Raises
    ------
    ValueError
        The flow is not a 2-D lab-frame flow, or no surface crosses the drum.
    """
    if method not in ("normal", "column"):
        raise ValueError(f"method must be 'normal' or 'column', got {method!r}")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    field = _field(flow, phase, radius)
    margin = wall_margin * field.h
    points = _column_crossings(field, level, margin)
    angle, offset = _line_from_points(points, field.radius)
    line = _make_line(field, angle, offset, points, level, "column")
    if method == "column":
        return line
    for _ in range(2):
        reach = fit_fraction * line.half_chord
        s = np.arange(-reach, reach + 1e-12, 0.5 * field.h)
        n = _normal_crossing(field, line, s, level)
        px, py = line.point(s, np.nan_to_num(n))
        keep = np.isfinite(n) & (field.radius - np.hypot(px, py) >= margin)
        if keep.sum() < 3:
            raise ValueError(f"no free surface: fewer than 3 normal lines cross fill = {level}")
        points = np.column_stack([px[keep], py[keep]])
        angle, offset = _line_from_points(points, field.radius)
        line = _make_line(field, angle, offset, points, level, "normal")
    return line


# ----------------------------------------------------------------------------- flux


def rolling_drum_flux(omega, half_chord, s):
    """Volume flux per unit depth through the flowing layer of a rolling drum.

    ``q(s) = ω (L² - s²) / 2`` for ``|s| <= L`` (0 beyond), DESIGN §7.

    Why it holds, whatever the rheology: in steady rolling the bed below the flowing
    layer turns rigidly with the drum, ``v = ω ẑ × r``, and the material's density is
    uniform. Take the line normal to the free surface through chord position s, from
    the wall (distance R from the axis) up to the surface (distance
    ``r_s = sqrt(s² + d²)``, d the chord's offset from the axis). Rigid rotation carries
    through a radial-like segment between distances r1 < r2 from the axis the flux
    ``∫ ω r dr = ω (r2² - r1²)/2`` (the stream function of rigid rotation is
    ``-ω r²/2``; the flux between two points depends only on their distances from the
    axis). Neither the wall nor the free surface lets material through, and the flow is
    steady, so the region under the chord between this line and the chord's lower end
    neither gains nor loses material: whatever the rigid bed carries up through the line
    must come back down through the same line in the flowing layer. As the layer's
    thickness goes to zero the rigid part spans the whole line, from R to r_s, and the
    flux the layer returns is ``ω (R² - s² - d²)/2 = ω (L² - s²)/2`` since
    ``L² = R² - d²``. Nothing about the layer's velocity profile enters: only mass
    conservation and the bed's rigid rotation.

    For a layer of finite depth δ that sits on a rigid bed the same argument gives
    ``ω (R² - r_b²)/2`` with r_b the distance of the layer's base from the axis,
    ``r_b² = s² + (d - δ)²``: ``ω (L² - s² + 2dδ - δ²)/2``, which is smaller than the
    thin-layer value by ``ω δ (δ - 2d)/2``, i.e. by a relative ``δ²/(L² - s²)`` in a
    half-full drum (d = 0) but ``2|d|δ/(L² - s²)`` to first order in a drum less than
    half full.

    Parameters
    ----------
    omega : float
        Angular speed of the drum, rad/s.
    half_chord : float
        Half-length L of the free surface's chord, m.
    s : float or array_like
        Chord coordinate from the chord's midpoint, m.

    Returns
    -------
    float or ndarray
        Flux in m²/s (volume per unit time per unit depth along the axis).
    """
    s = np.asarray(s, float)
    q = 0.5 * float(omega) * np.clip(float(half_chord) ** 2 - s * s, 0.0, None)
    return float(q) if q.ndim == 0 else q


def layer_flux(
    flow: xr.Dataset,
    s,
    *,
    surface: SurfaceLine | None = None,
    level: float = 0.5,
    radius: float | None = None,
    phase: int = 0,
) -> xr.Dataset:
    """Downslope volume flux per unit depth through the flowing layer at chord positions.

    Along the line normal to the surface line through chord position s, the downslope
    volume-flux density ``g(n) = -(fill v)·t`` is integrated from above the surface
    (where the fill is zero) down to the first depth below the surface where g turns
    negative, i.e. where the motion changes from the layer running downhill to the bed
    carried uphill. That depth is reported as the layer's thickness. The uphill flux
    below it, down to the wall, is integrated too: in a steady flow of material of
    uniform density both must be equal (no material crosses the wall or the surface),
    so their difference measures how far the averaged field is from mass balance.

    Parameters
    ----------
    flow : xarray.Dataset
        A 2-D drum flow in the lab frame.
    s : float or array_like
        Chord coordinates (m, from the chord's midpoint, uphill positive), within the
        half-chord.
    surface : SurfaceLine, optional
        The surface line (default: ``surface_line(flow, level)``).
    level : float
        Fill level marking the surface, when ``surface`` is not given.
    radius : float, optional
        Drum radius in m (default: :func:`drum_radius`).
    phase : int
        Index of the phase to read when the flow stores several.

    Returns
    -------
    xarray.Dataset
        On dimension ``s``: ``flux`` (downslope flux through the layer, m²/s),
        ``layer_depth`` (distance from the surface line to where the motion turns
        uphill, m; NaN and a NaN flux where it never does), ``upslope_flux`` (uphill
        flux from there to the wall, m²/s), ``wall_gap`` (distance along the line from
        the bed's outer edge, where the fill last reaches the surface's level, to the
        wall, m; about 0 for a bed that touches the wall), ``rigid_flux_below`` (what
        rigid rotation at ω carries between the bed's outer edge, at distance r_e from
        the axis, and the layer's base, ``ω (r_e² - r_b²)/2``, m²/s: the mass-balance
        prediction for the layer's flux with the bed as it is, see
        :func:`rolling_drum_flux`) and ``thin_layer_flux`` (:func:`rolling_drum_flux`
        at the surface line's half-chord). Attributes give the surface line.

    Notes
    -----
    The integrand is the fill times the velocity, i.e. a volume flux. It is a mass flux
    over the density only where the fill counts material at one packing (the built-in
    solver deposits the particles' seeded volumes, so its fill does); a fill that counted
    dilated volumes would make the layer's flux exceed the bed's by the dilation. The
    error of the measurement itself, on exact velocities, is about ``h / (2 δ)`` at worst
    (δ the layer's depth, h the cell): the cells the surface cuts.
    """
    field = _field(flow, phase, radius)
    line = surface if surface is not None else surface_line(flow, level, phase=phase)
    s_arr = np.atleast_1d(np.asarray(s, float))
    if np.any(np.abs(s_arr) >= line.half_chord):
        raise ValueError(
            f"s must lie within the half-chord (|s| < {line.half_chord:.4g} m), got "
            f"{s_arr[np.abs(s_arr) >= line.half_chord].tolist()}"
        )
    h = field.h
    tx, ty = line.tangent
    flux = np.full(s_arr.shape, np.nan)
    depth = np.full(s_arr.shape, np.nan)
    up = np.full(s_arr.shape, np.nan)
    rigid = np.full(s_arr.shape, np.nan)
    gap = np.full(s_arr.shape, np.nan)
    for k, sk in enumerate(s_arr):
        # past the wall by a cell and a half: the interpolated fields fall to zero only at
        # the centres of the empty cells beyond it, and the cells the wall cuts hold their
        # share of the material (their fill), so the integral keeps the cells' sum
        bottom = float(line.wall_depth(sk)) - _BEYOND_WALL * h
        n = np.arange(_ABOVE * h, bottom, -_NORMAL_STEP * h)
        px, py = line.point(sk, n)
        g = -(tx * field.sample(field.flux_x, px, py) + ty * field.sample(field.flux_y, px, py))
        # the first downhill-to-uphill change of sign below the surface line
        below = np.flatnonzero((n <= 0.0) & (g <= 0.0))
        if below.size == 0:
            continue
        j = below[0]
        if j == 0 or g[j - 1] <= 0.0:
            continue  # no downhill motion at the surface
        n0 = n[j - 1] + (n[j] - n[j - 1]) * g[j - 1] / (g[j - 1] - g[j])
        upper = np.append(n[:j], n0), np.append(g[:j], 0.0)
        lower = np.insert(n[j:], 0, n0), np.insert(g[j:], 0, 0.0)
        flux[k] = _integrate(*upper)
        up[k] = -_integrate(*lower)
        depth[k] = -n0
        # the bed's outer edge: the deepest point where the fill still reaches the level
        fill = field.sample(field.fill, px, py)
        inside = np.flatnonzero(fill >= line.level)
        i = inside[-1] if inside.size else -1
        if 0 <= i < n.size - 1:
            f0, f1 = fill[i], fill[i + 1]
            n_edge = n[i] + (n[i + 1] - n[i]) * (f0 - line.level) / (f0 - f1)
            gap[k] = n_edge - (bottom + _BEYOND_WALL * h)
            re2 = sk * sk + (line.offset + n_edge) ** 2
            rb2 = sk * sk + (line.offset + n0) ** 2
            rigid[k] = 0.5 * field.omega * (re2 - rb2)
    thin = rolling_drum_flux(field.omega, line.half_chord, s_arr)
    units = {"units": "m2 s-1"}
    return xr.Dataset(
        {
            "flux": ("s", flux, {**units, "long_name": "downslope flux through the layer"}),
            "layer_depth": ("s", depth, {"units": "m", "long_name": "depth of downslope motion"}),
            "upslope_flux": ("s", up, {**units, "long_name": "upslope flux below the layer"}),
            "rigid_flux_below": (
                "s",
                rigid,
                {**units, "long_name": "rigid-rotation flux between bed edge and layer base"},
            ),
            "wall_gap": ("s", gap, {"units": "m", "long_name": "bed edge to wall distance"}),
            "thin_layer_flux": (
                "s",
                np.atleast_1d(thin),
                {**units, "long_name": "omega (L^2 - s^2) / 2"},
            ),
        },
        coords={"s": ("s", s_arr, {"units": "m", "long_name": "chord coordinate, uphill"})},
        attrs=_line_attrs(line, field.omega),
    )


def _integrate(n: np.ndarray, g: np.ndarray) -> float:
    """Trapezoid rule for n running downwards (returns the integral over increasing n)."""
    return float(np.sum(0.5 * (g[1:] + g[:-1]) * (n[:-1] - n[1:])))


def _line_attrs(line: SurfaceLine, omega: float) -> dict:
    return {
        "angle_deg": line.angle_deg,
        "half_chord_m": line.half_chord,
        "offset_m": line.offset,
        "centre_m": list(line.centre),
        "radius_m": line.radius,
        "omega_rad_s": omega,
        "surface_level": line.level,
        "surface_rms_residual_m": line.rms_residual,
    }


# ----------------------------------------------------------------------------- surface speed


def surface_velocity(
    flow: xr.Dataset,
    *,
    surface: SurfaceLine | None = None,
    level: float = 0.5,
    s=None,
    depth: float = 0.0,
    wall_margin: float = 2.0,
    radius: float | None = None,
    phase: int = 0,
) -> xr.Dataset:
    """Downslope speed along the free surface.

    At each chord position the local surface is found along the normal line (where the
    fill reaches the surface's level, which may lie off the fitted line), and the
    velocity there (``depth`` below it) is the ratio of the interpolated volume-flux
    density and the interpolated fill: the fill-weighted velocity of the surrounding
    cells, which does not mix in the zero velocity of empty cells above.

    Parameters
    ----------
    flow : xarray.Dataset
        A 2-D drum flow in the lab frame.
    surface : SurfaceLine, optional
        The surface line (default: ``surface_line(flow, level)``).
    level : float
        Fill level marking the surface, when ``surface`` is not given.
    s : array_like, optional
        Chord positions (m). Default: every half cell within ``wall_margin`` cells of
        the chord's ends.
    depth : float
        Sample this far (m) below the local surface.
    wall_margin : float
        Cells left out at each end of the chord (default positions only).
    radius : float, optional
        Drum radius in m (default: :func:`drum_radius`).
    phase : int
        Index of the phase to read when the flow stores several.

    Returns
    -------
    xarray.Dataset
        On dimension ``s``: ``speed`` (downslope component, m/s, positive downhill),
        ``normal_speed`` (component along the outward normal, m/s) and ``surface_n``
        (the local surface's offset from the line, m); scalars ``max_speed`` (m/s) and
        ``s_at_max`` (m).
    """
    field = _field(flow, phase, radius)
    line = surface if surface is not None else surface_line(flow, level, phase=phase)
    h = field.h
    if s is None:
        reach = line.half_chord - wall_margin * h
        s_arr = np.arange(-reach, reach + 1e-12, 0.5 * h)
    else:
        s_arr = np.atleast_1d(np.asarray(s, float))
    n_surf = _normal_crossing(field, line, s_arr, line.level)
    px, py = line.point(s_arr, np.nan_to_num(n_surf) - depth)
    f = field.sample(field.fill, px, py)
    with np.errstate(invalid="ignore", divide="ignore"):
        vx = np.where(f > 0, field.sample(field.flux_x, px, py) / f, np.nan)
        vy = np.where(f > 0, field.sample(field.flux_y, px, py) / f, np.nan)
    vx = np.where(np.isfinite(n_surf), vx, np.nan)
    vy = np.where(np.isfinite(n_surf), vy, np.nan)
    (tx, ty), (mx, my) = line.tangent, line.normal
    speed = -(tx * vx + ty * vy)
    k = int(np.nanargmax(speed)) if np.isfinite(speed).any() else 0
    units = {"units": "m s-1"}
    return xr.Dataset(
        {
            "speed": ("s", speed, {**units, "long_name": "downslope speed at the surface"}),
            "normal_speed": ("s", mx * vx + my * vy, {**units, "long_name": "speed out of bed"}),
            "surface_n": ("s", n_surf, {"units": "m", "long_name": "local surface off the line"}),
            "max_speed": ((), float(speed[k]), {**units, "long_name": "largest downslope speed"}),
            "s_at_max": ((), float(s_arr[k]), {"units": "m", "long_name": "where it is largest"}),
        },
        coords={"s": ("s", s_arr, {"units": "m", "long_name": "chord coordinate, uphill"})},
        attrs={**_line_attrs(line, field.omega), "depth_m": float(depth)},
    )
