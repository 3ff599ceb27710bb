"""The ADE driver against exact solutions, conservation laws and hard cases.

Every scheme runs the same problems (parametrised), in the spirit of testing every
time-stepper against exact answers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr

import blendxr as bx

SCHEMES = list(bx.SCHEMES)


def gaussian(centre, sigma2, background=0.2, amplitude=0.6):
    """Initial c: a Gaussian bump on a constant background (stays inside [0, 1])."""

    def c0(*points):
        r2 = sum((p - c) ** 2 for p, c in zip(points, centre, strict=True))
        return background + amplitude * np.exp(-r2 / (2 * sigma2))

    return c0


def exact_gaussian(points, centre, sigma2, velocity, diffusivity, t, background=0.2, amplitude=0.6):
    """Exact solution of c_t + u.grad c = div(D grad c) for constant u and diagonal D."""
    value = np.full(points[0].shape, amplitude)
    for p, c, u, d in zip(points, centre, velocity, diffusivity, strict=True):
        s2 = sigma2 + 2 * d * t
        value = value * np.sqrt(sigma2 / s2) * np.exp(-((p - c - u * t) ** 2) / (2 * s2))
    return background + value


def final_field(mixed):
    c = mixed["c"].isel(snapshot=-1)
    points = np.meshgrid(*[c[d].values for d in c.dims], indexing="ij")
    return c.values, points


def l1_error(values, exact, spacing, window):
    inside = window & np.isfinite(values)
    return float(np.abs(values - exact)[inside].sum() * np.prod(spacing))


def observed_orders(errors):
    e = np.asarray(errors)
    return np.log2(e[:-1] / e[1:])


# ---------------------------------------------------------------------------- exact solutions


@pytest.mark.parametrize("scheme", SCHEMES)
def test_gaussian_in_oblique_uniform_flow_converges_at_design_order(scheme):
    velocity = (0.5, 0.3)
    diffusivity = (1.0e-3, 4.0e-4)
    centre, sigma2 = (0.35, 0.4), 0.07**2
    flow = bx.flows.uniform(velocity=velocity, cells=8, extent=1.0, rpm=60.0)
    t_end = 0.4  # revolutions of a 1 s period
    errors = []
    for cells in (32, 64, 128):
        mixed = bx.mix(
            flow,
            scheme=scheme,
            initial=gaussian(centre, sigma2),
            diffusivity=diffusivity,
            revolutions=t_end,
            output_every=t_end,
            snapshots=[t_end],
            cells=cells,
            progress=False,
        )
        values, points = final_field(mixed)
        exact = exact_gaussian(points, centre, sigma2, velocity, diffusivity, t_end)
        window = (np.abs(points[0] - 0.5) < 0.35) & (np.abs(points[1] - 0.5) < 0.35)
        errors.append(l1_error(values, exact, mixed.attrs["grid_spacing"], window))
    orders = observed_orders(errors)
    minimum = 1.8 if scheme == "lax-wendroff" else 1.5
    assert orders.min() >= minimum, f"{scheme}: L1 errors {errors}, orders {orders}"


@pytest.mark.parametrize("scheme", SCHEMES)
def test_solid_body_rotation_3d_returns_spread_gaussian_after_one_revolution(scheme):
    radius, rpm, diffusion = 0.1, 10.0, 2.0e-6
    flow = bx.flows.solid_body_rotation(ndim=3, radius=radius, cells=16, rpm=rpm)
    period = 60.0 / rpm
    centre, sigma2 = (0.045, 0.0, 0.0), 0.018**2
    errors = []
    for cells in (24, 48):
        mixed = bx.mix(
            flow,
            scheme=scheme,
            initial=gaussian(centre, sigma2),
            diffusivity=(diffusion,) * 3,
            revolutions=1.0,
            output_every=0.5,
            snapshots=[1.0],
            cells=cells,
            progress=False,
        )
        values, points = final_field(mixed)
        exact = exact_gaussian(points, centre, sigma2, (0, 0, 0), (diffusion,) * 3, period)
        r = np.hypot(points[0], points[1])
        window = (r < 0.8 * radius) & (np.abs(points[2]) < 0.6 * radius)
        errors.append(l1_error(values, exact, mixed.attrs["grid_spacing"], window))
    # the peak must come back to where it started, spread by exactly 2DT
    assert errors[1] < 0.5 * errors[0], errors
    peak = np.unravel_index(np.nanargmax(values), values.shape)
    assert np.allclose([p[peak] for p in points], centre, atol=2 * mixed.attrs["grid_spacing"][0])


@pytest.mark.parametrize("scheme", SCHEMES)
def test_swirl_returns_to_initial_state_after_each_revolution(scheme):
    flow = bx.flows.swirl(ndim=2, cells=32, n_phases=24, rpm=60.0, size=1.0)
    start = gaussian((0.5, 0.3), 0.1**2)
    errors = []
    for cells in (32, 64):
        mixed = bx.mix(
            flow,
            scheme=scheme,
            initial=start,
            k1=0.0,
            revolutions=1.0,
            output_every=0.25,
            snapshots=[0.0, 0.25, 1.0],
            cells=cells,
            progress=False,
        )
        values, points = final_field(mixed)
        window = np.ones(values.shape, bool)
        errors.append(l1_error(values, start(*points), mixed.attrs["grid_spacing"], window))
        stretched = mixed["c"].isel(snapshot=1).values
        # a quarter of the way through, the bump is stretched far from its start
        assert (
            l1_error(stretched, start(*points), mixed.attrs["grid_spacing"], window)
            > 3 * errors[-1]
        )
    assert errors[1] < 0.6 * errors[0], errors


@pytest.mark.parametrize("scheme", SCHEMES)
def test_swirl_return_converges_at_second_order(scheme):
    """The time-reversing swirl with its flow refined with the grid: L1 order >= 1.8.

    The flow varies in space and time, so this checks the (v . grad) v part of the
    second-order time derivative (without it both schemes fall to first order here).
    """
    start = gaussian((0.5, 0.3), 0.1**2)
    errors = []
    for cells in (32, 64):
        flow = bx.flows.swirl(ndim=2, cells=cells, n_phases=24, rpm=60.0, size=1.0)
        mixed = bx.mix(
            flow,
            scheme=scheme,
            initial=start,
            k1=0.0,
            revolutions=1.0,
            output_every=0.5,
            cells=cells,
            progress=False,
        )
        values, points = final_field(mixed)
        window = np.ones(values.shape, bool)
        errors.append(l1_error(values, start(*points), mixed.attrs["grid_spacing"], window))
    assert math.log2(errors[0] / errors[1]) >= 1.8, errors


# ---------------------------------------------------------------------------- conservation


def test_finite_volume_conserves_species_in_closed_vessel_with_moving_bed():
    flow = bx.flows.solid_body_rotation(
        ndim=2, radius=0.1, cells=24, rpm=10.0, fill_fraction=0.4, n_phases=36
    )
    mixed = bx.mix(
        flow,
        scheme="finite-volume",
        initial="transverse",
        k1=0.05,
        d=0.004,
        revolutions=1.0,
        output_every=0.05,
        cells=48,
        max_steps=1000,
        progress=False,
    )
    assert mixed.attrs["steps"] >= 1000 or mixed.attrs["stopped_by"] == "revolutions"
    mass = mixed["mass_a"].values
    assert np.max(np.abs(mass - mass[0])) / mass[0] <= 1e-10
    c = mixed["c"].values
    assert np.nanmin(c) >= 0.0 and np.nanmax(c) <= 1.0  # no clipping in this scheme


def test_lax_wendroff_reports_its_mass_drift():
    flow = bx.flows.solid_body_rotation(
        ndim=2, radius=0.1, cells=24, rpm=10.0, fill_fraction=0.4, n_phases=36
    )
    mixed = bx.mix(
        flow,
        scheme="lax-wendroff",
        initial="transverse",
        k1=0.0,
        revolutions=0.5,
        cells=40,
        progress=False,
    )
    mass = mixed["mass_a"].values
    reported = mixed.attrs["mass_a_relative_drift"]
    assert reported == pytest.approx(np.max(np.abs(mass - mass[0])) / mass[0])


def test_swapping_colours_gives_one_minus_c():
    flow = bx.flows.swirl(ndim=2, cells=24, n_phases=12, rpm=60.0, size=0.2)
    start = gaussian((0.1, 0.06), 0.03**2)

    def swapped(*p):
        return 1.0 - start(*p)

    runs = [
        bx.mix(
            flow,
            scheme="finite-volume",
            initial=f,
            k1=0.5,
            d=0.004,
            revolutions=0.5,
            cells=32,
            progress=False,
        )
        for f in (start, swapped)
    ]
    a, b = (r["c"].isel(snapshot=-1).values for r in runs)
    material = np.isfinite(a)
    np.testing.assert_allclose(a[material] + b[material], 1.0, atol=1e-12)


# ---------------------------------------------------------------------------- hard cases


@pytest.mark.parametrize("scheme", SCHEMES)
def test_zero_velocity_and_no_diffusion_leaves_c_unchanged(scheme):
    flow = bx.flows.uniform(velocity=(0.0, 0.0, 0.0), cells=6, extent=1.0)
    mixed = bx.mix(
        flow, scheme=scheme, initial="top-bottom", k1=0.0, revolutions=1.0, cells=12, progress=False
    )
    c = mixed["c"].values
    np.testing.assert_array_equal(c[0][np.isfinite(c[0])], c[-1][np.isfinite(c[-1])])
    assert mixed.attrs["diffusion_substeps_max"] == 0


def test_stiff_diffusion_substeps_match_a_fine_time_step_and_stay_bounded():
    """k1 = 1 with large grains: diffusion-limited. The sub-cycled run must agree with a
    run at a dt far below every limit, and with the paper's scheme, and stay in [0, 1]."""
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=8, rpm=60.0, size=0.1)
    kwargs = dict(initial="top-bottom", k1=1.0, d=0.01, revolutions=0.5, cells=32, progress=False)
    stiff = bx.mix(flow, scheme="finite-volume", **kwargs)
    fine = bx.mix(flow, scheme="finite-volume", dt=2e-4, **kwargs)
    paper = bx.mix(flow, scheme="lax-wendroff", **kwargs)
    assert stiff.attrs["diffusion_substeps_max"] > 1  # the case is really diffusion-limited
    assert fine.attrs["diffusion_substeps_max"] == 1
    for mixed in (stiff, fine, paper):
        c = mixed["c"].values
        assert np.nanmin(c) >= -1e-12 and np.nanmax(c) <= 1 + 1e-12
    rsd = [m["rsd"].values[-1] for m in (stiff, fine, paper)]
    assert rsd[0] < 0.8 * stiff["rsd"].values[0]  # it mixes
    np.testing.assert_allclose(rsd[0], rsd[1], rtol=0.01)
    np.testing.assert_allclose(rsd[0], rsd[2], rtol=0.01)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_one_material_cell_and_full_vessel(scheme):
    full = bx.flows.uniform(velocity=(0.01, 0.0), cells=8, extent=1.0)
    one = full.copy(deep=True)
    fill = np.zeros_like(one["fill"].values)
    fill[:, 4, 4] = 1.0
    one["fill"].values[...] = fill
    for flow in (full, one):
        mixed = bx.mix(
            flow,
            scheme=scheme,
            initial="transverse",
            k1=0.0,
            revolutions=0.2,
            cells=16,
            progress=False,
        )
        c = mixed["c"].values
        assert np.isfinite(c).any()
        assert np.nanmin(c) >= 0 and np.nanmax(c) <= 1


def test_no_material_at_start_is_refused():
    flow = bx.flows.uniform(velocity=(0.0, 0.0), cells=8)
    flow["fill"].values[...] = 0.0
    with pytest.raises(ValueError, match="no material"):
        bx.mix(flow, revolutions=0.1, cells=16, progress=False)


def test_a_phase_without_material_does_not_break_the_run():
    flow = bx.flows.solid_body_rotation(
        ndim=2, radius=0.1, cells=16, rpm=10.0, fill_fraction=0.4, n_phases=6
    )
    flow["fill"].values[3] = 0.0
    mixed = bx.mix(
        flow,
        scheme="finite-volume",
        initial="transverse",
        k1=0.0,
        revolutions=1.0,
        cells=24,
        progress=False,
    )
    mass = mixed["mass_a"].values
    assert np.max(np.abs(mass - mass[0])) / mass[0] <= 1e-10


@pytest.mark.parametrize("scheme", SCHEMES)
def test_dt_above_the_stability_limit_is_refused_with_the_limit(scheme):
    flow = bx.flows.uniform(velocity=(1.0, 0.5), cells=8)
    with pytest.raises(ValueError, match=r"exceeds the stability limit .* s"):
        bx.mix(flow, scheme=scheme, dt=1.0, revolutions=0.1, cells=32, progress=False)


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"scheme": "upwind"}, "scheme"),
        ({"k1": -0.1}, "k1"),
        ({"d": -1.0}, "d"),
        ({"initial": "diagonal"}, "initial"),
        ({"revolutions": 0}, "revolutions"),
    ],
)
def test_bad_arguments_name_the_argument(kwargs, word):
    flow = bx.flows.uniform(velocity=(0.0, 0.0), cells=8)
    with pytest.raises(ValueError, match=word):
        bx.mix(flow, progress=False, **kwargs)


def test_axial_loading_needs_z():
    flow = bx.flows.uniform(velocity=(0.0, 0.0), cells=8)
    with pytest.raises(ValueError, match="z"):
        bx.mix(flow, initial="axial", revolutions=0.1, progress=False)


# ---------------------------------------------------------------------------- outputs


def test_mixing_dataset_is_valid_and_labelled():
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=8, rpm=60.0, size=0.2)
    mixed = bx.mix(
        flow,
        initial="top-bottom",
        k1=0.1,
        d=0.004,
        revolutions=1.0,
        output_every=0.25,
        snapshots=[0, 1],
        cells=24,
        progress=False,
    )
    bx.validate(mixed)
    assert "z" not in mixed.dims
    np.testing.assert_allclose(mixed["revolution"].values, [0, 0.25, 0.5, 0.75, 1.0])
    assert mixed["rsd"].values[0] == pytest.approx(1.0, rel=0.1)  # segregated start
    for key in ("scheme", "dt_max", "k1", "k2", "d", "wall_time_s", "grid_cells"):
        assert key in mixed.attrs
    assert mixed.attrs["k2"] == pytest.approx(1.9 * 0.1)


def test_checkpoint_resume_gives_the_same_answer(tmp_path):
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=8, rpm=60.0, size=0.2)
    kwargs = dict(
        initial="top-bottom", k1=0.1, d=0.004, cells=24, progress=False, output_every=0.25
    )
    straight = bx.mix(flow, revolutions=2.0, **kwargs)
    ckpt = tmp_path / "run.ckpt.nc"
    first = bx.mix(
        flow, revolutions=2.0, checkpoint=ckpt, checkpoint_every=0.5, max_steps=1, **kwargs
    )
    assert first.attrs["stopped_by"] == "max_steps"
    resumed = bx.mix(flow, revolutions=2.0, checkpoint=ckpt, **kwargs)
    np.testing.assert_array_equal(resumed["rsd"].values, straight["rsd"].values)
    np.testing.assert_array_equal(resumed["c"].values, straight["c"].values)


def test_only_the_phases_in_use_are_read():
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=24, rpm=60.0, size=0.2)
    mixed = bx.mix(flow, k1=0.0, revolutions=0.25, output_every=0.25, cells=24, progress=False)
    # a quarter revolution touches phases 0..6 (plus one prefetched ahead)
    assert mixed.attrs["phases_read"] <= 8


def test_a_small_lazy_flow_is_read_whole_and_answers_the_same(tmp_path, monkeypatch):
    """A dask-backed or on-disk flow below SMALL_FLOW_BYTES is read into memory before
    the run (its validation reads every value anyway): the same answer, bit for bit, as
    reading it phase by phase, and the caller's dataset stays lazy."""
    from blendxr.ade import stepper

    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=24, rpm=60.0, size=0.2)
    kwargs = dict(k1=0.0, revolutions=0.25, output_every=0.25, cells=24, progress=False)
    path = tmp_path / "flow.nc"
    bx.io.write_dataset(flow, path)
    lazy = flow.chunk({"rev_phase": 1})
    assert stepper._read_if_small(lazy).vx.chunks is None
    whole = [bx.mix(lazy, **kwargs), bx.mix(path, **kwargs)]
    assert lazy.vx.chunks is not None
    monkeypatch.setattr(stepper, "SMALL_FLOW_BYTES", 0)  # phase by phase, as for big flows
    by_phase = [bx.mix(lazy, **kwargs), bx.mix(path, **kwargs)]
    for one, other in zip(whole, by_phase, strict=True):
        np.testing.assert_array_equal(one["c"].values, other["c"].values)
        np.testing.assert_array_equal(one["rsd"].values, other["rsd"].values)
    assert by_phase[0].attrs["phases_read"] == whole[0].attrs["phases_read"]


@pytest.mark.parametrize("loading", ["top-bottom", "transverse", "axial"])
def test_loadings_put_equal_volumes_of_each_colour(loading):
    """A tilted, asymmetric bed is still loaded half and half (volume median plane)."""
    ndim = 3 if loading == "axial" else 2
    flow = bx.flows.rolling_drum(ndim=ndim, cells=24, fill_depth=0.3, angle_deg=30.0)
    # an ADE grid that coincides with the flow grid, so both hold the same material
    cells = flow.sizes["x"]
    mixed = bx.mix(flow, initial=loading, k1=0.0, revolutions=0.01, cells=cells, progress=False)
    fill0 = flow["fill"].isel(rev_phase=0)
    cell_volume = np.prod([float(flow[d][1] - flow[d][0]) for d in fill0.dims])
    material = float(fill0.where(flow["vessel"] > 0, 0.0).sum()) * cell_volume
    assert mixed["mass_a"].values[0] == pytest.approx(0.5 * material, rel=1e-9)


# ------------------------------------------------------------ limits that limit


def test_max_steps_stops_inside_an_interval_and_the_resume_is_bit_identical(tmp_path):
    """The step budget is checked after every step, not only at output times; the
    interrupted interval's plan is carried in the checkpoint."""
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=4, rpm=60.0, size=0.2)
    kwargs = dict(initial="top-bottom", k1=0.1, d=0.004, cells=24, progress=False)
    straight = bx.mix(flow, revolutions=0.5, output_every=0.5, **kwargs)
    assert straight.attrs["steps"] > 7  # several steps in each stored-phase interval
    ckpt = tmp_path / "run.ckpt.nc"
    first = bx.mix(flow, revolutions=0.5, output_every=0.5, checkpoint=ckpt, max_steps=7, **kwargs)
    assert first.attrs["stopped_by"] == "max_steps" and first.attrs["steps"] == 7
    resumed = bx.mix(flow, revolutions=0.5, output_every=0.5, checkpoint=ckpt, **kwargs)
    assert resumed.attrs["steps"] == straight.attrs["steps"]
    np.testing.assert_array_equal(resumed["c"].values, straight["c"].values)


def test_wall_time_stops_inside_an_interval():
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=4, rpm=60.0, size=0.2)
    mixed = bx.mix(flow, revolutions=0.5, output_every=0.5, cells=24, wall_time=1e-9,
                   progress=False)  # fmt: skip
    assert mixed.attrs["stopped_by"] == "wall_time" and mixed.attrs["steps"] == 1


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"cells": 100_000}, ["numerics.cells = 100000", "MiB", "numerics.cells <="]),
        ({"output_every": 1e-12}, ["mixing.output_every", "records", "at most 1,000,000"]),
        ({"dt": 1e-12, "revolutions": 1.0}, ["dt = 1e-12", "cell updates"]),
        ({"cells": 64, "memory_budget_mb": 1.0}, ["above numerics.memory_budget_mb = 1"]),
    ],
)
def test_a_run_that_cannot_fit_or_end_is_refused_before_it_allocates(kwargs, words):
    flow = bx.flows.uniform(velocity=(0.01, 0.0), cells=8)
    with pytest.raises(ValueError) as err:
        bx.mix(flow, progress=False, **kwargs)
    for word in words:
        assert word in str(err.value)


def test_the_memory_estimate_covers_what_the_run_allocates():
    """The plan's bytes per cell bound what tracemalloc sees (every scheme, 2-D; a budget
    that leaves the reader its window of three phases, not the whole revolution)."""
    import tracemalloc

    from blendxr.ade.stepper import _settings_from, plan

    flow = bx.flows.solid_body_rotation(ndim=2, radius=0.1, cells=24, rpm=10.0,
                                        fill_fraction=0.4, n_phases=12)  # fmt: skip
    for scheme in bx.SCHEMES:
        kwargs = dict(scheme=scheme, cells=160, revolutions=0.02, output_every=0.01, k1=0.01,
                      d=0.002, memory_budget_mb=20.0, progress=False)  # fmt: skip
        bx.mix(flow, **{**kwargs, "cells": 8})  # compiled before measuring
        tracemalloc.start()
        bx.mix(flow, **kwargs)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        planned = plan(flow, _settings_from(None, kwargs))["bytes"]
        assert peak <= planned


def test_a_velocity_no_bed_can_reach_is_refused_naming_the_cell():
    flow = bx.flows.uniform(velocity=(0.01, 0.0), cells=8)
    flow["vx"] = flow["vx"].copy()
    flow["vx"][0, 3, 4] = 1e30
    with pytest.raises(ValueError, match=r"vx = 1e\+30 m/s at rev_phase index 0, cell \(3, 4\)"):
        bx.mix(flow, revolutions=0.1, cells=8, progress=False)


def test_a_diffusivity_that_needs_too_many_substeps_is_refused():
    flow = bx.flows.uniform(velocity=(0.01, 0.0), cells=8)
    with pytest.raises(ValueError, match="sub-steps"):
        bx.mix(flow, diffusivity=(1e3, 1e3), revolutions=0.1, cells=32, progress=False)


def _c0_on(flow, value=0.5):
    return xr.full_like(flow["fill"].isel(rev_phase=0, drop=True), value, dtype=float)


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda c: c * np.nan, ["not finite at 64 of 64 points"]),
        (lambda c: c.where(c.x < 0.05), ["not finite at", "first at x="]),
        (lambda c: c.drop_vars(["x", "y"]), ["no coordinates", "by index"]),
        (lambda c: c.assign_coords(x=c.x / 100), ["covers x"]),
        (lambda c: c.assign_coords(x=c.x.assign_attrs(units="cm")), ["in 'cm'"]),
    ],
)
def test_an_initial_dataarray_that_would_be_guessed_at_is_refused(make, words):
    """NaN was taken as c = 0.5 (RSD 0, "perfectly mixed"); no coordinates placed the
    values by index; an array beside the bed was filled from its nearest edge."""
    flow = bx.flows.uniform(velocity=(0.01, 0.0), cells=8)
    c0 = make(_c0_on(flow))
    with pytest.raises(ValueError) as err:
        bx.mix(flow, initial=c0, revolutions=0.1, cells=8, progress=False)
    for word in words:
        assert word in str(err.value)


def test_the_checkpoint_schedule_saves_on_each_multiple_once():
    from blendxr.driver import CheckpointSchedule

    saves = CheckpointSchedule(0.5)
    due = [r for r in (0.25, 0.5, 0.75, 1.0, 1.0, 1.25, 1.75) if saves.due(r)]
    assert due == [0.5, 1.0, 1.75]
    saves.resume_at(1.2)  # a run resumed part way: the next save at 1.5
    assert not saves.due(1.25) and saves.due(1.5)


def test_a_callback_sees_every_record():
    flow = bx.flows.swirl(ndim=2, cells=16, n_phases=4, size=0.2)
    seen = []
    mixed = bx.mix(flow, revolutions=1.0, output_every=0.25, cells=24, progress=False,
                   callback=lambda state: seen.append((state.revolution, state.rsd)))  # fmt: skip
    np.testing.assert_allclose([r for r, _ in seen], mixed["revolution"].values[1:])
    np.testing.assert_array_equal([v for _, v in seen], mixed["rsd"].values[1:])
