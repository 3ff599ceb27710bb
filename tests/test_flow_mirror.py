"""A bed mirror-symmetric about z = 0 solved as one half with an exact mirror plane.

Checked against the whole bed: the fold of the half's P2G equals the P2G of the bed and
its image (kernel level), and a Tote run by halves follows the same state as the whole
run, which itself keeps the symmetry to round-off (the run level). Then the fall-backs
(tilted vessel, asymmetric fill, 2-D), the refusal of an impossible request, and the
whole-bed outputs.
"""

from __future__ import annotations

import numpy as np
import pytest

from blendxr.flow import kernels
from blendxr.flow.solver import FlowSimulation, PhaseAverager, _particle_dataset
from blendxr.flow.walls import reflect_across_mirror
from blendxr.scene import SceneError, load_scene
from blendxr.vessels import fill_from_scene, vessel_from_scene

MIRROR = np.array([1.0, 1.0, -1.0])
FLIP = np.array([[1.0, 1.0, -1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]])  # R A R


def _half_bed(n, h, seed=3):
    """Random particles above z = 0 within 1.2 h of it (their stencils cross it)."""
    rng = np.random.default_rng(seed)
    x = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n),
                         rng.uniform(0.0, 1.2 * h, n)])  # fmt: skip
    v = rng.normal(0.0, 0.3, (n, 3))
    C = rng.normal(0.0, 2.0, (n, 3, 3))
    m = rng.uniform(0.5, 1.5, n) * 1e-3
    sigma = rng.normal(0.0, 1e3, (n, 3, 3))
    return x, v, C, m, m / 1500.0, sigma + sigma.transpose(0, 2, 1)


def _grid_of(x, v, C, m, vol, sigma, origin, h, shape):
    grids = np.zeros((1, *shape, 4))
    starts = kernels.chunk_starts(len(m), 1)
    kernels.p2g_3d(x, v, C, m, vol, sigma, origin, 1.0 / h, 1e-4, (0.0, 0.0), grids, starts)
    out_m, out_p = np.empty(shape), np.empty((*shape, 3))
    kernels.reduce_grids_3d(grids, out_m, out_p)
    return out_m, out_p


def test_folded_half_equals_the_p2g_of_the_bed_and_its_image():
    h, k0 = 0.02, 3
    x, v, C, m, vol, sigma = _half_bed(300, h)
    origin = np.array([-0.16, -0.16, -k0 * h])
    shape = (17, 17, 2 * k0 + 6)
    whole = [np.concatenate([a, a * f]) for a, f in ((x, MIRROR), (v, MIRROR), (C, FLIP))]
    whole_m, whole_p = _grid_of(
        *whole, np.tile(m, 2), np.tile(vol, 2), np.concatenate([sigma, sigma * FLIP]),
        origin, h, shape,
    )  # fmt: skip
    half_m, half_p = _grid_of(x, v, C, m, vol, sigma, origin, h, shape)
    kernels.fold_mirror_3d(half_m, half_p, k0)
    # the whole bed's grid, nodes 0 .. 2 k0 (symmetric about k0); above them only the
    # half contributes to both
    span = slice(0, 2 * k0 + 1)
    np.testing.assert_allclose(half_m[:, :, span], whole_m[:, :, span], rtol=1e-13,
                               atol=1e-13 * whole_m.max())  # fmt: skip
    np.testing.assert_allclose(half_p[:, :, span], whole_p[:, :, span], rtol=1e-12,
                               atol=1e-12 * np.abs(whole_p).max())  # fmt: skip
    assert np.all(half_p[:, :, k0, 2] == 0.0)


def test_reflection_puts_crossed_particles_back_as_their_images():
    rng = np.random.default_rng(4)
    x = rng.normal(0.0, 0.01, (50, 3))
    v, C, sigma = rng.normal(size=(50, 3)), rng.normal(size=(50, 3, 3)), rng.normal(size=(50, 3, 3))
    before = [a.copy() for a in (x, v, C, sigma)]
    below = x[:, 2] < 0.0
    count = reflect_across_mirror(
        x, v, C, sigma, 0.0, kernels.chunk_starts(50, 2), np.zeros((2, 4))
    )
    assert count == below.sum() > 0
    for new, old, f in zip((x, v, C, sigma), before, (MIRROR, MIRROR, FLIP, FLIP), strict=True):
        np.testing.assert_array_equal(new[below], old[below] * f)
        np.testing.assert_array_equal(new[~below], old[~below])


def _tote(symmetry, **solver):
    return {
        "name": "tote-mirror",
        "vessel": {"kind": "tote", "ndim": 3},
        "operation": {"rpm": 10.0},
        "fill": {"fraction": 0.4},
        "mixing": {"loading": "axial"},
        "flow": {"cell": 0.03, "phases": 4},
        "solver": {"stiffness_scaling": 100.0, "settle_time": 0.1, "revolutions": 2,
                   "symmetry": symmetry, **solver},
    }  # fmt: skip


def _image_of_grid(a):
    image = a[:, :, ::-1].copy()
    image[..., 2] *= -1.0
    return image


@pytest.mark.parametrize("projection", [0, 10], ids=["unprojected", "projected"])
def test_a_tote_by_halves_follows_the_whole_run_which_stays_symmetric(projection):
    # the step's mirror fold is exact; the density projection solves its Poisson problem
    # on the half grid, which stops its iterations at another iterate than the whole
    # grid's: the half then follows the whole to within the solve's tolerance
    whole = FlowSimulation(_tote("none", density_projection=projection))
    half = FlowSimulation(_tote("auto", density_projection=projection))
    assert half.mirror and not whole.mirror
    follows = 1e-9 if projection == 0 else half.projection.tol
    assert 2 * half.particles.count == whole.particles.count
    dt = whole.stable_dt()
    for _ in range(160):  # settling, then 0.28 s (a sixth of a revolution) of turning
        whole.step(dt)
        half.step(dt)
    assert whole.t > whole.settings.settle_time + 0.25
    v, scale = whole.grid.velocity, np.abs(whole.grid.velocity).max()
    assert scale > 0.02  # the bed moves in the vessel frame
    np.testing.assert_allclose(v, _image_of_grid(v), rtol=0, atol=1e-9 * scale)
    offset = round((half.grid.origin[2] - whole.grid.origin[2]) / whole.grid.h)
    upper = v[:, :, offset : offset + half.grid.shape[2]]
    np.testing.assert_allclose(half.grid.velocity, upper, rtol=0, atol=follows * scale)


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        ({"vessel": {"kind": "tote", "ndim": 3, "tilt_deg": 10.0}}, "vessel"),
        ({"fill": {"box": [[-0.1, 0.1], [-0.3, 0.0], [-0.1, 0.05]]}}, "seeded bed"),
        ({"vessel": {"kind": "drum", "ndim": 2, "diameter": 0.15}}, "2-D"),
    ],
    ids=["tilted", "asymmetric-fill", "2d"],
)
def test_asymmetric_scenes_run_whole_and_refuse_the_mirror(change, reason):
    scene = {**_tote("auto"), **change}
    assert not FlowSimulation(scene).mirror
    scene["solver"] = {**scene["solver"], "symmetry": "mirror-z"}
    with pytest.raises(SceneError, match=f"solver.symmetry.*{reason}"):
        FlowSimulation(scene)


def test_unknown_symmetry_names_the_key():
    with pytest.raises(SceneError, match="solver.symmetry"):
        FlowSimulation(_tote("xy"))


@pytest.mark.slow
def test_outputs_of_a_half_run_describe_the_whole_bed(tmp_path):
    scene = load_scene(_tote("auto", revolutions=2))
    sim = FlowSimulation(scene)
    seeded, _ = fill_from_scene(vessel_from_scene(scene), scene, 0.03)
    sim.run(max_steps=30, progress=False)
    particles = _particle_dataset(sim)
    n = sim.particles.count
    assert particles.sizes["particle"] == 2 * n == len(seeded)
    pos = particles["position"].values
    np.testing.assert_array_equal(pos[n:], pos[:n] * MIRROR)
    np.testing.assert_array_equal(particles["stress"].values[n:],
                                  particles["stress"].values[:n] * FLIP)  # fmt: skip
    # axial loading: species A at z < 0, all of it in the images
    colour = particles["colour"].values
    assert colour[:n].sum() == 0 and colour[n:].sum() == n
    assert "mirror_plane" in particles.attrs
    # a checkpoint keeps the images' colour
    sim.save_checkpoint(tmp_path / "c.nc")
    again = FlowSimulation(scene)
    again.load_checkpoint(tmp_path / "c.nc")
    np.testing.assert_array_equal(again.particles.image_colour, sim.particles.image_colour)


def test_phase_averages_of_a_half_bed_are_those_of_the_bed_and_its_image():
    rng = np.random.default_rng(5)
    h, shape = 0.02, (6, 5, 8)
    lower = np.array([-0.06, -0.05, -0.08])
    x = rng.uniform([-0.06, -0.05, 0.0], [0.06, 0.05, 0.08], (400, 3))
    v = rng.normal(size=(400, 3))
    vol = rng.uniform(1e-6, 2e-6, 400)
    whole = PhaseAverager(lower, shape, h, 2, halves=True)
    half = PhaseAverager(lower, shape, h, 2, halves=True, mirror=True)
    assert half.vol.shape[-1] == shape[2] // 2  # only the upper half accumulates
    for k in (0, 1):
        whole.add(k, np.concatenate([x, x * MIRROR]), np.concatenate([v, v * MIRROR]),
                  np.tile(vol, 2))  # fmt: skip
        half.add(k, x, v, vol)
    for got, want in zip(half.fields(), whole.fields(), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-15)
    with pytest.raises(ValueError, match="symmetric about z = 0"):
        PhaseAverager(lower + [0, 0, 0.01], shape, h, 2, mirror=True)
