"""The built-in Mohr-Coulomb MPM flow solver against exact mechanics and its contracts.

Small 2-D cases with the stiffness scaled down (a larger stable dt) keep the file fast;
the quantities checked (Coulomb sliding, rigid rotation, conservation) do not depend on
the elastic stiffness once the material is at rest relative to itself.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import blendxr as bx
from blendxr.flow.averaging import PhaseAverager, coarsen_fields, lab_velocities, periodicity
from blendxr.flow.output import (
    _warn_of_clipped_fill,
    occupied_volume_over_seeded,
    revolution_change,
)
from blendxr.flow.solver import SPIN_UP_THINNING, FlowBlowUpError, FlowSimulation, solve_flow
from blendxr.scene import SceneError

G = 9.81


def incline_scene(mu=0.324, duration=0.3):
    return {
        "name": "incline",
        "vessel": {"kind": "box", "ndim": 2, "size": [0.6, 0.1]},
        "operation": {"rpm": 0.0, "duration": duration},
        "material": {"wall_friction": mu},
        "fill": {"box": [[-0.05, 0.05], [-0.05, -0.03]]},
        "flow": {"cell": 0.005},
        "solver": {"stiffness_scaling": 100.0, "settle_time": 0.0},
    }


def slide(theta_deg, until=0.3, mu=0.324):
    """Mean velocity along the floor against time for a block on a floor tilted by theta."""
    theta = math.radians(theta_deg)
    sim = FlowSimulation(
        incline_scene(mu=mu), gravity_direction=(math.sin(theta), -math.cos(theta))
    )
    times, speeds = [], []

    def sample(s):
        if s.steps % 10 == 0:
            times.append(s.t)
            speeds.append(np.average(s.particles.v[:, 0], weights=s.particles.mass))

    sim.run(until=until, progress=False, callback=sample)
    return np.array(times), np.array(speeds)


@pytest.mark.parametrize("mu", [0.324, 0.2])
def test_block_slides_down_a_30_degree_wall_at_the_coulomb_acceleration(mu):
    # 0.324 is Table 1's (and the default); 0.2 checks that the scene's value is used
    times, speeds = slide(30.0, mu=mu)
    late = times > 0.1  # after the block has seated on the floor
    acceleration = np.polyfit(times[late], speeds[late], 1)[0]
    exact = G * (math.sin(math.radians(30)) - mu * math.cos(math.radians(30)))
    if mu == 0.324:
        assert exact == pytest.approx(2.15, abs=0.005)  # DESIGN §7
    assert acceleration == pytest.approx(exact, rel=0.05)


def test_block_stays_at_rest_on_a_15_degree_wall():
    times, speeds = slide(15.0)
    free = G * math.sin(math.radians(15)) * times[-1]  # speed without friction
    assert np.abs(speeds).max() < 0.02 * free


def drum_scene(fraction, rpm=30.0, revolutions=2, cell=0.01):
    return {
        "name": "small-drum",
        "vessel": {"kind": "drum", "ndim": 2, "diameter": 0.15},
        "operation": {"rpm": rpm},
        "fill": {"fraction": fraction},
        "flow": {"cell": cell},
        "mixing": {"loading": "top-bottom"},
        "solver": {
            "stiffness_scaling": 100.0,
            "settle_time": 0.2,
            "revolutions": revolutions,
            "checkpoint_every": 1e9,
        },
    }


@pytest.mark.slow
def test_a_full_vessel_turns_as_a_rigid_body():
    # the elastic sway under the turning gravity scales with 1/E: 3 % of omega R with
    # E / 100, 0.28 % with E / 10, 0.03 % unscaled (measured), so E / 10 here
    scene = drum_scene(1.0, rpm=10.0)
    scene["solver"]["stiffness_scaling"] = 10.0
    sim = FlowSimulation(scene)
    omega_r = sim.omega * 0.075
    sim.run(until=sim.settings.settle_time + 0.25 * sim.period, progress=False)
    speed = np.sqrt((sim.particles.v**2).sum(axis=1))  # relative to the vessel
    assert speed.max() < 0.01 * omega_r


@pytest.mark.slow
def test_solve_flow_gives_a_valid_flow_that_conserves_material_and_mixes(tmp_path):
    scene = drum_scene(0.4)
    flow, particles = solve_flow(scene, particles=True, progress=False)
    bx.validate(flow)
    assert flow.attrs["frame"] == "lab" and flow.sizes["rev_phase"] == 1
    sim = FlowSimulation(scene)  # the initial state of the same scene
    # mass and reference volume are carried by the particles: exactly conserved
    assert particles.sizes["particle"] == sim.particles.count
    assert particles["mass"].sum() == pytest.approx(sim.particles.mass.sum(), rel=1e-15)
    assert flow.attrs["material_volume_m3"] == pytest.approx(sim.particles.vol0.sum(), rel=1e-15)
    # no particle outside the vessel, and the averaged fill holds the material's volume
    assert (sim.vessel.sdf(particles["position"].values) <= 1e-12).all()
    # every sample deposits every particle's seeded volume: before clipping at 1 the
    # fill holds exactly the material's volume; clipping may only remove a little
    assert flow.attrs["fill_volume_before_clipping_m3"] == pytest.approx(
        flow.attrs["material_volume_m3"], rel=1e-12
    )
    cell_area = flow.attrs["solver_cell_m"] ** 2
    clipped = float(flow["fill"].mean("rev_phase").sum()) * cell_area
    assert 0.95 * flow.attrs["material_volume_m3"] < clipped
    assert clipped <= flow.attrs["material_volume_m3"] * (1 + 1e-12)
    # the attribute says what the stored (float32) fill holds
    assert flow.attrs["fill_volume_m3"] == pytest.approx(clipped, rel=1e-6)
    for key in (
        "periodicity_vx",
        "periodicity_vy",
        "periodicity_noise_vx",
        "particle_updates_per_s",
    ):
        assert math.isfinite(flow.attrs[key])
    mixed = bx.mix(flow, revolutions=0.5, cells=24, k1=0.01, progress=False)
    assert np.isfinite(mixed["rsd"]).all()


def test_phase_average_of_the_two_particle_halves_is_the_whole_average():
    # the noise estimate splits the particles into even and odd halves; their volumes and
    # momenta must add up to the single average exactly
    rng = np.random.default_rng(5)
    whole = PhaseAverager(np.zeros(3), (4, 3, 5), 0.1, 2)
    split = PhaseAverager(np.zeros(3), (4, 3, 5), 0.1, 2, halves=True)
    for k in (0, 1, 1):
        x = rng.uniform(0.0, 0.3, (501, 3))
        v = rng.normal(size=(501, 3))
        vol = rng.uniform(0.5, 1.5, 501) * 1e-4
        whole.add(k, x, v, vol)
        split.add(k, x, v, vol)
    fill, vel, raw = whole.fields()
    np.testing.assert_allclose(split.fields()[2], raw, rtol=1e-13)
    np.testing.assert_allclose(split.fields()[1], vel, rtol=1e-12, atol=1e-15)
    (_, vel_a, raw_a), (_, vel_b, raw_b) = split.half_fields()
    np.testing.assert_allclose(0.5 * (raw_a + raw_b), raw, rtol=1e-13)
    both = raw_a[..., None] * vel_a + raw_b[..., None] * vel_b
    np.testing.assert_allclose(both, 2.0 * raw[..., None] * vel, rtol=1e-11, atol=1e-15)
    assert np.abs(vel_a - vel_b).max() > 0.1  # the halves are different samples


def test_phase_averager_gives_volume_per_cell_and_the_volume_weighted_velocity():
    h, samples = 0.1, 4
    inside = np.ones((8, 7), np.int8)
    inside[6:] = 0  # a wall: the columns x >= 0.6 hold no material
    avg = PhaseAverager(np.zeros(2), (8, 7), h, 2, inside=inside)
    # a uniform lattice, two particles per cell and axis, over 0.1 <= x < 0.6, 0.1 <= y < 0.5
    axes = [(np.arange(10) + 2.5) * h / 2, (np.arange(8) + 2.5) * h / 2]
    block = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 2)
    vol = np.full(len(block), (h / 2) ** 2)
    v = np.tile([1.0, -2.0], (len(block), 1))
    lone = np.array([[0.62, 0.05]])  # just past the wall: kept by the cells inside
    for _ in range(samples):
        avg.add(avg.bin_of(0.98), block, v, vol)  # phase 0.98 lies in bin 0
        avg.add(avg.bin_of(0.5), lone, np.array([[0.5, 0.5]]), np.array([1e-3]))
    assert avg.samples.tolist() == [samples, samples]
    fill, vel, raw = avg.fields()
    # the B-splines reproduce the lattice's packing in the cells away from its edges
    np.testing.assert_allclose(raw[0, 2:4, 2:4], 1.0, rtol=1e-13)
    # every sample keeps each particle's whole volume, none of it in the wall column
    assert raw[0].sum() * h**2 == pytest.approx(vol.sum(), rel=1e-13)
    assert raw[1].sum() * h**2 == pytest.approx(1e-3, rel=1e-13)
    assert (raw[:, 6:] == 0.0).all()
    # a velocity shared by every particle is every filled cell's velocity
    for k, want in ((0, [1.0, -2.0]), (1, [0.5, 0.5])):
        got = vel[k][raw[k] > 0]
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), rtol=1e-13)
    assert (vel[0][raw[0] == 0] == 0.0).all()  # empty cells: no velocity
    # more material than a cell holds is clipped in the fill, kept in the raw fill
    centre = np.array([[0.25, 0.25]])
    avg.add(0, np.repeat(centre, 10, axis=0), np.zeros((10, 2)), np.full(10, 0.1))
    fill, _, raw = avg.fields()
    assert fill[0, 2, 2] == 1.0 and raw[0, 2, 2] > 1.0


def test_phase_bins_without_samples_are_refused():
    avg = PhaseAverager(np.zeros(2), (3, 2), 0.1, 4)
    avg.add(1, np.array([[0.05, 0.05]]), np.zeros((1, 2)), np.ones(1))
    assert not avg.complete()
    with pytest.raises(RuntimeError, match=r"phase bins \[0, 2, 3\] received no samples"):
        avg.fields()


def test_eq30_is_the_mean_relative_change_over_cells_with_material():
    rng = np.random.default_rng(11)
    v_prev = rng.uniform(0.5, 2.0, (3, 4, 5, 2)) * rng.choice([-1.0, 1.0], (3, 4, 5, 2))
    fill = np.ones((3, 4, 5))
    # a uniform 10 % change: 0.1 in both forms, for every component
    change = periodicity(v_prev, 1.1 * v_prev, fill, fill)
    for key in ("vx", "vy", "vx_norm", "vy_norm"):
        assert change[key] == pytest.approx(0.1, rel=1e-13)
    # cells with fill <= 0.5 in either revolution do not count, whatever they hold
    v_last = 1.1 * v_prev
    fill_prev, fill_last = fill.copy(), fill.copy()
    fill_prev[0, 0, 0], fill_last[1, 2, 3] = 0.5, 0.2
    v_last[0, 0, 0], v_last[1, 2, 3] = 1e3, -1e3
    assert periodicity(v_prev, v_last, fill_prev, fill_last)["vx"] == pytest.approx(0.1)
    # nor cells where |v| is under 5 % of the component's largest (eq. (30) divides by it)
    small = v_prev.copy()
    small[2, 1, 1, 0] = 1e-3
    v_last = 1.1 * small
    v_last[2, 1, 1, 0] = 1.0
    assert periodicity(small, v_last, fill, fill)["vx"] == pytest.approx(0.1, rel=1e-13)
    # hand-worked: two cells, x changes by 50 % and 0 %, y by 100 % and 25 %
    a = np.array([[[2.0, 1.0], [4.0, -4.0]]])
    b = np.array([[[3.0, 0.0], [4.0, -5.0]]])
    one = np.ones((1, 2))
    got = periodicity(a, b, one, one)
    assert got["vx"] == pytest.approx(0.25) and got["vy"] == pytest.approx(0.625)
    assert got["vx_norm"] == pytest.approx(1.0 / 6.0) and got["vy_norm"] == pytest.approx(0.4)


def test_lab_velocities_add_the_rigid_rotation_turned_to_each_phase():
    sim = FlowSimulation(drum_scene(0.4, rpm=10.0))
    n = 4
    shape = tuple(len(axis) for axis in sim.out_axes)
    lab = lab_velocities(sim.output, np.zeros((n, *shape, 2)))
    x, y = np.meshgrid(*sim.out_axes, indexing="ij")
    for k in range(n):
        # a point fixed in the vessel at (x, y) is at R(theta) (x, y) in the lab, where
        # it moves at omega e_z x R(theta) (x, y)
        theta = 2.0 * math.pi * k / n
        X = x * math.cos(theta) - y * math.sin(theta)
        Y = x * math.sin(theta) + y * math.cos(theta)
        np.testing.assert_allclose(lab[k, ..., 0], -sim.omega * Y, atol=1e-15)
        np.testing.assert_allclose(lab[k, ..., 1], sim.omega * X, atol=1e-15)


STATE = ("x", "v", "C", "stress", "gap", "vol", "J", "colour")


def _assert_same_flow(a, b):
    for name in a.data_vars:
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
    for key, value in a.attrs.items():
        if key.startswith("periodicity_") and not key.endswith("definition"):
            np.testing.assert_array_equal(value, b.attrs[key], err_msg=key)


@pytest.fixture(scope="module")
def uninterrupted_drum():
    """A 2-D drum run of two revolutions in one go, and the step half-way through its
    second revolution (while the phase bins of both revolutions are being filled)."""
    scene = drum_scene(0.4, revolutions=2)
    sim = FlowSimulation(scene)
    mark = sim.settings.settle_time + 1.5 * sim.period
    middle = []

    def note(s):
        if not middle and s.t >= mark:
            middle.append(s.steps)

    sim.run(progress=False, callback=note)
    return scene, sim, sim.dataset(wall=0.0), middle[0]


@pytest.mark.slow
def test_run_resumed_in_the_middle_of_a_recorded_revolution_is_the_same_run(
    tmp_path, uninterrupted_drum
):
    scene, whole, flow, middle = uninterrupted_drum
    path = tmp_path / "flow.ckpt.nc"
    first = FlowSimulation(scene)
    assert first.run(max_steps=middle, progress=False, checkpoint=path) == "max_steps"
    # half-way through revolution 2: revolution 1's averages done, 2's half filled
    assert first.recording == 2 and first.previous.complete()
    assert 0 < first.last.samples.sum() < whole.last.samples.sum()
    second = FlowSimulation(scene)
    second.load_checkpoint(path)
    assert second.steps == middle and second.t == first.t
    second.run(progress=False)
    assert second.steps == whole.steps and second.t == whole.t
    for name in STATE:
        np.testing.assert_array_equal(
            getattr(second.particles, name), getattr(whole.particles, name), err_msg=name
        )
    _assert_same_flow(flow, second.dataset(wall=0.0))


@pytest.mark.slow
def test_solve_flow_stopped_by_wall_time_resumes_to_the_same_flow(tmp_path, uninterrupted_drum):
    scene, whole, flow, _ = uninterrupted_drum
    budget = whole.wall_seconds / 5  # about five stops, wherever they fall
    path = tmp_path / "flow.ckpt.nc"
    stops = 0
    while True:
        try:
            resumed = solve_flow(scene, checkpoint=path, wall_time=budget, progress=False)
            break
        except RuntimeError as error:  # the checkpoint holds the state so far
            assert "stopped early (wall_time)" in str(error)
            assert path.exists()
            stops += 1
            assert stops < 1000
    assert stops >= 2  # wherever the stops fell, the same flow
    _assert_same_flow(flow, resumed)


@pytest.mark.slow
def test_every_revolution_is_compared_with_the_one_before(tmp_path):
    # eq. (30) between each two successive revolutions, as the paper's Table 3 gives it:
    # the entry of revolution 2 compares the averages of revolutions 1 and 2 as they
    # stood when revolution 2 ended; the last entry is the dataset's periodicity
    sim = FlowSimulation(drum_scene(0.4, revolutions=3))
    sim.run(until=sim.settings.settle_time + 2 * sim.period, progress=False)
    assert sim.recording == 2 and sim.history == []
    # the spin-up, reported by this row alone, takes a quarter of the samples
    spin_up, second = sim.previous.samples.sum(), sim.last.samples.sum()
    assert abs(spin_up - second / SPIN_UP_THINNING) <= 1
    expected = revolution_change(sim, sim.previous, sim.last)
    sim.run(progress=False)
    flow = sim.dataset(wall=0.0)
    np.testing.assert_array_equal(flow.attrs["periodicity_history_revolution"], [2, 3])
    for c in ("vx", "vy"):
        assert flow.attrs[f"periodicity_history_{c}"][0] == expected[c]
        assert flow.attrs[f"periodicity_history_{c}"][-1] == flow.attrs[f"periodicity_{c}"]
    assert expected["vx"] != flow.attrs["periodicity_vx"]
    # a resumed run carries the history on
    path = tmp_path / "flow.ckpt.nc"
    sim.save_checkpoint(path)
    again = FlowSimulation(drum_scene(0.4, revolutions=3))
    again.load_checkpoint(path)
    assert again.periodicity_history() == sim.periodicity_history()


def test_spin_up_courant_holds_until_revolution_1_ends_and_only_when_it_is_spin_up():
    # the stable step is linear in the Courant number: 0.8 doubles it while settling and
    # in revolution 1 of a three-revolution run, then the scene's courant takes over;
    # the sampling interval is the main courant's either way
    scene = drum_scene(0.4, revolutions=3)
    scene["solver"]["spin_up_courant"] = 0.8
    plain = FlowSimulation(drum_scene(0.4, revolutions=3))
    sim = FlowSimulation(scene)
    assert sim.spin_up_end() == pytest.approx(sim.settings.settle_time + sim.period)
    assert sim.stable_dt() == pytest.approx(2.0 * plain.stable_dt(), rel=1e-12)
    assert sim.sample_every == plain.sample_every
    sim.t = sim.spin_up_end()
    assert sim.courant_now() == sim.settings.courant
    # two revolutions: revolution 1 is the one compared with the kept one, not spin-up
    scene["solver"]["revolutions"] = 2
    assert FlowSimulation(scene).spin_up_end() == 0.0


def _by_revolution(scene, revolutions):
    """Run ``scene`` stopping at the end of every revolution; the run and, for each
    revolution, a copy of what the last phase averager held then (volume, momentum,
    samples), the parts summed."""
    sim = FlowSimulation(scene)
    held = {}
    for r in range(1, revolutions + 1):
        sim.run(until=sim.settings.settle_time + r * sim.period, progress=False)
        last = sim.last
        held[r] = (last.vol.sum(axis=1).copy(), last.mom.sum(axis=1).copy(), last.samples.copy())
    return sim, held


def _fields_of(*accumulated, cell_volume):
    vol = sum(a[0] for a in accumulated)
    mom = sum(a[1] for a in accumulated)
    samples = sum(a[2] for a in accumulated)
    fill = vol / (cell_volume * samples.reshape((-1,) + (1,) * (vol.ndim - 1)))
    with np.errstate(invalid="ignore", divide="ignore"):
        vel = np.where(vol[..., None] > 0, mom / vol[..., None], 0.0)
    return np.clip(fill, 0.0, 1.0), vel


def test_flow_averaged_over_revolutions_is_their_volume_weighted_mean():
    # the same run recorded revolution by revolution (average_revolutions = 1) gives each
    # revolution's sums; averaging two revolutions must give the pooled average of
    # revolutions 4 and 5, and eq. (30) must compare it with the pooled revolutions 2-3
    # (revolution 1, the spin-up of both runs, is sampled alike in both: thinned)
    scene = drum_scene(0.4, revolutions=5)
    scene["material"] = {"dilation_angle_deg": 0.0}  # past revolution 3 (no warning)
    single, held = _by_revolution(scene, 5)
    assert single.last.samples.sum() == held[5][2].sum()  # the last revolution alone
    scene["solver"]["average_revolutions"] = 2
    pooled, _ = _by_revolution(scene, 5)
    flow = pooled.dataset(wall=0.0)
    assert flow.attrs["averaged_revolutions"] == 2
    cell_volume = pooled.settings.output_cell**2
    fill, vel = _fields_of(held[4], held[5], cell_volume=cell_volume)
    np.testing.assert_allclose(flow["fill"].values, fill, rtol=1e-12, atol=1e-15)
    got = np.stack([flow["vx"].values, flow["vy"].values], axis=-1)
    np.testing.assert_allclose(got, vel, rtol=1e-10, atol=1e-14)
    before = _fields_of(held[2], held[3], cell_volume=cell_volume)
    expected = periodicity(before[1], vel, before[0], fill)  # a drum: lab frame already
    for c in ("vx", "vy"):
        assert flow.attrs[f"periodicity_{c}"] == pytest.approx(expected[c], rel=1e-9)
    np.testing.assert_array_equal(flow.attrs["periodicity_history_revolution"], [3, 5])


def test_averaging_more_revolutions_than_half_the_run_is_refused():
    scene = drum_scene(0.4, revolutions=3)
    scene["solver"]["average_revolutions"] = 2
    with pytest.raises(SceneError, match=r"solver\.average_revolutions = 2 .* <= "):
        FlowSimulation(scene)


@pytest.mark.parametrize("cells", [(7, 5), (6, 4, 5)])
@pytest.mark.parametrize("factor", [1, 2, 3])
def test_coarsened_fields_keep_material_and_momentum_and_match_block_sums(cells, factor):
    rng = np.random.default_rng(3)
    d = len(cells)
    fill = rng.uniform(0.0, 1.0, (2, *cells)) * (rng.uniform(size=(2, *cells)) > 0.3)
    vel = rng.normal(size=(2, *cells, d))
    coarse_fill, coarse_vel = coarsen_fields(fill, vel, factor)
    blocks = tuple(-(-n // factor) for n in cells)  # upper ends padded, nothing dropped
    assert coarse_fill.shape == (2, *blocks)
    # conservation: material volume and its momentum, per phase
    np.testing.assert_allclose(
        coarse_fill.sum(axis=tuple(range(1, d + 1))) * factor**d,
        fill.sum(axis=tuple(range(1, d + 1))),
        rtol=1e-13,
    )
    np.testing.assert_allclose(
        (coarse_vel * coarse_fill[..., None]).sum(axis=tuple(range(1, d + 1))) * factor**d,
        (vel * fill[..., None]).sum(axis=tuple(range(1, d + 1))),
        rtol=1e-12,
        atol=1e-12,
    )
    # each block, by a plain loop over its cells
    for block in np.ndindex(*blocks):
        sl = tuple(slice(b * factor, (b + 1) * factor) for b in block)
        volume = fill[(slice(None), *sl)].reshape(2, -1).sum(axis=1)
        flux = (vel * fill[..., None])[(slice(None), *sl)].reshape(2, -1, d).sum(axis=1)
        np.testing.assert_allclose(coarse_fill[(slice(None), *block)], volume / factor**d)
        want = np.where(volume[:, None] > 0, flux / np.where(volume > 0, volume, 1)[:, None], 0)
        np.testing.assert_allclose(coarse_vel[(slice(None), *block)], want, atol=1e-14)
    if factor == 1:
        np.testing.assert_array_equal(coarse_fill, fill)


def box_bed_scene(ndim, cell):
    return {
        "name": f"box-bed-{ndim}d",
        "vessel": {"kind": "box", "ndim": ndim, "size": [0.4] * ndim},
        "operation": {"rpm": 0.0, "duration": 0.1},
        "fill": {"box": [[-0.1, 0.1]] * ndim},
        "flow": {"cell": cell},
        "solver": {"settle_time": 0.0, "particles_per_cell": 3, "symmetry": "none"},
    }


@pytest.mark.parametrize("ndim, cell", [(2, 0.005), (3, 0.01)])
def test_occupied_volume_counts_the_particles_spacing(ndim, cell):
    sim = FlowSimulation(box_bed_scene(ndim, cell))
    # seeded: every cell inside the bed holds per_cell**d particles
    assert occupied_volume_over_seeded(sim) == 1.0
    # the same particles spread uniformly at random over a box 1.25 times the bed's
    # volume: the mean count inside falls by that factor (Poisson, 7 or more a cell, so
    # hardly a cell is empty; standard error under 1 %)
    rng = np.random.default_rng(5)
    side = 0.2 * 1.25 ** (1.0 / ndim)
    sim.particles.x[...] = rng.uniform(-side / 2, side / 2, sim.particles.x.shape)
    assert occupied_volume_over_seeded(sim) == pytest.approx(1.25, rel=0.03)
    # J says nothing of where the particles are
    assert sim.particles.volume_over_seeded == 1.0


def test_recording_past_revolution_3_with_dilation_warns():
    scene = drum_scene(0.4, revolutions=4)
    scene["material"] = {"dilation_angle_deg": 0.1}  # Table 1's
    with pytest.warns(UserWarning, match="dilation_angle_deg = 0.1 dilates"):
        FlowSimulation(scene)
    scene["material"] = {"dilation_angle_deg": 0.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        FlowSimulation(scene)  # no dilation: nothing to warn of
        FlowSimulation(drum_scene(0.4, revolutions=3))  # the paper's span and one more


def test_a_fill_that_clipping_left_short_of_the_material_warns():
    attrs = {"material_volume_m3": 2.0, "fill_clipped_max": 1.8, "stiffness_scaling": 100.0}
    with pytest.warns(UserWarning, match=r"holds 90\.0% of the bed's material.*1\.80 times"):
        _warn_of_clipped_fill({**attrs, "fill_volume_m3": 1.8})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _warn_of_clipped_fill({**attrs, "fill_volume_m3": 1.95})  # 2.5 % lost: no warning


def test_coarsening_refuses_a_bad_factor_or_shape():
    fill, vel = np.ones((1, 4, 4)), np.zeros((1, 4, 4, 2))
    with pytest.raises(ValueError, match="factor"):
        coarsen_fields(fill, vel, 0)
    with pytest.raises(ValueError, match="expected"):
        coarsen_fields(fill, vel[..., :1], 2)


@pytest.mark.slow
def test_checkpoint_of_another_scene_is_refused(tmp_path):
    path = tmp_path / "flow.ckpt.nc"
    FlowSimulation(drum_scene(0.4)).run(max_steps=5, progress=False, checkpoint=path)
    with pytest.raises(ValueError, match="another scene"):
        FlowSimulation(drum_scene(0.5)).load_checkpoint(path)


@pytest.mark.slow
def test_instability_stops_with_step_time_and_place(monkeypatch):
    sim = FlowSimulation(drum_scene(0.4))
    monkeypatch.setattr(sim, "stable_dt", lambda: 0.2)  # far beyond the elastic limit
    with pytest.raises(FlowBlowUpError, match=r"step \d+, t = .* s: particle \d+ at \("):
        sim.run(until=20.0, progress=False)


def test_a_non_finite_velocity_stops_the_run_naming_the_particle():
    sim = FlowSimulation(drum_scene(0.4))
    sim.particles.v[17, 1] = np.nan
    with pytest.raises(FlowBlowUpError, match=r"step 0, t = 0 s: particle 17 at \(.* speed nan"):
        sim._check_state()


def test_a_particle_off_the_grid_stops_the_run_naming_it():
    sim = FlowSimulation(drum_scene(0.4))
    sim.particles.x[5, 0] = sim.grid.origin[0] - 3 * sim.grid.h
    with pytest.raises(FlowBlowUpError, match=r"particle 5 at \(.*\) m left the background grid"):
        sim._check_state()


@pytest.mark.slow
@pytest.mark.parametrize(
    ("section", "key", "value", "fragment"),
    [
        ("material", "density", -1.0, "material.density"),
        ("material", "youngs_modulus", 0.0, "material.youngs_modulus"),
        ("material", "friction_angle_deg", 90.0, "material.friction_angle_deg"),
        ("fill", "fraction", 1.5, "fill.fraction"),
        ("operation", "rpm", -1.0, "operation.rpm"),
        ("flow", "cell", 1.0, "flow.cell"),
        ("material", "friction_angle_limit_deg", 20.0, "material.friction_angle_limit_deg"),
        ("material", "friction_angle_limit_deg", 95.0, "material.friction_angle_limit_deg"),
        ("solver", "density_projection", -1, "solver.density_projection"),
    ],
)
def test_out_of_range_scene_values_name_the_key(section, key, value, fragment):
    scene = drum_scene(0.4)
    scene.setdefault(section, {})[key] = value
    with pytest.raises(SceneError, match=fragment.replace(".", r"\.")):
        solve_flow(scene, progress=False)


def test_lost_contact_is_on_unless_the_scene_turns_it_off():
    scene = drum_scene(0.4)
    scene["solver"]["lost_contact"] = False
    assert FlowSimulation(scene).stress_arguments[7] == 0.0
    sim = FlowSimulation(drum_scene(0.4))
    # the inverse of a node's mass at the seeded packing: an interior node of the
    # freshly seeded bed holds exactly that mass after the first P2G
    sim.step(sim.stable_dt())
    g = sim.grid
    centre = tuple(
        np.argmin(np.abs(g.origin[a] + g.h * np.arange(n))) for a, n in enumerate(g.shape)
    )
    deep = (centre[0], centre[1] - round(0.04 / g.h))  # 40 mm below the drum's centre
    assert sim.stress_arguments[7] * g.mass[deep] == pytest.approx(1.0, rel=1e-9)


def test_mu_of_i_is_off_unless_the_scene_asks_for_it():
    assert FlowSimulation(drum_scene(0.4)).stress_arguments[8] == 0.0
    scene = drum_scene(0.4)
    scene.setdefault("material", {}).update(
        friction_angle_limit_deg=45.0, particle_diameter=0.002, packing_fraction=0.6
    )
    rise, i0, scale = FlowSimulation(scene).stress_arguments[8:]
    phi = math.radians(scene["material"].get("friction_angle_deg", 27.1))
    assert rise == pytest.approx(1.0 - math.tan(phi), rel=1e-14)
    assert i0 == 0.279
    density = scene["material"].get("density", 1500.0)
    assert scale == pytest.approx(0.002 * math.sqrt(density / 0.6), rel=1e-14)


def test_a_silo_discharges_through_its_slot_and_nothing_enters_its_floor():
    """The silo of the discharge benchmark, small: the bed drains through the slot into
    the bin, the bin's material lies under the slot, and no particle ends in a wall."""
    width, bin_h, fill, slot, cell = 0.08, 0.08, 0.06, 0.03, 0.005
    height = bin_h + fill + 0.02
    scene = {
        "name": "silo",
        "vessel": {
            "kind": "silo",
            "ndim": 2,
            "size": [width, height],
            "center": [0.0, height / 2],
            "orifice": slot,
            "floor_height": bin_h,
            "floor_thickness": 2 * cell,
        },  # fmt: skip
        "operation": {"rpm": 0.0, "duration": 0.25},
        "material": {"cohesion": 0.0},
        "fill": {"box": [[-width / 2, width / 2], [bin_h, bin_h + fill]]},
        "flow": {"cell": cell},
        "solver": {"stiffness_scaling": 100.0, "settle_time": 0.0},
    }
    sim = FlowSimulation(scene)
    sim.run(progress=False)
    x = sim.particles.x
    below = x[:, 1] < bin_h - 2 * cell
    assert 0.05 < below.mean() < 0.9
    # the stream falls straight from the slot: nothing has spread sideways beyond it yet
    # at the level of the floor's underside
    stream = below & (x[:, 1] > bin_h - 4 * cell)
    assert np.all(np.abs(x[stream, 0]) < slot / 2 + cell)
    assert np.max(sim.vessel.sdf(x)) < 0.25 * cell


@pytest.mark.parametrize("mirror", [False, True])
def test_particle_permutations_reorder_every_array_into_its_second_buffer(mirror):
    """The re-sort gathers each particle array into a spare and swaps the two: every
    array ends up as NumPy's fancy indexing would give it, no two share memory, and a
    particle count changed by a load makes fresh spares."""
    from blendxr.flow.state import Particles

    rng = np.random.default_rng(21)
    p = Particles(rng.uniform(-1.0, 1.0, (50, 3)), 1e-6, 1500.0, mirror=mirror)
    for name in p.fields:
        getattr(p, name)[...] = rng.standard_normal(getattr(p, name).shape)
    want = {name: a.copy() for name, a in p.arrays().items()}
    for _ in range(3):  # the third permutation writes into the first one's arrays
        order = rng.permutation(p.count)
        p.permute(order)
        want = {name: a[order] for name, a in want.items()}
        for name, a in p.arrays().items():
            np.testing.assert_array_equal(a, want[name])
            assert a.flags.c_contiguous
    arrays = list(p.arrays().values())
    assert not any(np.shares_memory(a, b) for i, a in enumerate(arrays) for b in arrays[i + 1 :])
    p.load({name: a[:20] for name, a in want.items()})
    order = rng.permutation(20)
    p.permute(order)
    for name, a in p.arrays().items():
        np.testing.assert_array_equal(a, want[name][:20][order])
