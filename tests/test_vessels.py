"""Vessel SDFs, volumes and the seeded bed against exact geometry.

Tolerances of lattice counts: a vessel and its filled part are convex, so their surface
S is at most that of their bounding box, and a lattice of spacing Δ miscounts at most
the sites of the cells the surface cuts, about one layer S·Δ of volume (S the perimeter
and Δ² per site in 2-D). Every such check uses S_box·Δ, which shrinks with Δ.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import blendxr as bx
from blendxr import vessels as vs
from blendxr.scene import Scene

# Default tote (DESIGN §7), in its body frame
W, HS, THETA, WO = 0.22, 0.227, math.radians(30.0), 0.05
HW, HS2, HO = W / 2, HS / 2, WO / 2
HH = (W - WO) / (2 * math.tan(THETA))
YB = -HS2 - HH

VESSELS = {
    "drum-2d": vs.Drum(0.15, ndim=2),
    "drum-3d": vs.Drum(0.2, ndim=3, length=0.1),
    "tote-2d": vs.Tote(ndim=2),
    "tote-3d": vs.Tote(),
    "tote-3d-tilted": vs.Tote(tilt_deg=20.0, axis_offset=0.03),
    "box-2d": vs.Box((0.2, 0.1), (0.01, -0.02)),
    "box-3d": vs.Box((0.2, 0.1, 0.3), (0.01, -0.02, 0.03)),
    "silo-2d": vs.Silo(
        (0.12, 0.3), (0.01, 0.1), orifice=0.03, floor_height=0.12, floor_thickness=0.01
    ),  # fmt: skip
    "silo-3d": vs.Silo(
        (0.12, 0.3, 0.05), (0.0, 0.0, 0.01), orifice=0.02, floor_height=0.1, floor_thickness=0.02
    ),  # fmt: skip
}
EXACT = ["drum-2d", "drum-3d", "box-2d", "box-3d"]
#: exact inside the vessel only
EXACT_INSIDE = ["tote-2d", "tote-3d", "tote-3d-tilted", "silo-2d", "silo-3d"]


def _random_points(vessel, n=400, margin=0.05, seed=1):
    lo, hi = vessel.bounds
    rng = np.random.default_rng(seed)
    return rng.uniform(lo - margin, hi + margin, size=(n, vessel.ndim))


def _fd_gradient(vessel, points, h=1e-6):
    """Central, forward and backward differences of the vectorised SDF."""
    f0 = vessel.sdf(points)
    central, forward, backward = (np.empty_like(points) for _ in range(3))
    for a in range(vessel.ndim):
        e = np.zeros(vessel.ndim)
        e[a] = h
        fp, fm = vessel.sdf(points + e), vessel.sdf(points - e)
        central[:, a] = (fp - fm) / (2 * h)
        forward[:, a] = (fp - f0) / h
        backward[:, a] = (f0 - fm) / h
    return central, forward, backward


def _lattice(vessel, spacing):
    lo, hi = vessel.bounds
    axes = [np.arange(a + spacing / 2, b, spacing) for a, b in zip(lo, hi, strict=True)]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grids], axis=-1)


def _box_surface(vessel):
    edges = np.subtract(*vessel.bounds[::-1])
    if vessel.ndim == 2:
        return 2 * edges.sum()
    return 2 * (edges[0] * edges[1] + edges[1] * edges[2] + edges[0] * edges[2])


def _segment_distance(p, a, b):
    ab, ap = b - a, p - a
    t = np.clip(ap @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + np.outer(t, ab)), axis=-1)


# ---------------------------------------------------------------------------------------
# SDF values
# ---------------------------------------------------------------------------------------


def test_drum_sdf_exact_values():
    drum = VESSELS["drum-2d"]
    pts = [[0, 0], [0.075, 0], [0, -0.075], [0.06, 0.08], [-0.03, 0.04]]
    np.testing.assert_allclose(drum.sdf(pts), [-0.075, 0, 0, 0.025, -0.025], atol=1e-15)
    cyl = VESSELS["drum-3d"]  # R = 0.1, L/2 = 0.05
    pts = [
        [0, 0, 0],  # nearer the end walls
        [0.1, 0, 0.01],  # on the mantle
        [0.02, 0.0, 0.05],  # on the end wall
        [0, 0.09, 0.0],  # nearer the mantle
        [0.0, 0.13, 0.0],  # outside the mantle
        [0.0, 0.0, 0.08],  # outside the end wall
        [0.0, 0.13, 0.09],  # beyond the rim: distance to the rim circle
    ]
    np.testing.assert_allclose(cyl.sdf(pts), [-0.05, 0, 0, -0.01, 0.03, 0.03, 0.05], atol=1e-15)


def test_box_sdf_exact_values():
    box = VESSELS["box-3d"]  # centre (0.01, -0.02, 0.03), half edges (0.1, 0.05, 0.15)
    c = np.array(box.center)
    pts = c + np.array(
        [[0, 0, 0], [0.1, 0, 0], [0, 0.06, 0], [0.13, 0.09, 0], [0.13, 0.09, 0.27], [0, 0.04, 0]]
    )
    np.testing.assert_allclose(box.sdf(pts), [-0.05, 0, 0.01, 0.05, 0.13, -0.01], atol=1e-15)
    flat = VESSELS["box-2d"]
    pts = np.array(flat.center) + np.array([[0, 0], [-0.1, 0.01], [-0.13, -0.09]])
    np.testing.assert_allclose(flat.sdf(pts), [-0.05, 0, 0.05], atol=1e-15)


def _rectangle_distance(p, lo, hi):
    """Euclidean distance from points p (N, 2) to the solid rectangle [lo, hi]."""
    gap = np.maximum(np.maximum(lo - p, p - hi), 0.0)
    return np.linalg.norm(gap, axis=-1)


@pytest.mark.parametrize("name", ["silo-2d", "silo-3d"])
def test_silo_sdf_is_the_distance_to_the_nearest_wall_inside(name):
    """Inside, -sdf is the distance to the nearest of the outer walls and the two halves of
    the floor, computed here from the geometry directly."""
    silo = VESSELS[name]
    pts = _random_points(silo, n=6000, margin=0.0, seed=4)
    lo, hi = (np.asarray(b) for b in silo.bounds)
    d = silo.sdf(pts)
    xy = pts[:, :2]
    top, bottom = silo.floor_top, silo.floor_top - silo.floor_thickness
    cx, half = silo.center[0], silo.orifice / 2
    left = _rectangle_distance(xy, np.array([lo[0], bottom]), np.array([cx - half, top]))
    right = _rectangle_distance(xy, np.array([cx + half, bottom]), np.array([hi[0], top]))
    walls = np.min(np.concatenate([pts - lo, hi - pts], axis=1), axis=1)
    in_plate = (left == 0) | (right == 0)
    inside = ~in_plate & np.all((pts > lo) & (pts < hi), axis=1)
    assert 0.5 < inside.mean() < 1.0
    np.testing.assert_array_equal(d < 0, inside)
    truth = np.minimum(walls, np.minimum(left, right))
    np.testing.assert_allclose(-d[inside], truth[inside], atol=1e-15)


def test_silo_sdf_exact_values():
    # x in [-0.05, 0.07], the floor y in [0.06, 0.07], the slot |x - 0.01| < 0.015
    silo = VESSELS["silo-2d"]
    pts = np.array([[0.015, 0.065], [0.0, 0.065], [-0.03, 0.065], [-0.03, 0.08], [0.01, 0.09]])
    want = [-0.01, -0.005, 0.005, -0.01, -np.hypot(0.015, 0.02)]
    np.testing.assert_allclose(silo.sdf(pts), want, atol=1e-15)
    np.testing.assert_allclose(silo.normal(pts[:2]), [[1.0, 0.0], [-1.0, 0.0]], atol=1e-15)


def test_tote_sdf_values_in_the_body_frame():
    tote = VESSELS["tote-3d"]
    n_hopper = np.array([math.cos(THETA), -math.sin(THETA), 0.0])
    mid_wall = np.array([(HO + HW) / 2, (YB - HS2) / 2, 0.0])  # middle of a hopper face
    pts = [
        [0, 0, 0],  # centre: the side walls are the nearest (0.11 < 0.1135)
        [0, HS2, 0],  # on the lid
        [0, HS2 + 0.01, 0.02],  # above the lid
        [0.02, YB, -0.01],  # on the outlet
        [0, 0, HW + 0.02],  # beside a z wall
        mid_wall,
        mid_wall + 0.01 * n_hopper,  # outside, the face's foot point is inside the face
        mid_wall - 0.01 * n_hopper,
    ]
    np.testing.assert_allclose(tote.sdf(pts), [-HW, 0, 0.01, 0, 0.02, 0, 0.01, -0.01], atol=1e-15)
    np.testing.assert_allclose(tote.normal(mid_wall + 0.01 * n_hopper), n_hopper, atol=1e-15)


def _tote_polygon_distance(points):
    corners = np.array([(-HW, HS2), (HW, HS2), (HW, -HS2), (HO, YB), (-HO, YB), (-HW, -HS2)])
    edges = zip(corners, np.roll(corners, -1, axis=0), strict=True)
    return np.min([_segment_distance(points, a, b) for a, b in edges], axis=0)


def test_2d_tote_is_exact_inside_and_a_lower_bound_outside():
    tote = VESSELS["tote-2d"]
    pts = _random_points(tote, n=4000, margin=0.1)
    d, truth = tote.sdf(pts), _tote_polygon_distance(pts)
    inside = d < 0
    assert 0.2 < inside.mean() < 0.9
    np.testing.assert_allclose(-d[inside], truth[inside], atol=1e-15)
    assert np.all(d[~inside] <= truth[~inside] + 1e-15)
    # beyond the lid corner the bound is the larger of the two face distances
    corner = np.array([[HW + 0.03, HS2 + 0.04]])
    assert tote.sdf(corner)[0] == pytest.approx(0.04)
    assert _tote_polygon_distance(corner)[0] == pytest.approx(0.05)


@pytest.mark.parametrize("name", VESSELS)
def test_compiled_point_functions_match_the_vectorised_sdf(name):
    vessel = VESSELS[name]
    pts = _random_points(vessel)
    kind, params = vessel.kind, vessel.params
    out = np.empty(3)
    d_point, d_normal, normals = [], [], []
    for p in pts:
        z = float(p[2]) if vessel.ndim == 3 else 0.0
        d_point.append(vs.sdf_point(kind, params, float(p[0]), float(p[1]), z))
        d_normal.append(vs.sdf_normal(kind, params, float(p[0]), float(p[1]), z, out))
        normals.append(out.copy())
    np.testing.assert_array_equal(d_point, vessel.sdf(pts))
    np.testing.assert_array_equal(d_normal, d_point)
    normals = np.array(normals)
    np.testing.assert_array_equal(normals[:, : vessel.ndim], vessel.normal(pts))
    if vessel.ndim == 2:
        assert np.all(normals[:, 2] == 0.0)
        # z is ignored by 2-D kinds
        assert vs.sdf_point(kind, params, 0.01, 0.02, 5.0) == vs.sdf_point(
            kind, params, 0.01, 0.02, 0.0
        )
    assert vessel.contains(pts).tolist() == (vessel.sdf(pts) < 0).tolist()


def test_unknown_kind_gives_nan():
    assert math.isnan(vs.sdf_point(99, np.zeros(9), 0.0, 0.0, 0.0))


@pytest.mark.parametrize("name", VESSELS)
def test_normals_are_unit_and_equal_the_finite_difference_gradient(name):
    vessel = VESSELS[name]
    pts = _random_points(vessel, n=1000, seed=2)
    normals = vessel.normal(pts)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=-1), 1.0, atol=1e-12)
    central, forward, backward = _fd_gradient(vessel, pts)
    # away from edges and ridges the one-sided differences agree
    smooth = np.all(np.abs(forward - backward) < 1e-4, axis=-1)
    assert smooth.mean() > 0.95
    np.testing.assert_allclose(normals[smooth], central[smooth], atol=1e-5)
    # |grad sdf| = 1 wherever it is smooth (every face plane of a tote is a unit-slope SDF)
    np.testing.assert_allclose(np.linalg.norm(central[smooth], axis=-1), 1.0, atol=1e-5)


@pytest.mark.parametrize("name", EXACT + EXACT_INSIDE)
def test_stepping_back_along_the_normal_lands_on_the_wall(name):
    """The defining property of an exact SDF: p − sdf(p)·n(p) is on the wall."""
    vessel = VESSELS[name]
    pts = _random_points(vessel, n=1000, seed=3)
    if name in EXACT_INSIDE:
        pts = pts[vessel.sdf(pts) < 0]
    foot = pts - vessel.sdf(pts)[:, None] * vessel.normal(pts)
    np.testing.assert_allclose(vessel.sdf(foot), 0.0, atol=1e-12)


# ---------------------------------------------------------------------------------------
# Volumes
# ---------------------------------------------------------------------------------------


def test_volumes_against_formulas():
    tote = VESSELS["tote-3d"]
    frustum = HH / 3 * (W**2 + WO**2 + W * WO)
    assert tote.volume == pytest.approx(W * W * HS + frustum, rel=1e-14)
    assert round(tote.volume * 1e3, 1) == 14.0  # litres, DESIGN §7
    assert tote.height == pytest.approx(0.374, abs=5e-4)
    assert VESSELS["tote-2d"].volume == pytest.approx(W * HS + (W + WO) / 2 * HH, rel=1e-14)
    assert VESSELS["drum-2d"].volume == pytest.approx(math.pi * 0.075**2, rel=1e-14)
    assert VESSELS["drum-3d"].volume == pytest.approx(math.pi * 0.1**2 * 0.1, rel=1e-14)
    assert VESSELS["box-3d"].volume == pytest.approx(0.2 * 0.1 * 0.3, rel=1e-14)
    plate = (0.12 - 0.03) * 0.01
    assert VESSELS["silo-2d"].volume == pytest.approx(0.12 * 0.3 - plate, rel=1e-14)
    assert vs.volume_below(VESSELS["silo-2d"], 0.065) == pytest.approx(
        0.12 * 0.115 - (0.12 - 0.03) * 0.005, rel=1e-14
    )
    # a rigid motion keeps the volume
    assert VESSELS["tote-3d-tilted"].volume == pytest.approx(tote.volume, rel=1e-14)


@pytest.mark.parametrize("name", VESSELS)
def test_lattice_count_agrees_with_the_volume(name):
    vessel = VESSELS[name]
    spacing = 0.002 if vessel.ndim == 3 else 0.0005
    pts = _lattice(vessel, spacing)
    counted = np.count_nonzero(vessel.sdf(pts) < 0) * spacing**vessel.ndim
    assert abs(counted - vessel.volume) <= _box_surface(vessel) * spacing


@pytest.mark.parametrize("name", VESSELS)
def test_volume_below_runs_from_zero_to_the_volume(name):
    vessel = VESSELS[name]
    lo, hi = vessel.bounds
    ys = np.linspace(lo[1] - 0.01, hi[1] + 0.01, 201)
    below = vs.volume_below(vessel, ys)
    assert np.all(np.diff(below) >= -1e-17)
    within = (ys[1:] > lo[1]) & (ys[:-1] < hi[1])
    assert np.all(np.diff(below)[within] > 0)  # strictly rising inside the vessel
    assert vs.volume_below(vessel, lo[1]) == pytest.approx(0.0, abs=1e-18)
    assert vs.volume_below(vessel, hi[1]) == pytest.approx(vessel.volume, rel=1e-12)
    assert below[0] == 0.0 and below[-1] == pytest.approx(vessel.volume, rel=1e-12)


def test_volume_below_exact_values():
    r = 0.075
    drum = VESSELS["drum-2d"]
    assert vs.volume_below(drum, 0.0) == pytest.approx(math.pi * r * r / 2, rel=1e-14)
    # segment of height r/2: r²(π/3) − (r/2)·(√3 r/2)
    seg = r * r * (math.pi / 3 - math.sqrt(3) / 4)
    assert vs.volume_below(drum, -r / 2) == pytest.approx(seg, rel=1e-12)
    assert vs.volume_below(VESSELS["drum-3d"], 0.0) == pytest.approx(math.pi * 0.01 * 0.1 / 2)
    tote = VESSELS["tote-3d"]
    frustum = HH / 3 * (W**2 + WO**2 + W * WO)
    assert vs.volume_below(tote, -HS2) == pytest.approx(frustum, rel=1e-13)
    assert vs.volume_below(tote, 0.0) == pytest.approx(frustum + W * W * HS2, rel=1e-13)
    # half-way down the hopper: a frustum from the outlet to width w_o + 2 tanθ (HH/2)
    mid = WO + math.tan(THETA) * HH
    part = HH / 6 * (mid**2 + WO**2 + mid * WO)
    assert vs.volume_below(tote, YB + HH / 2) == pytest.approx(part, rel=1e-13)
    flat = VESSELS["tote-2d"]
    assert vs.volume_below(flat, YB + HH / 2) == pytest.approx((mid + WO) / 2 * HH / 2)
    box = VESSELS["box-2d"]
    assert vs.volume_below(box, -0.02) == pytest.approx(0.2 * 0.05, rel=1e-14)


def test_tilted_tote_volume_below_against_a_lattice_and_its_mirror_image():
    tilted = VESSELS["tote-3d-tilted"]
    mirror = vs.Tote(tilt_deg=-20.0, axis_offset=0.03)
    spacing = 0.002
    pts = _lattice(tilted, spacing)
    inside = pts[tilted.sdf(pts) < 0]
    for y in (-0.2, -0.1, 0.0, 0.08):
        exact = vs.volume_below(tilted, y)
        counted = np.count_nonzero(inside[:, 1] < y) * spacing**3
        assert abs(counted - exact) <= _box_surface(tilted) * spacing
        assert vs.volume_below(mirror, y) == pytest.approx(exact, rel=1e-12)
    # the quadrature is exact: at tilt 0 it reproduces the box-and-frustum sums
    assert vs.volume_below(vs.Tote(tilt_deg=1e-12), -HS2) == pytest.approx(
        HH / 3 * (W**2 + WO**2 + W * WO), rel=1e-9
    )


@pytest.mark.parametrize("name", VESSELS)
@pytest.mark.parametrize("fraction", [0.05, 0.32, 0.4, 0.6, 1.0])
def test_fill_level_reproduces_the_fraction(name, fraction):
    vessel = VESSELS[name]
    y = vs.fill_level(vessel, fraction)
    assert vs.volume_below(vessel, y) == pytest.approx(fraction * vessel.volume, rel=1e-10)


def test_fill_level_exact_values():
    assert vs.fill_level(VESSELS["drum-2d"], 0.5) == pytest.approx(0.0, abs=1e-12)
    tote = VESSELS["tote-3d"]
    frustum = HH / 3 * (W**2 + WO**2 + W * WO)
    assert vs.fill_level(tote, frustum / tote.volume) == pytest.approx(-HS2, abs=1e-12)
    with pytest.raises(ValueError, match="fraction"):
        vs.fill_level(tote, 1.5)


# ---------------------------------------------------------------------------------------
# Axis offset and tilt
# ---------------------------------------------------------------------------------------


def test_axis_offset_moves_the_tote_down():
    a = 0.04
    upright, moved = vs.Tote(), vs.Tote(axis_offset=a)
    np.testing.assert_allclose(moved.bounds[0], upright.bounds[0] - [0, a, 0], atol=1e-15)
    np.testing.assert_allclose(moved.bounds[1], upright.bounds[1] - [0, a, 0], atol=1e-15)
    assert upright.bounds[0][1] == pytest.approx(YB)
    pts = _random_points(upright, seed=4)
    np.testing.assert_allclose(moved.sdf(pts - [0, a, 0]), upright.sdf(pts), atol=1e-15)
    assert vs.volume_below(moved, -a) == pytest.approx(vs.volume_below(upright, 0.0))


def test_tilt_turns_the_symmetry_axis_towards_z():
    t, a = math.radians(25.0), 0.03
    tote = vs.Tote(tilt_deg=25.0, axis_offset=a)
    axis = np.array([0.0, math.cos(t), math.sin(t)])
    lid_centre = (HS2 - a) * axis
    outlet_centre = (YB - a) * axis
    for p, n in ((lid_centre, axis), (outlet_centre, -axis)):
        np.testing.assert_allclose(tote.sdf([p, p + 0.01 * n, p - 0.01 * n]), [0, 0.01, -0.01])
        np.testing.assert_allclose(tote.normal(p + 0.01 * n), n, atol=1e-15)
    # the x walls do not move; the lowest point is an outlet corner at -z
    assert tote.sdf([HW, 0.0, 0.0]) == pytest.approx(0.0, abs=1e-15)
    lowest = (YB - a) * math.cos(t) - HO * math.sin(t)
    assert tote.bounds[0][1] == pytest.approx(lowest)
    # the SDF is that of the upright tote at the point turned back about x
    upright = vs.Tote(axis_offset=a)
    pts = _random_points(tote, seed=5)
    back = pts.copy()
    back[:, 1] = math.cos(t) * pts[:, 1] + math.sin(t) * pts[:, 2]
    back[:, 2] = -math.sin(t) * pts[:, 1] + math.cos(t) * pts[:, 2]
    np.testing.assert_allclose(tote.sdf(pts), upright.sdf(back), atol=1e-15)


# ---------------------------------------------------------------------------------------
# Validation and scenes
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "make, key",
    [
        (lambda: vs.Drum(-0.1), "diameter"),
        (lambda: vs.Drum(0.1, ndim=3), "length"),
        (lambda: vs.Drum(0.1, ndim=3, length=0.0), "length"),
        (lambda: vs.Drum(0.1, ndim=4), "ndim"),
        (lambda: vs.Tote(width=0.0), "width"),
        (lambda: vs.Tote(straight_height=-1.0), "straight_height"),
        (lambda: vs.Tote(hopper_angle_deg=90.0), "hopper_angle_deg"),
        (lambda: vs.Tote(hopper_angle_deg=0.0), "hopper_angle_deg"),
        (lambda: vs.Tote(outlet_width=0.3), "outlet_width"),
        (lambda: vs.Tote(outlet_width=-0.01), "outlet_width"),
        (lambda: vs.Tote(tilt_deg=90.0), "tilt_deg"),
        (lambda: vs.Tote(ndim=2, tilt_deg=5.0), "tilt_deg"),
        (lambda: vs.Tote(axis_offset=math.nan), "axis_offset"),
        (lambda: vs.Box((0.1, 0.0)), "size"),
        (lambda: vs.Box((0.1,)), "size"),
        (lambda: vs.Box((0.1, 0.2), (0.0, 0.0, 0.0)), "center"),
        (
            lambda: vs.Silo((0.1, 0.2), orifice=0.1, floor_height=0.1, floor_thickness=0.01),
            "orifice",
        ),
        (
            lambda: vs.Silo((0.1, 0.2), orifice=0.02, floor_height=0.2, floor_thickness=0.01),
            "floor_height",
        ),
        (
            lambda: vs.Silo((0.1, 0.2), orifice=0.02, floor_height=0.1, floor_thickness=0.0),
            "floor_thickness",
        ),
    ],
)
def test_bad_dimensions_raise_naming_the_parameter(make, key):
    with pytest.raises(ValueError, match=key):
        make()


def test_describe_names_kind_and_size():
    assert "tote" in VESSELS["tote-3d"].describe() and "14.02 L" in VESSELS["tote-3d"].describe()
    assert "150 mm" in VESSELS["drum-2d"].describe()
    assert "box" in VESSELS["box-2d"].describe()
    assert "30 mm slot" in VESSELS["silo-2d"].describe()


def _scene(vessel, **sections):
    return Scene({"name": "t", "vessel": vessel, **sections})


def test_vessels_from_scenes():
    drum = vs.vessel_from_scene(bx.load_scene("drum-2d"))
    assert drum == vs.Drum(0.15, ndim=2, length=0.05) and drum.kind == vs.DRUM_2D
    cyl = vs.vessel_from_scene(_scene({"kind": "drum", "ndim": 3, "diameter": 0.2, "width": 0.1}))
    assert cyl.length == 0.1 and cyl.kind == vs.DRUM_3D
    cyl = vs.vessel_from_scene({"kind": "drum", "ndim": 3, "diameter": 0.2, "length": 0.3})
    assert cyl.length == 0.3
    tote = vs.vessel_from_scene(_scene({"kind": "tote"}))
    assert tote == vs.Tote() and tote.kind == vs.TOTE_3D
    tote = vs.vessel_from_scene(_scene({"kind": "tote", "ndim": 2, "axis_offset": 0.02}))
    assert tote == vs.Tote(ndim=2, axis_offset=0.02) and tote.kind == vs.TOTE_2D
    box = vs.vessel_from_scene(_scene({"kind": "box", "ndim": 2, "size": [0.2, 0.1]}))
    assert box == vs.Box((0.2, 0.1)) and box.kind == vs.BOX_2D
    silo = {"kind": "silo", "ndim": 2, "size": [0.12, 0.3], "center": [0.01, 0.1],
            "orifice": 0.03, "floor_height": 0.12, "floor_thickness": 0.01}  # fmt: skip
    assert vs.vessel_from_scene(_scene(silo)) == VESSELS["silo-2d"]
    assert vs.vessel_from_scene(_scene(silo)).kind == vs.SILO_2D


@pytest.mark.parametrize(
    "section, key",
    [
        ({"kind": "drum", "ndim": 3, "diameter": 0.2}, "length"),
        ({"kind": "drum", "ndim": 2}, "diameter"),
        ({"kind": "box", "ndim": 2}, "size"),
        ({"kind": "box", "ndim": 3, "size": [0.2, 0.1]}, "size"),
        ({"kind": "box", "ndim": 2, "size": [0.2, 0.1], "center": [0.0]}, "center"),
        ({"kind": "tote", "ndim": 2, "tilt_deg": 10.0}, "tilt_deg"),
        ({"kind": "tote", "outlet_width": 0.5}, "outlet_width"),
        (
            {
                "kind": "silo",
                "ndim": 2,
                "size": [0.2, 0.1],
                "floor_height": 0.05,
                "floor_thickness": 0.01,
            },
            "orifice",
        ),  # fmt: skip
        ({"kind": "cone"}, "kind"),
    ],
)
def test_bad_scene_vessels_raise_naming_the_key(section, key):
    with pytest.raises(ValueError, match=key):
        vs.vessel_from_scene({"vessel": section})


# ---------------------------------------------------------------------------------------
# Seeding the bed
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("cell", [0.01, 0.005])
def test_seeded_drum_bed_has_the_filled_volume(cell):
    drum = VESSELS["drum-2d"]
    pos, vp = vs.seed_particles(drum, cell, per_cell=2, fraction=0.32)
    spacing = cell / 2
    assert vp == spacing**2
    exact = 0.32 * drum.volume
    assert abs(len(pos) * vp - exact) <= 2 * (2 * 0.15) * spacing  # box perimeter × Δ
    assert np.all(drum.sdf(pos) < 0)
    assert pos[:, 1].max() < vs.fill_level(drum, 0.32)


def test_seeded_tote_bed_has_the_filled_volume():
    tote = VESSELS["tote-3d-tilted"]
    cell = 0.005
    pos, vp = vs.seed_particles(tote, cell, per_cell=2, fraction=0.4)
    assert abs(len(pos) * vp - 0.4 * tote.volume) <= _box_surface(tote) * cell / 2
    assert np.all(tote.sdf(pos) < 0)


def test_particles_sit_on_the_sub_cell_centres():
    cell, per_cell = 0.01, 3
    pos, _ = vs.seed_particles(VESSELS["tote-3d"], cell, per_cell=per_cell, fraction=0.3)
    sub = pos / cell * per_cell - 0.5  # integers on the lattice
    np.testing.assert_allclose(sub, np.round(sub), atol=1e-9)


def test_box_region_in_a_box_vessel_is_counted_exactly():
    vessel = vs.Box((0.2, 0.1))
    pos, vp = vs.seed_particles(vessel, 0.01, box=[[-0.05, 0.05], [-0.05, 0.0]])
    assert len(pos) == 20 * 10 and vp == pytest.approx(0.005**2)
    assert pos[:, 0].min() > -0.05 and pos[:, 1].max() < 0.0


def test_box_intersects_the_fraction_and_the_vessel():
    drum = VESSELS["drum-2d"]
    half, vp = vs.seed_particles(drum, 0.002, fraction=0.5)
    quarter, _ = vs.seed_particles(drum, 0.002, fraction=0.5, box=[[0.0, 1.0], [-1.0, 1.0]])
    assert np.all(quarter[:, 0] >= 0) and np.all(quarter[:, 1] < 0)
    assert len(quarter) == np.count_nonzero(half[:, 0] >= 0)
    assert len(quarter) * vp == pytest.approx(drum.volume / 4, abs=2 * 0.15 * 0.001)


def test_depth_fills_from_the_lowest_point():
    tote = vs.Tote(axis_offset=0.05)
    depth = HH  # exactly the hopper
    pos, vp = vs.seed_particles(tote, 0.005, depth=depth)
    frustum = HH / 3 * (W**2 + WO**2 + W * WO)
    assert pos[:, 1].max() < tote.bounds[0][1] + depth
    assert abs(len(pos) * vp - frustum) <= _box_surface(tote) * 0.0025


def test_jitter_keeps_the_count_and_stays_inside():
    drum = VESSELS["drum-2d"]
    base, _ = vs.seed_particles(drum, 0.005, fraction=0.4)
    moved, _ = vs.seed_particles(drum, 0.005, fraction=0.4, jitter=1.0, seed=7)
    again, _ = vs.seed_particles(drum, 0.005, fraction=0.4, jitter=1.0, seed=7)
    assert moved.shape == base.shape
    np.testing.assert_array_equal(moved, again)
    assert np.all(np.abs(moved - base) <= 0.5 * 0.0025 + 1e-15)
    assert np.any(moved != base)
    assert np.all(drum.sdf(moved) < 0) and moved[:, 1].max() < vs.fill_level(drum, 0.4)


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({}, "fraction"),
        ({"fraction": 0.3, "depth": 0.1}, "depth"),
        ({"fraction": 0.0}, "fraction"),
        ({"depth": -0.1}, "depth"),
        ({"box": [[0.0, 1.0]]}, "box"),
        ({"box": [[0.1, 0.0], [0.0, 1.0]]}, "box"),
        ({"fraction": 0.3, "jitter": 2.0}, "jitter"),
        ({"fraction": 0.3, "per_cell": 0}, "per_cell"),
    ],
)
def test_bad_fill_raises_naming_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        vs.seed_particles(VESSELS["drum-2d"], 0.01, **kwargs)


def test_fill_from_scene_reads_fill_and_solver():
    scene = _scene(
        {"kind": "drum", "ndim": 2, "diameter": 0.15},
        fill={"fraction": 0.32},
        solver={"particles_per_cell": 3, "seed": 4},
    )
    vessel = vs.vessel_from_scene(scene)
    pos, vp = vs.fill_from_scene(vessel, scene, 0.01, jitter=0.5)
    want, want_vp = vs.seed_particles(vessel, 0.01, per_cell=3, fraction=0.32, jitter=0.5, seed=4)
    np.testing.assert_array_equal(pos, want)
    assert vp == want_vp
    with pytest.raises(ValueError, match="fill"):
        vs.fill_from_scene(vessel, bx.load_scene("drum-2d"), 0.01)


def test_tote_normals_keep_the_mirror_symmetry_where_faces_tie():
    # points on the diagonals of the corner edges (x = +-z), as a grid makes them: the
    # coordinates carry last-bit errors that must not pick different faces on the two
    # sides of the plane z = 0
    tote = vs.Tote(ndim=3)
    h = 0.02
    k = np.arange(-9, 10)
    axes = [-0.18 + h * (k + 9), -0.34 + h * np.arange(30), -0.18 + h * (k + 9)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    image = nodes * [1.0, 1.0, -1.0]
    normal, normal_image = tote.normal(nodes), tote.normal(image) * [1.0, 1.0, -1.0]
    np.testing.assert_allclose(tote.sdf(nodes), tote.sdf(image), rtol=0, atol=1e-15)
    # except on the axis of the straight section, where all four side walls tie and any
    # one serves (the normal is undefined there, far from every wall)
    axis = (nodes[..., 0] == 0.0) & (nodes[..., 2] == 0.0) & (np.abs(nodes[..., 1]) < 0.1)
    np.testing.assert_allclose(normal[~axis], normal_image[~axis], rtol=0, atol=1e-12)
    # on a tie the normal is the mean of the tied faces': x = z = 0.16 outside the
    # vertical corner edge, 0.05 from both side walls
    np.testing.assert_allclose(
        tote.normal(np.array([0.16, 0.0, 0.16])), [0.5**0.5, 0.0, 0.5**0.5], atol=1e-15
    )
