"""A rolling drum: the drum diagnostics on exact flows, then the built-in solver's drum.

The diagnostics (`blendxr.flow.diagnostics`) are first checked on the kinematic
`rolling_drum` flow, whose surface, layer and flux are known exactly, so that they are
validated independently of the solver. Then one small run of the solver (2-D drum,
150 mm, half full, 10 rpm, cohesionless, 5 mm cells, E / 100) is checked against the
rolling-drum facts of DESIGN §7: the surface sits flat at the dynamic angle, which for
a cohesionless Mohr-Coulomb material is about the friction angle, and the flowing layer
returns what the rigid bed under it carries up.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from blendxr.flow.analytic import _drum_section, rolling_drum
from blendxr.flow.diagnostics import (
    drum_radius,
    layer_flux,
    rolling_drum_flux,
    surface_line,
    surface_velocity,
)
from blendxr.flow.solver import solve_flow

RADIUS = 0.075
RPM = 10.0
OMEGA = 2.0 * math.pi * RPM / 60.0
PHI_DEG = 27.1  # paper Table 1
LAYER = 0.15  # rolling_drum's layer thickness at mid-chord, as a fraction of L
S_MID = np.array([-0.4, -0.2, 0.0, 0.2, 0.4])  # chord positions, fractions of L


def analytic(cells, fill_depth=0.5, angle_deg=PHI_DEG, exact_velocity=False):
    """rolling_drum and its section; optionally the exact velocity at the cell centres
    instead of the stream function's central differences."""
    kw = {"radius": RADIUS, "rpm": RPM, "fill_depth": fill_depth, "angle_deg": angle_deg}
    flow = rolling_drum(cells=cells, layer_fraction=LAYER, **kw)
    section = _drum_section(RADIUS, RPM, fill_depth, angle_deg, LAYER)
    if exact_velocity:
        x, y = np.meshgrid(flow["x"].values, flow["y"].values, indexing="ij")
        u, v = section.velocity(x, y)
        has = flow["fill"].values[0] > 0
        flow["vx"].values[0] = np.where(has, u, 0.0)
        flow["vy"].values[0] = np.where(has, v, 0.0)
    return flow, section


def exact_layer_flux(section, s):
    """Downslope flux through the layer: the largest ψ on the normal line less ψ_s.

    ``u·t = ∂ψ/∂n``, so the flux from the surface down to where ``u·t`` changes sign is
    ψ there (its maximum along the line) less the surface's ψ. Sampled on 20001 points
    across 1.5 layer depths: exact to about 1e-8 relative.
    """
    (tx, ty), (mx, my) = section.tangent, section.normal
    n = np.linspace(-1.5 * section.layer, 0.0, 20001)
    out = []
    for sk in np.atleast_1d(s):
        a = n + section.offset
        psi = section.stream_function(tx * sk + mx * a, ty * sk + my * a)
        out.append(psi.max() - section.surface_stream_function)
    return np.array(out)


# ----------------------------------------------------------------------------- analytic


@pytest.mark.parametrize("fill_depth", [0.5, 0.32])
@pytest.mark.parametrize("angle_deg", [27.1, 40.0])
@pytest.mark.parametrize("method", ["normal", "column"])
def test_surface_line_recovers_the_analytic_surface(fill_depth, angle_deg, method):
    flow, section = analytic(64, fill_depth, angle_deg)
    h = float(flow.x[1] - flow.x[0])
    line = surface_line(flow, method=method)
    # The fill of a cell a straight line cuts is its exact area fraction, 0.5 when the
    # line passes through the centre; in between, the interpolated fill's 0.5 contour
    # strays from the line where a cell's area fraction is not linear in the line's
    # offset (near its corners): 0.08 h at most here. h/4 is well below the residual of
    # a surface curved by a cell.
    assert line.max_residual < 0.25 * h
    assert line.rms_residual < 0.1 * h
    assert line.angle_deg == pytest.approx(angle_deg, abs=math.degrees(0.1 * h / RADIUS))
    assert line.offset == pytest.approx(section.offset, abs=0.1 * h)
    assert line.half_chord == pytest.approx(section.half_chord, abs=0.1 * h)
    # chord midpoint: the foot of the perpendicular from the axis
    mx, my = section.normal
    assert line.centre == pytest.approx((mx * section.offset, my * section.offset), abs=0.1 * h)


def test_rolling_drum_flux_is_what_rigid_rotation_carries_under_the_chord():
    # rigid rotation carries ω r dr through a line element at distance r from the axis
    # (the stream function is -ω r²/2); from the wall up to the surface point at chord
    # position s that is ω (R² - s² - d²)/2 = ω (L² - s²)/2
    section = _drum_section(RADIUS, RPM, 0.32, PHI_DEG, LAYER)
    s = S_MID * section.half_chord
    assert rolling_drum_flux(OMEGA, section.half_chord, s) == pytest.approx(
        section.thin_layer_flux(s), rel=1e-14
    )
    (tx, ty), (mx, my) = section.tangent, section.normal
    for sk in s:
        bottom = -section.offset - math.sqrt(RADIUS**2 - sk**2)
        n = np.linspace(bottom, 0.0, 200001)
        a = n + section.offset
        x, y = tx * sk + mx * a, ty * sk + my * a
        along = OMEGA * (-y * tx + x * ty)  # (ω ẑ × r)·t
        carried = np.sum(0.5 * (along[1:] + along[:-1]) * np.diff(n))  # uphill
        assert carried == pytest.approx(rolling_drum_flux(OMEGA, section.half_chord, sk), rel=1e-9)
    assert rolling_drum_flux(OMEGA, section.half_chord, 1.2 * section.half_chord) == 0.0


@pytest.mark.parametrize("fill_depth", [0.5, 0.32])
def test_layer_flux_recovers_the_exact_flux_of_exact_velocities(fill_depth):
    flow, section = analytic(128, fill_depth, exact_velocity=True)
    h = float(flow.x[1] - flow.x[0])
    s = S_MID * section.half_chord
    q = layer_flux(flow, s)
    exact = exact_layer_flux(section, s)
    # The velocity is exact at every cell centre; the error is the interpolation across
    # the cells the surface cuts, where the speed changes by u_s h / δ0 over a cell:
    # bounded by h / (2 δ0) (about 5 % here) relative to the flux, about u_s δ0 / 2.
    bound = h / (2.0 * section.layer)
    np.testing.assert_allclose(q["flux"], exact, rtol=bound)
    # mass balance: what runs down in the layer comes back up below it, and what the
    # rigid bed between the layer's base and the bed's edge carries, ω (r_e² - r_b²)/2
    np.testing.assert_allclose(q["upslope_flux"], q["flux"], rtol=bound)
    np.testing.assert_allclose(q["rigid_flux_below"], exact, rtol=bound)
    # the layer's base sits inside the kinematic layer (where u·t changes sign)
    assert np.all(q["layer_depth"] < section.layer_thickness(s) + h)
    assert np.all(q["layer_depth"] > 0.5 * section.layer_thickness(s))
    np.testing.assert_allclose(q["wall_gap"], 0.0, atol=0.25 * h)


def test_layer_flux_converges_at_first_order_on_the_gridded_analytic_drum():
    # rolling_drum's velocities are central differences of ψ over 2h, smoothed over a
    # cell at the surface (its docstring): a first-order error of about h / δ0
    errors, hs = [], []
    for cells in (64, 128, 256):
        flow, section = analytic(cells)
        h = float(flow.x[1] - flow.x[0])
        s = S_MID * section.half_chord
        error = np.abs(layer_flux(flow, s)["flux"].values / exact_layer_flux(section, s) - 1)
        assert error.max() < h / section.layer
        errors.append(error.mean())
        hs.append(h)
    orders = np.log(np.array(errors[:-1]) / errors[1:]) / np.log(np.array(hs[:-1]) / hs[1:])
    assert np.all((orders > 0.7) & (orders < 1.5)), orders


@pytest.mark.parametrize("fill_depth", [0.5, 0.32])
def test_surface_velocity_recovers_the_exact_surface_speed(fill_depth):
    flow, section = analytic(128, fill_depth, exact_velocity=True)
    h = float(flow.x[1] - flow.x[0])
    sv = surface_velocity(flow)
    s = sv["s"].values
    L = section.half_chord
    exact = section.omega * L * np.sqrt(L * L - s * s) / section.layer  # downhill
    middle = np.abs(s) < 0.5 * L
    # the speed falls by u_s h / δ over a cell below the surface, and the fill-weighted
    # velocity at the fill = 0.5 point leans on the cell below: within h / δ
    bound = h / section.layer
    np.testing.assert_allclose(sv["speed"].values[middle], exact[middle], rtol=bound)
    assert float(sv["max_speed"]) == pytest.approx(section.omega * L * L / section.layer, rel=bound)
    assert abs(float(sv["s_at_max"])) < 0.2 * L


def test_diagnostics_refuse_a_vessel_frame_flow():
    flow, _ = analytic(32)
    flow.attrs["frame"] = "vessel"
    with pytest.raises(ValueError, match="lab frame"):
        surface_line(flow)


@pytest.mark.parametrize(
    ("change", "call", "match"),
    [
        (None, lambda f: surface_line(f, method="rows"), "method must be 'normal' or 'column'"),
        (None, lambda f: surface_line(f, level=1.0), r"level must be in \(0, 1\)"),
        (None, lambda f: layer_flux(f, 0.075), "s must lie within the half-chord"),
        ("empty", surface_line, "no free surface"),
        ("full", surface_line, "no free surface"),
        ("3-D", surface_line, "2-D flow"),
        ("stretched", surface_line, "square cells"),
    ],
)
def test_diagnostics_refuse_what_they_cannot_measure(change, call, match):
    flow, _ = analytic(32)
    if change == "empty":
        flow["fill"][...] = 0.0
    elif change == "full":  # a completely filled drum has no free surface either
        flow["fill"][...] = flow["vessel"].astype(float).values[None]
    elif change == "3-D":
        flow = flow.expand_dims(z=[0.0])
    elif change == "stretched":
        flow = flow.assign_coords(y=2.0 * flow["y"])
    with pytest.raises(ValueError, match=match):
        call(flow)


def test_drum_radius_from_the_analytic_recipe_the_scene_or_the_mask():
    flow, _ = analytic(64)
    assert drum_radius(flow) == RADIUS  # the analytic flow's own recipe
    del flow.attrs["analytic"]
    flow.attrs["scene"] = '[vessel]\nkind = "drum"\ndiameter = 0.3\n'
    assert drum_radius(flow) == 0.15  # the scene's diameter
    del flow.attrs["scene"]
    # the disc of the masked cells' area: within a fraction of a cell of the radius
    h = float(flow.x[1] - flow.x[0])
    assert drum_radius(flow) == pytest.approx(RADIUS, abs=0.25 * h)


# ----------------------------------------------------------------------------- solver


def drum_scene():
    return {
        "name": "rolling-drum-test",
        "vessel": {"kind": "drum", "ndim": 2, "diameter": 2 * RADIUS},
        "operation": {"rpm": RPM},
        "fill": {"fraction": 0.5},
        "material": {"cohesion": 0.0},
        "flow": {"cell": 0.005},
        "solver": {
            "stiffness_scaling": 100.0,
            "settle_time": 0.3,
            "revolutions": 2,
            "checkpoint_every": 1e9,
        },
    }


@pytest.fixture(scope="module")
def drum_flow():
    return solve_flow(drum_scene(), progress=False)


@pytest.fixture(scope="module")
def drum_surface(drum_flow):
    return surface_line(drum_flow)


@pytest.mark.slow
def test_solver_drum_turns_counter_clockwise_and_its_surface_rises_towards_plus_x(
    drum_flow, drum_surface
):
    assert drum_flow.attrs["frame"] == "lab"
    assert drum_surface.angle_deg > 0  # rises towards +x
    # lab frame: the bed at the bottom is carried towards +x by the wall (ω ẑ × r)
    bottom = drum_flow.sel(x=0.0, y=-0.06, method="nearest").isel(rev_phase=0)
    assert float(bottom["vx"]) == pytest.approx(OMEGA * 0.06, rel=0.15)
    # and the surface runs downhill along the whole middle of the chord
    sv = surface_velocity(drum_flow, surface=drum_surface)
    middle = np.abs(sv["s"].values) < 0.5 * drum_surface.half_chord
    assert np.all(sv["speed"].values[middle] > 0)


@pytest.mark.slow
def test_solver_drum_surface_sits_at_the_friction_angle(drum_surface):
    # cohesionless Mohr-Coulomb material rolls at a dynamic angle close to φ; at
    # 10 rpm in a 150 mm drum the Froude number ω²R/g is 0.008, too small to steepen it
    assert drum_surface.angle_deg == pytest.approx(PHI_DEG, abs=3.0)


@pytest.fixture(scope="module")
def angles_by_friction():
    """Surface angle of the rolling drum (7.5 mm cells) with φ = 20° and 35°."""
    out = {}
    for phi in (20.0, 35.0):
        scene = drum_scene()
        scene["material"]["friction_angle_deg"] = phi
        scene["flow"]["cell"] = 0.0075
        out[phi] = surface_line(solve_flow(scene, progress=False)).angle_deg
    return out


@pytest.mark.slow
@pytest.mark.parametrize("phi", [20.0, 35.0])
def test_solver_drum_angle_follows_the_scenes_friction_angle(angles_by_friction, phi):
    # measured: 22.6° and 33.5° at 7.5 mm (21.8° and 32.7° at 5 mm)
    assert angles_by_friction[phi] == pytest.approx(phi, abs=3.0)


@pytest.mark.slow
def test_solver_drum_angle_rises_with_the_friction_angle(angles_by_friction):
    assert angles_by_friction[35.0] - angles_by_friction[20.0] > 0.6 * 15.0


@pytest.mark.slow
def test_solver_drum_surface_is_flat(drum_flow, drum_surface):
    h = drum_flow.attrs["solver_cell_m"]
    # the exact flat surface of the analytic drum leaves 0.05 h rms (interpolation);
    # a quarter of a cell rms and one cell at most is flat at this resolution
    assert drum_surface.rms_residual < 0.25 * h
    assert drum_surface.max_residual < 1.0 * h


@pytest.mark.slow
def test_solver_drum_layer_returns_what_the_rigid_bed_below_carries(drum_flow, drum_surface):
    # DESIGN §7's mass balance, for the bed as the solver has it: rigid rotation at ω
    # carries ω (r_e² - r_b²)/2 between the bed's outer edge r_e and the layer's base
    # r_b, and the layer must return it. 10 %: on exact velocities at this resolution
    # (30 cells across; the analytic tests above) the flux measurement alone errs by up
    # to 6 %, and the bed just below the layer's base lags rigid rotation a little
    # (measured at 5 mm: 93-99 % of ω between 25 mm and 70 mm from the axis)
    s = S_MID * drum_surface.half_chord
    q = layer_flux(drum_flow, s, surface=drum_surface)
    np.testing.assert_allclose(q["flux"], q["rigid_flux_below"], rtol=0.10)
    # and the averaged field conserves material: the layer's flux comes back up below it
    # (to the flux measurement's error on exact velocities, 6 % at this resolution)
    np.testing.assert_allclose(q["upslope_flux"], q["flux"], rtol=0.10)


@pytest.mark.slow
@pytest.mark.xfail(
    reason="at 5 mm cells the layer carries 13-19 % less than omega (L^2 - s^2) / 2 in the "
    "middle of the chord (benchmarks/results/flow_drum.md), because the formula is the "
    "thin-layer limit: the downslope-moving layer here is 21 mm (4 cells) deep, which "
    "takes ((d - delta)^2 - d^2) / L^2 = 8 % off what the rigid bed hands over, and the "
    "bed's edge stands 1.6 mm off the wall (the wall law acts on nodes up to half a cell "
    "inside the vessel), another 2 R g / L^2 = 4 %. Both shrink with the cell (2.5 mm: "
    "-11 to -15 %); the rigid-bed balance with the measured edge and base holds (above)",
    strict=False,
)
def test_solver_drum_layer_flux_is_the_thin_layer_flux(drum_flow, drum_surface):
    s = S_MID * drum_surface.half_chord
    q = layer_flux(drum_flow, s, surface=drum_surface)
    np.testing.assert_allclose(q["flux"], q["thin_layer_flux"], rtol=0.10)
