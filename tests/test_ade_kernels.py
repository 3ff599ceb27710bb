"""ADE kernels: numba kernels against their NumPy twins and against independent facts.

Covers the Lax-Wendroff scheme of the paper (eq. (6)), the conservative bounded
finite-volume scheme, the stability limits and the shear diffusivity of eq. (5). Grids are
small so that the file runs in well under a minute including numba compilation.
"""

import collections
import math

import numba
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from blendxr.ade import kernels, reference, stability
from blendxr.ade.diffusivity import shear_diffusivity, shear_rates
from blendxr.ade.schemes import semi_lagrangian as sl
from blendxr.ade.stability import (
    diffusion_substeps,
    finite_volume_max_dt,
    lax_wendroff_max_dt,
    unsplit_diffusion_substeps,
)

SHAPES = {2: (40, 36), 3: (18, 16, 14)}
M_MIN = 1e-200  # below this m can underflow q to zero; such cells hold no colour


@pytest.fixture
def one_thread():
    """Run numba kernels on one thread for the duration of a test.

    Long runs on these tiny grids are dominated by waking the worker threads for every
    parallel loop (several per step), which gets slow on a loaded machine. The twin tests
    run on all threads and are the ones that would catch a race.
    """
    before = numba.get_num_threads()
    numba.set_num_threads(1)
    yield
    numba.set_num_threads(before)


def _smooth(rng, shape, sigma=1.5):
    return gaussian_filter(rng.normal(size=shape), sigma, mode="wrap")


def _blob_fill(rng, shape):
    """Smooth random fill in [0, 1] with empty outermost layer and a ragged surface."""
    f = _smooth(rng, shape, 2.0)
    f = (f - f.min()) / (f.max() - f.min())
    f = np.clip(1.6 * f - 0.3, 0.0, 1.0)
    edge = np.ones(shape, dtype=bool)
    edge[tuple(slice(1, n - 1) for n in shape)] = False
    f[edge] = 0.0
    return f


def _ball_vessel(shape, radius=0.85):
    axes = [np.linspace(-1.0, 1.0, n) for n in shape]
    grids = np.meshgrid(*axes, indexing="ij")
    r = np.sqrt(sum(g * g for g in grids))
    return (r < radius).astype(np.uint8), grids


def _fv_case(rng, ndim, courant=0.45, diffusion=True, tiny=True):
    """Closed random vessel, non-divergence-free flow, random m (with empty and tiny cells)."""
    shape = SHAPES[ndim]
    vessel, grids = _ball_vessel(shape)
    spacing = tuple(2.0 / (n - 1) * s for n, s in zip(shape, (1.0, 0.9, 1.1)[:ndim], strict=True))
    vel = [3.0 * _smooth(rng, shape) for _ in range(ndim)]
    dif = [0.05 * np.abs(_smooth(rng, shape)) * diffusion for _ in range(ndim)]
    m = np.where(vessel > 0, rng.uniform(0.0, 1.0, shape), 0.0)
    m[m < 0.15] = 0.0
    if tiny:
        m[(m > 0.0) & (m < 0.22)] = 1e-9
    m[grids[1] > 0.45] = 0.0  # a free surface
    c = rng.uniform(0.2, 0.7, shape)
    q = m * c
    dt = courant / 0.5 * finite_volume_max_dt(vel, spacing, vessel)
    return dict(m=m, q=q, vel=vel, dif=dif, vessel=vessel, spacing=spacing, dt=dt)


def _fv_kernel(ndim):
    return kernels.fv_step_2d if ndim == 2 else kernels.fv_step_3d


def _fv_run(case, steps, q=None, n_diff_sub=None):
    """Run the numba FV kernel, alternating the sweep order; yields (m, q) after each step."""
    m = case["m"].copy()
    q = (case["q"] if q is None else q).copy()
    shape = m.shape
    ndim = m.ndim
    if n_diff_sub is None:
        n_diff_sub = diffusion_substeps(case["dif"], case["spacing"], case["dt"])
    work = kernels.fv_workspace(shape)
    m_out = np.empty(shape)
    q_out = np.empty(shape)
    step = _fv_kernel(ndim)
    for n in range(steps):
        step(
            m, q, m_out, q_out, work, *case["vel"], *case["dif"], case["vessel"],
            case["dt"], *case["spacing"], n % 2 == 1, n_diff_sub,
        )  # fmt: skip
        m, m_out = m_out, m
        q, q_out = q_out, q
        yield m, q


def _last(states):
    return collections.deque(states, maxlen=1)[0]


def _concentration(m, q):
    out = np.empty_like(m)
    return kernels.concentration(m, q, out, M_MIN)


# ---------------------------------------------------------------------------------------
# numba kernels against their NumPy twins
# ---------------------------------------------------------------------------------------


def _lw_case(rng, ndim):
    shape = SHAPES[ndim]
    fill = _blob_fill(rng, shape)
    material = (fill >= 0.5).astype(np.uint8)
    spacing = (0.01, 0.012, 0.009)[:ndim]
    vel = [0.3 * _smooth(rng, shape) for _ in range(ndim)]
    dif = [1e-5 * np.abs(_smooth(rng, shape)) * (fill > 0) for _ in range(ndim)]
    dt = 0.8 * lax_wendroff_max_dt(vel, dif, spacing, material)
    c = rng.uniform(0.0, 1.0, shape)
    return c, vel, dif, material, fill, dt, spacing


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_matches_twin(ndim):
    rng = np.random.default_rng(10 + ndim)
    c, vel, dif, material, fill, dt, spacing = _lw_case(rng, ndim)
    interior = reference._interior_material(material)
    surface = (material > 0) & ~interior
    assert interior.sum() > 50 and surface.sum() > 50
    got = np.full_like(c, -1.0)
    want = np.full_like(c, -2.0)
    if ndim == 2:
        kernels.lw_step_2d(c, got, *vel, *dif, material, dt, *spacing)
        reference.lw_step_2d(c, want, *vel, *dif, material, dt, *spacing)
    else:
        kernels.lw_step_3d(c, got, *vel, *dif, material, dt, *spacing)
        reference.lw_step_3d(c, want, *vel, *dif, material, dt, *spacing)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert np.array_equal(got[~interior], c[~interior])
    # random data: the clipping is exercised as well
    unclipped = np.empty_like(c)
    if ndim == 2:
        reference.lw_step_2d(c, unclipped, *vel, *dif, material, dt, *spacing, clip=False)
    else:
        reference.lw_step_3d(c, unclipped, *vel, *dif, material, dt, *spacing, clip=False)
    assert ((unclipped < 0) | (unclipped > 1))[interior].any()

    surface_kernel = kernels.lw_free_surface_2d if ndim == 2 else kernels.lw_free_surface_3d
    surface_twin = reference.lw_free_surface_2d if ndim == 2 else reference.lw_free_surface_3d
    surface_kernel(got, material, fill)
    surface_twin(want, material, fill)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    changed = got != c
    assert changed[surface].sum() > 0.5 * surface.sum()
    assert not changed[material == 0].any()


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("reverse", [False, True])
@pytest.mark.parametrize("n_diff_sub", [0, 3])
def test_finite_volume_matches_twin(ndim, reverse, n_diff_sub):
    rng = np.random.default_rng(100 + 10 * ndim + 2 * reverse + n_diff_sub)
    case = _fv_case(rng, ndim)
    m, q, shape = case["m"], case["q"], case["m"].shape
    # every advection code path: both directions, empty upwind cells, walls, tiny m
    assert (m == 1e-9).any() and (m == 0).any()
    args = (*case["vel"], *case["dif"], case["vessel"], case["dt"], *case["spacing"])
    got_m, got_q = np.full(shape, np.nan), np.full(shape, np.nan)
    want_m, want_q = np.empty(shape), np.empty(shape)
    work = kernels.fv_workspace(shape)
    _fv_kernel(ndim)(m, q, got_m, got_q, work, *args, reverse, n_diff_sub)
    twin = reference.fv_step_2d if ndim == 2 else reference.fv_step_3d
    twin(m, q, want_m, want_q, None, *args, reverse, n_diff_sub)
    np.testing.assert_allclose(got_m, want_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_q, want_q, rtol=0, atol=1e-12)
    assert not np.array_equal(got_m, m)
    # a second step from the result, reusing the (now dirty) workspace
    again_m, again_q = np.empty(shape), np.empty(shape)
    _fv_kernel(ndim)(got_m, got_q, again_m, again_q, work, *args, not reverse, n_diff_sub)
    twin(want_m, want_q, want_m, want_q, None, *args, not reverse, n_diff_sub)
    np.testing.assert_allclose(again_m, want_m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(again_q, want_q, rtol=0, atol=1e-12)


def test_finite_volume_matches_twin_on_long_lines_with_many_substeps():
    """Lines longer than the kernel's row window, several blocks per sweep, 5 sub-steps."""
    rng = np.random.default_rng(150)
    shape = (45, 13, 38)
    vessel, grids = _ball_vessel(shape, radius=0.95)
    spacing = (0.05, 0.15, 0.06)
    vel = [3.0 * _smooth(rng, shape) for _ in range(3)]
    dif = [0.2 * np.abs(_smooth(rng, shape)) for _ in range(3)]
    m = np.where((vessel > 0) & (grids[1] < 0.3), rng.uniform(0.2, 1.0, shape), 0.0)
    q = m * rng.uniform(0.0, 1.0, shape)
    dt = 0.9 * finite_volume_max_dt(vel, spacing, vessel)
    n_sub = 5
    assert diffusion_substeps(dif, spacing, dt) <= n_sub
    args = (*vel, *dif, vessel, dt, *spacing)
    work = kernels.fv_workspace(shape)
    for reverse in (False, True):
        got_m, got_q = np.empty(shape), np.empty(shape)
        want_m, want_q = np.empty(shape), np.empty(shape)
        kernels.fv_step_3d(m, q, got_m, got_q, work, *args, reverse, n_sub)
        reference.fv_step_3d(m, q, want_m, want_q, None, *args, reverse, n_sub)
        np.testing.assert_allclose(got_m, want_m, rtol=0, atol=1e-12)
        np.testing.assert_allclose(got_q, want_q, rtol=0, atol=1e-12)
        assert not np.array_equal(got_q, q)


def _fv_steps_against_twin(m, q, vel, dif, vessel, spacing, steps=3):
    """Three steps (alternating sweep order) of the kernel and of its NumPy twin at 0.9 of
    the stable dt, compared after each; returns the kernel's last (m, q)."""
    shape = m.shape
    dt = 0.9 * finite_volume_max_dt(vel, spacing, vessel)
    n_sub = max(1, diffusion_substeps(dif, spacing, dt))
    args = (*vel, *dif, vessel, dt, *spacing)
    step = _fv_kernel(m.ndim)
    twin = reference.fv_step_2d if m.ndim == 2 else reference.fv_step_3d
    got = (m, q)
    want = (m, q)
    for n in range(steps):
        out = (np.empty(shape), np.empty(shape))
        step(*got, *out, kernels.fv_workspace(shape), *args, n % 2 == 1, n_sub)
        got = out
        want = twin(*want, np.empty(shape), np.empty(shape), None, *args, n % 2 == 1, n_sub)
        np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-12)
    return got


def _ball_with_band(rng, ndim):
    """A ball vessel closed at both x ends, smooth random velocity and diffusivity, and a
    band of cells across its middle: (shape, vessel, spacing, vel, dif, band)."""
    shape = (30, 26, 22)[:ndim]
    vessel, grids = _ball_vessel(shape, radius=1.2)
    vessel[(0, -1), ...] = 0
    spacing = (0.1,) * ndim
    vel = [2.0 * _smooth(rng, shape) for _ in range(ndim)]
    dif = [0.05 * np.abs(_smooth(rng, shape)) for _ in range(ndim)]
    band = sum(np.abs(g) for g in grids) < 0.5
    return shape, vessel, spacing, vel, dif, band


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_matches_twin_with_material_in_a_band(ndim):
    """Material away from every edge: the kernel works on windows around it."""
    rng = np.random.default_rng(140 + ndim)
    shape, vessel, spacing, vel, dif, band = _ball_with_band(rng, ndim)
    m = np.where(band & (vessel > 0), rng.uniform(0.3, 1.0, shape), 0.0)
    q = m * rng.uniform(0.0, 1.0, shape)
    got = _fv_steps_against_twin(m, q, vel, dif, vessel, spacing)
    assert (got[0][~band] > 0).any()  # material left the band


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_leaves_material_outside_the_support_as_it_is(ndim):
    """Material the flow left behind (m > 0 where the support is 0) takes no flux and no
    diffusion: it comes out unchanged, and everything else matches the twin (the kernel
    makes its windows around movable material only)."""
    rng = np.random.default_rng(150 + ndim)
    shape, vessel, spacing, vel, dif, band = _ball_with_band(rng, ndim)
    m = np.where(vessel > 0, rng.uniform(0.3, 1.0, shape), 0.0)
    support = (vessel > 0) & (band | (rng.uniform(size=shape) > 0.6))
    stranded = (m > 0) & ~support  # material where the flow no longer is
    assert stranded.sum() > 100 and (m > 0)[support].sum() > 100
    support = support.astype(np.uint8)
    q = m * rng.uniform(0.0, 1.0, shape)
    got = _fv_steps_against_twin(m, q, vel, dif, support, spacing)
    assert np.array_equal(got[0][stranded], m[stranded])
    assert np.array_equal(got[1][stranded], q[stranded])


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_same_bits_on_any_thread_count(ndim):
    """How the sweeps are split between threads changes no bit of the result."""
    rng = np.random.default_rng(160 + ndim)
    case = _fv_case(rng, ndim)
    before = numba.get_num_threads()
    results = []
    try:
        for threads in sorted({1, min(2, numba.config.NUMBA_NUM_THREADS), before}):
            numba.set_num_threads(threads)
            results.append(_last(_fv_run(case, 4)))
    finally:
        numba.set_num_threads(before)
    for m, q in results[1:]:
        np.testing.assert_array_equal(m, results[0][0])
        np.testing.assert_array_equal(q, results[0][1])


@pytest.mark.parametrize("ndim", [2, 3])
@pytest.mark.parametrize("material", ["everywhere", "band", "stranded"])
def test_finite_volume_in_place_is_the_same_bits_as_into_other_arrays(ndim, material):
    """In place (m_out is m) every sweep reads its block into scratch before writing it:
    the same bits as steps into other arrays, over steps with both sweep orders, and the
    cells away from material, never touched, unchanged (with material left outside the
    support, which the windows skip)."""
    rng = np.random.default_rng(190 + 3 * ndim + len(material))
    if material == "everywhere":
        case = _fv_case(rng, ndim)
        vessel, m, q = case["vessel"], case["m"], case["q"]
        vel, dif, spacing, dt = case["vel"], case["dif"], case["spacing"], case["dt"]
    else:
        shape, vessel, spacing, vel, dif, band = _ball_with_band(rng, ndim)
        inside = np.where(vessel > 0, rng.uniform(0.3, 1.0, shape), 0.0)
        m = np.where(band, inside, 0.0) if material == "band" else inside
        if material == "stranded":
            vessel = ((vessel > 0) & (band | (rng.uniform(size=shape) > 0.6))).view(np.uint8)
        q = m * rng.uniform(0.0, 1.0, shape)
        dt = 0.9 * finite_volume_max_dt(vel, spacing, vessel)
    n_sub = max(1, diffusion_substeps(dif, spacing, dt))
    args = (*vel, *dif, vessel, dt, *spacing)
    step = _fv_kernel(ndim)
    work = kernels.fv_workspace(m.shape)
    into = (m.copy(), q.copy())
    same = (m.copy(), q.copy())
    for n in range(4):
        out = (np.empty(m.shape), np.empty(m.shape))
        step(*into, *out, work, *args, n % 2 == 1, n_sub)
        into = out
        step(*same, *same, work, *args, n % 2 == 1, n_sub)
        np.testing.assert_array_equal(same[0], into[0])
        np.testing.assert_array_equal(same[1], into[1])
    assert not np.array_equal(same[0], m)


def test_finite_volume_refuses_outputs_that_overlap_the_inputs():
    rng = np.random.default_rng(171)
    case = _fv_case(rng, 2)
    m, q = case["m"].copy(), case["q"].copy()
    args = (*case["vel"], *case["dif"], case["vessel"], case["dt"], *case["spacing"], False, 0)
    work = kernels.fv_workspace(m.shape)
    with pytest.raises(ValueError, match="together"):
        kernels.fv_step_2d(m, q, m, np.empty(m.shape), work, *args)
    with pytest.raises(ValueError, match="overlap"):
        kernels.fv_step_2d(m, q, q, m, work, *args)


def test_finite_volume_rejects_strided_arrays():
    rng = np.random.default_rng(170)
    case = _fv_case(rng, 2)
    shape = case["m"].shape
    strided = np.empty((shape[0], 2 * shape[1]))[:, ::2]
    with pytest.raises(ValueError, match="C-contiguous"):
        kernels.fv_step_2d(
            case["m"], case["q"], strided, np.empty(shape), kernels.fv_workspace(shape),
            *case["vel"], *case["dif"], case["vessel"], case["dt"], *case["spacing"], False, 0,
        )  # fmt: skip


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_ignores_coefficients_of_other_cells(ndim):
    """The stencil may read coefficients of surface cells in a row; they must not leak."""
    rng = np.random.default_rng(180 + ndim)
    c, vel, dif, material, fill, dt, spacing = _lw_case(rng, ndim)
    plan = kernels.LaxWendroffPlan(c.shape)
    plan.coef[...] = np.nan
    plan.classify(material)
    plan.coefficients(vel, dif, dt, spacing)
    got = c.copy()
    plan.apply(c, got)
    want = np.empty_like(c)
    twin = reference.lw_step_2d if ndim == 2 else reference.lw_step_3d
    twin(c, want, *vel, *dif, material, dt, *spacing)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_coefficients_of_a_blend_are_those_of_the_blended_fields(ndim):
    """Blending inside the coefficient kernel gives the coefficients of the fields blended
    beforehand (a + w (b - a), the same operations), bit for bit, and the step they make
    is the reference twin's step on the blended fields."""
    rng = np.random.default_rng(170 + ndim)
    c, vel_a, dif_a, material, fill, dt, spacing = _lw_case(rng, ndim)
    _, vel_b, dif_b, _, _, _, _ = _lw_case(np.random.default_rng(175 + ndim), ndim)
    stack_a, stack_b = np.stack(vel_a), np.stack(vel_b)
    dstack_a, dstack_b = np.stack(dif_a), np.stack(dif_b)
    w = 0.37
    vel = stack_a + w * (stack_b - stack_a)
    dif = dstack_a + w * (dstack_b - dstack_a)
    # the blend's own stable step (the twin's limit on the blended fields)
    dt = 0.8 * lax_wendroff_max_dt(tuple(vel), tuple(dif), spacing, material)
    between = kernels.LaxWendroffPlan(c.shape)
    blended = kernels.LaxWendroffPlan(c.shape)
    for plan in (between, blended):
        plan.classify(material)
    between.coefficients_between(stack_a, stack_b, dstack_a, dstack_b, w, dt, spacing)
    blended.coefficients(tuple(vel), tuple(dif), dt, spacing)
    interior = between.cls == kernels.LW_INTERIOR
    assert interior.sum() > 50
    assert np.array_equal(between.coef[:, interior], blended.coef[:, interior])
    got = c.copy()
    between.apply(c, got)
    want = np.empty_like(c)
    twin = reference.lw_step_2d if ndim == 2 else reference.lw_step_3d
    twin(c, want, *vel, *dif, material, dt, *spacing)
    np.testing.assert_allclose(got[interior], want[interior], rtol=0, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_plan_surface_follows_fill_and_classification(ndim):
    """The plan keeps the inward steps between calls; a new fill or a new
    classification must be taken into account."""
    rng = np.random.default_rng(190 + ndim)
    shape = SHAPES[ndim]
    twin = reference.lw_free_surface_2d if ndim == 2 else reference.lw_free_surface_3d
    plan = kernels.LaxWendroffPlan(shape)
    fill = _blob_fill(rng, shape)
    out = rng.uniform(0.0, 1.0, shape)
    for change in ("start", "other array", "same array, reclassified"):
        if change == "other array":
            # same material, other normals
            fill = np.where(fill >= 0.5, 0.5 + 0.5 * rng.uniform(size=shape), fill)
        elif change == "same array, reclassified":
            fill[...] = _blob_fill(rng, shape)
        if change != "other array":
            plan.classify((fill >= 0.5).astype(np.uint8))
        for _ in range(2):
            out = rng.uniform(0.0, 1.0, shape)
            want = twin(out.copy(), (fill >= 0.5).astype(np.uint8), fill)
            plan.surface(out, fill)
            np.testing.assert_allclose(out, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_concentration_matches_twin(ndim):
    rng = np.random.default_rng(7)
    case = _fv_case(rng, ndim)
    got = kernels.concentration(case["m"], case["q"], np.empty(case["m"].shape), 1e-6)
    want = reference.concentration(case["m"], case["q"], np.empty(case["m"].shape), 1e-6)
    np.testing.assert_array_equal(np.isnan(got), case["m"] <= 1e-6)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_fv_transport_velocity_matches_twin(ndim):
    rng = np.random.default_rng(31)
    shape = SHAPES[ndim]
    for axis in range(ndim):
        v = _smooth(rng, shape)
        for cap in (1.0, 1.25):
            got = kernels.fv_transport_velocity(v, np.empty(shape), axis, 0.3, 0.1, cap)
            want = reference.fv_transport_velocity(v, axis, 0.3, 0.1, cap)
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def _sl_case(rng, ndim, courant=3.0):
    """A ragged bed in a (nx, ny, nz) array (nz = 1 in 2-D), a smooth flow of up to
    ``courant`` cells per step, random c."""
    shape = SHAPES[ndim] + (1,) * (3 - ndim)
    fill = _blob_fill(rng, SHAPES[ndim]).reshape(shape)
    material = (fill >= 0.5).astype(np.uint8)
    spacing = (0.01, 0.012, 0.009)[:ndim] + (1.0,) * (3 - ndim)
    vel = [_smooth(rng, shape) if axis < ndim else np.zeros(shape) for axis in range(3)]
    dt = courant / max(np.abs(v).max() / h for v, h in zip(vel, spacing, strict=True))
    dif = [1e-5 * np.abs(_smooth(rng, shape)) if axis < ndim else np.zeros(shape)
           for axis in range(3)]  # fmt: skip
    c = rng.uniform(0.0, 1.0, shape)
    return dict(c=c, vel=vel, dif=dif, material=material, dt=dt, spacing=spacing)


def _sl_core(material):
    core = np.empty_like(material)
    sl.sl_core(material, core, np.empty_like(material))
    return core


@pytest.mark.parametrize("ndim", [2, 3])
def test_semi_lagrangian_matches_twin(ndim):
    rng = np.random.default_rng(300 + ndim)
    case = _sl_case(rng, ndim)
    c, material = case["c"], case["material"]
    core = _sl_core(material)
    np.testing.assert_array_equal(core, reference.sl_core(material))
    assert 0 < core.sum() < material.sum()  # both branches of the sample are taken
    got, want = np.empty_like(c), np.empty_like(c)
    args = (*case["vel"], material, core, case["dt"], *case["spacing"])
    sl.sl_advect(c, got, *args)
    reference.sl_advect(c, want, *args)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert (got != c)[material == 1].mean() > 0.9
    r = [1e3 if axis < ndim else 0.0 for axis in range(3)]
    sl.sl_diffuse(c, got, *case["dif"], material, *r)
    reference.sl_diffuse(c, want, *case["dif"], material, *r)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


@pytest.mark.parametrize("shift", [(1, 0, 0), (2, -1, 0), (3, 1, -2)])
def test_semi_lagrangian_whole_cell_shift_is_exact(shift):
    """A uniform flow moving c by whole cells in one step: every departure point is a
    cell centre, so the step is the exact shift (interpolation at a node is the node)."""
    rng = np.random.default_rng(7)
    shape = (20, 18, 16)
    spacing = (0.01, 0.02, 0.015)
    dt = 0.5
    vel = [np.full(shape, s * h / dt) for s, h in zip(shift, spacing, strict=True)]
    material = np.ones(shape, np.uint8)
    c = rng.uniform(size=shape)
    out = np.empty_like(c)
    sl.sl_advect(c, out, *vel, material, _sl_core(material), dt, *spacing)
    inner = tuple(slice(4, n - 4) for n in shape)
    source = tuple(slice(4 - s, n - 4 - s) for s, n in zip(shift, shape, strict=True))
    np.testing.assert_allclose(out[inner], c[source], rtol=0, atol=1e-13)


@pytest.mark.parametrize("ndim", [2, 3])
def test_semi_lagrangian_is_bounded_keeps_constants_and_leaves_empty_cells(ndim):
    rng = np.random.default_rng(40 + ndim)
    case = _sl_case(rng, ndim, courant=4.0)
    material = case["material"]
    args = (*case["vel"], material, _sl_core(material), case["dt"], *case["spacing"])
    out = np.empty_like(case["c"])
    sl.sl_advect(case["c"], out, *args)
    assert out.min() >= case["c"].min() and out.max() <= case["c"].max()
    np.testing.assert_array_equal(out[material == 0], case["c"][material == 0])
    constant = np.full_like(case["c"], 0.37)
    sl.sl_advect(constant, out, *args)
    np.testing.assert_allclose(out, 0.37, rtol=0, atol=1e-15)


def test_semi_lagrangian_rates_hand_values():
    """Simple shear v_x = g y plus a constant v_y: the largest speed in cells per second
    and the velocity jump between neighbours in cells per second, g hy / hx; cells without
    material do not count."""
    shape = (10, 12, 1)
    hx, hy = 0.02, 0.01
    g, vy = 3.0, -0.05
    y = (np.arange(shape[1]) * hy).reshape(1, -1, 1)
    vel = np.stack([np.broadcast_to(g * y, shape), np.full(shape, vy)])
    material = np.ones(shape, np.uint8)
    material[:, -1] = 0  # the fastest row is empty
    fast = vel.copy()
    fast[0, :, -1] = 1e3  # and what it holds does not count
    speed, jump = sl.sl_max_rates(fast, vel, material, np.array([1 / hx, 1 / hy]))
    assert speed == pytest.approx(max(g * (shape[1] - 2) * hy / hx, abs(vy) / hy), rel=1e-12)
    assert jump == pytest.approx(g * hy / hx, rel=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_semi_lagrangian_diffusion_conserves_and_is_bounded_at_its_limit(ndim):
    """Flux form between material cells: the material's colour sum is kept to round-off,
    and at dt_sub * sum_k 2 max(D_kk) / h_k^2 = 1 every update is a convex combination."""
    rng = np.random.default_rng(60 + ndim)
    case = _sl_case(rng, ndim)
    material = case["material"]
    dif, spacing = case["dif"], case["spacing"]
    # the scheme's rule: each axis at its largest diffusivity
    rate = sum(2 * d.max() / h**2 for d, h in zip(dif[:ndim], spacing[:ndim], strict=True))
    r = [1.0 / rate / h**2 if axis < ndim else 0.0 for axis, h in enumerate(spacing)]
    c = case["c"].copy()
    out = np.empty_like(c)
    inside = material == 1
    total = c[inside].sum()
    for _ in range(50):
        sl.sl_diffuse(c, out, *dif, material, *r)
        assert out[inside].min() >= c[inside].min() - 1e-15
        assert out[inside].max() <= c[inside].max() + 1e-15
        c, out = out, c
    assert abs(c[inside].sum() - total) <= 1e-11 * total
    assert c[inside].std() < 0.8 * case["c"][inside].std()  # it diffuses


# ---------------------------------------------------------------------------------------
# finite volume: conservation, bounds, symmetry
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_conserves_and_stays_bounded(ndim, one_thread):
    rng = np.random.default_rng(20 + ndim)
    case = _fv_case(rng, ndim)
    assert diffusion_substeps(case["dif"], case["spacing"], case["dt"]) >= 1
    outside = case["vessel"] == 0
    m0, q0 = case["m"].sum(), case["q"].sum()
    c0 = _concentration(case["m"], case["q"])
    lo, hi = np.nanmin(c0), np.nanmax(c0)
    steps = 0
    for m, q in _fv_run(case, 200):
        steps += 1
        assert abs(m.sum() - m0) <= 1e-12 * m0
        assert abs(q.sum() - q0) <= 1e-12 * q0
        assert m.min() >= 0.0
        assert not m[outside].any() and not q[outside].any()
        c = _concentration(m, q)
        assert np.nanmin(c) >= lo - 1e-12 and np.nanmax(c) <= hi + 1e-12
    assert steps == 200
    # the flow really moved material around (compressible: m piles up in places)
    assert np.abs(m - case["m"]).max() > 0.5


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_colour_swap_symmetry(ndim, one_thread):
    rng = np.random.default_rng(30 + ndim)
    case = _fv_case(rng, ndim)
    swapped = case["m"] - case["q"]
    for (m1, q1), (m2, q2) in zip(_fv_run(case, 30), _fv_run(case, 30, q=swapped), strict=True):
        np.testing.assert_array_equal(m1, m2)
        np.testing.assert_allclose(q2, m1 - q1, rtol=0, atol=1e-12 * m1.max())


@pytest.mark.parametrize("ndim", [2, 3])
def test_finite_volume_keeps_constant_colour(ndim, one_thread):
    rng = np.random.default_rng(40 + ndim)
    case = _fv_case(rng, ndim)
    c0 = 0.37
    for m, q in _fv_run(case, 60, q=c0 * case["m"]):
        c = _concentration(m, q)
        assert np.nanmax(np.abs(c - c0)) <= 1e-13


def test_finite_volume_walls_block_flux_and_diffusion(one_thread):
    shape = (24, 20)
    vessel = np.zeros(shape, dtype=np.uint8)
    vessel[1:-1, 1:-1] = 1
    vessel[12, :] = 0  # an internal wall across x
    m = np.zeros(shape)
    m[2:12, 1:-1] = 1.0
    q = m * np.linspace(0.0, 1.0, shape[1])[None, :]
    case = dict(
        m=m,
        q=q,
        vel=[np.full(shape, 0.5), np.full(shape, 0.2)],
        dif=[np.full(shape, 0.05), np.full(shape, 0.05)],
        vessel=vessel,
        spacing=(0.1, 0.1),
        dt=0.08,
    )
    m_new, q_new = _last(_fv_run(case, 50))
    assert not m_new[12:].any() and not q_new[12:].any()
    assert math.isclose(m_new.sum(), m.sum(), rel_tol=1e-13)
    # the flow compresses the material against the wall (and the upper boundary)
    assert m_new[11].max() > 2.0


def test_finite_volume_is_second_order_on_smooth_translation(one_thread):
    def error(n):
        shape = (n + 2, n + 2)
        x = (np.arange(n + 2) - 0.5) / n
        gx, gy = np.meshgrid(x, x, indexing="ij")

        def profile(px, py):
            return 0.2 + 0.6 * np.exp(-((px - 0.35) ** 2 + (py - 0.35) ** 2) / 0.01)

        vessel = np.zeros(shape, dtype=np.uint8)
        vessel[1:-1, 1:-1] = 1
        m = vessel.astype(float)
        u, h, t_end = 0.3, 1.0 / n, 1.0
        vel = [np.full(shape, u), np.full(shape, u)]
        dt = 0.8 * finite_volume_max_dt(vel, (h, h), vessel)
        steps = math.ceil(t_end / dt)
        case = dict(
            m=m,
            q=m * profile(gx, gy),
            vel=vel,
            dif=[np.zeros(shape)] * 2,
            vessel=vessel,
            spacing=(h, h),
            dt=t_end / steps,
        )
        m_new, q_new = _last(_fv_run(case, steps, n_diff_sub=0))
        c = _concentration(m_new, q_new)
        return np.abs(c - profile(gx - u * t_end, gy - u * t_end))[1:-1, 1:-1].mean()

    coarse, fine = error(30), error(60)
    assert fine < 0.01
    assert coarse / fine > 3.0


# ---------------------------------------------------------------------------------------
# Lax-Wendroff: consistency with the PDE
# ---------------------------------------------------------------------------------------


def _lw(ndim):
    return kernels.lw_step_2d if ndim == 2 else kernels.lw_step_3d


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_keeps_constant_field(ndim):
    rng = np.random.default_rng(50 + ndim)
    c, vel, dif, material, fill, dt, spacing = _lw_case(rng, ndim)
    c = np.full_like(c, 0.3)
    out = np.empty_like(c)
    _lw(ndim)(c, out, *vel, *dif, material, dt, *spacing)
    surface = kernels.lw_free_surface_2d if ndim == 2 else kernels.lw_free_surface_3d
    surface(out, material, fill)
    np.testing.assert_allclose(out, 0.3, rtol=0, atol=1e-15)


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_uniform_x_flow_is_classical_1d_scheme(ndim):
    rng = np.random.default_rng(60 + ndim)
    shape = SHAPES[ndim]
    spacing = (0.01, 0.02, 0.015)[:ndim]
    nu, dt = 0.35, 0.05
    vel = [np.full(shape, nu * spacing[0] / dt)] + [np.zeros(shape)] * (ndim - 1)
    dif = [np.zeros(shape)] * ndim
    material = np.ones(shape, dtype=np.uint8)
    c = rng.uniform(0.2, 0.8, shape)
    out = np.empty_like(c)
    _lw(ndim)(c, out, *vel, *dif, material, dt, *spacing)
    cm, c0, cp = c[:-2], c[1:-1], c[2:]
    classical = c0 - 0.5 * nu * (cp - cm) + 0.5 * nu**2 * (cp - 2.0 * c0 + cm)
    inner = (slice(1, -1),) * ndim
    np.testing.assert_allclose(out[inner], classical[(slice(None),) + inner[1:]], atol=1e-14)


def _periodic_field(shape, spacing, shift=(0.0, 0.0, 0.0)):
    axes = [(np.arange(n) - s / h) * h for n, h, s in zip(shape, spacing, shift, strict=False)]
    g = np.meshgrid(*axes, indexing="ij")
    k = 2.0 * np.pi
    phase = k * g[0] + 2.0 * k * g[1] + (-k * g[2] if len(g) == 3 else 0.0)
    return 0.5 + 0.2 * np.sin(phase) + 0.1 * np.cos(k * (g[0] - g[1]))


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_one_step_error_is_third_order(ndim):
    """Exact translation: the local error of a second-order step falls as h**3.

    A sign error in a cross term would leave an O(h**2) local error (ratio 4, not 8).
    """

    def one_step_error(n):
        shape = (n + 2,) * ndim
        spacing = (1.0 / n,) * ndim
        velocity = (0.7, -0.5, 0.6)[:ndim]
        dt = 0.12 / n / max(abs(v) for v in velocity)
        vel = [np.full(shape, v) for v in velocity]
        dif = [np.zeros(shape)] * ndim
        c = _periodic_field(shape, spacing)
        out = np.empty_like(c)
        _lw(ndim)(c, out, *vel, *dif, np.ones(shape, np.uint8), dt, *spacing)
        exact = _periodic_field(shape, spacing, tuple(v * dt for v in velocity))
        inner = (slice(1, -1),) * ndim
        return np.abs(out - exact)[inner].max()

    ratio = one_step_error(8) / one_step_error(16)
    assert 6.5 < ratio < 10.0


def test_lax_wendroff_one_step_error_is_third_order_in_rotation():
    """Solid-body rotation, a velocity that varies in space: local error O(h**3).

    Without the (v . grad) v part of c_tt the local error is O(dt**2), ratio 4.
    """
    omega = 1.0

    def blob(x, y):
        return np.exp(-((x - 0.3) ** 2 + y**2) / (2 * 0.15**2))

    def one_step_error(n):
        h = 2.0 / n
        axis = -1.0 + h * (np.arange(n + 2) - 0.5)
        x, y = np.meshgrid(axis, axis, indexing="ij")
        vx, vy = -omega * y, omega * x
        dt = 0.4 * h / (omega * 1.5)
        zeros = np.zeros_like(x)
        c = blob(x, y)
        out = np.empty_like(c)
        kernels.lw_step_2d(c, out, vx, vy, zeros, zeros, np.ones(c.shape, np.uint8), dt, h, h)
        back = -omega * dt  # the exact solution is the field rotated by omega dt
        exact = blob(np.cos(back) * x - np.sin(back) * y, np.sin(back) * x + np.cos(back) * y)
        inner = (np.abs(x) < 0.8) & (np.abs(y) < 0.8)
        return np.abs(out - exact)[inner].max()

    ratio = one_step_error(32) / one_step_error(64)
    assert 6.5 < ratio < 10.0, ratio


def test_lax_wendroff_diffusivity_gradient_term():
    """Tiny steps: (c_new - c) / dt tends to d/dx(D_xx dc/dx) + d/dy(D_yy dc/dy)."""

    def residual(n):
        shape = (n + 2, n + 2)
        h = 1.0 / n
        x = (np.arange(n + 2) - 0.5) * h
        gx, gy = np.meshgrid(x, x, indexing="ij")
        k = 2.0 * np.pi
        d0 = 1e-3
        dxx = d0 * (1.0 + gx)
        dyy = d0 * (1.0 + 0.5 * gy)
        c = 0.5 + 0.3 * np.sin(k * gx) * np.cos(k * gy)
        c_x = 0.3 * k * np.cos(k * gx) * np.cos(k * gy)
        c_y = -0.3 * k * np.sin(k * gx) * np.sin(k * gy)
        c_xx = c_yy = -k * k * (c - 0.5)
        rhs = d0 * c_x + dxx * c_xx + 0.5 * d0 * c_y + dyy * c_yy
        dt = 1e-4 * h * h / d0
        zero = np.zeros(shape)
        out = np.empty_like(c)
        kernels.lw_step_2d(c, out, zero, zero, dxx, dyy, np.ones(shape, np.uint8), dt, h, h)
        inner = (slice(1, -1),) * 2
        return np.abs((out - c) / dt - rhs)[inner].max() / np.abs(rhs).max()

    coarse, fine = residual(16), residual(32)
    assert fine < 0.01
    assert 3.0 < coarse / fine < 5.0


# ---------------------------------------------------------------------------------------
# stability limits
# ---------------------------------------------------------------------------------------


def _single_cell(ndim, velocity, diffusivity_lo_hi, spacing):
    """Fields on a 3**ndim box with only the centre cell material."""
    shape = (3,) * ndim
    vel = [np.full(shape, v) for v in velocity]
    dif = []
    for axis, (d_lo, d_c, d_hi) in enumerate(diffusivity_lo_hi):
        idx = np.arange(3).reshape([-1 if a == axis else 1 for a in range(ndim)])
        dif.append(np.broadcast_to(np.choose(idx, [d_lo, d_c, d_hi]), shape).astype(float))
    material = np.zeros(shape, dtype=np.uint8)
    material[(1,) * ndim] = 1
    return vel, dif, spacing, material


def test_lax_wendroff_max_dt_hand_values():
    # advection only: |a|/h = (30, 20, 10) 1/s;
    # (30^(2/3) + 20^(2/3) + 10^(2/3))^(-3/2) = 21.665^(-3/2) = 0.0099169 s beats
    # the quadratic limit 1 / (30 + 20 + 10) = 0.016667 s
    args = _single_cell(3, (0.3, -0.4, 0.1), [(0, 0, 0)] * 3, (0.01, 0.02, 0.01))
    assert math.isclose(lax_wendroff_max_dt(*args), 0.0099168928560619, rel_tol=1e-12)
    # advection and diffusion: |a|/h = 5, A = 5, B = 2 (1e-4 + 2e-4) / 1e-4 = 6:
    # 2 / (6 + sqrt(36 + 100)) = 0.113238 s beats 1 / 5 = 0.2 s
    args = _single_cell(3, (0.05, 0, 0), [(1e-4,) * 3, (2e-4,) * 3, (0, 0, 0)], (0.01,) * 3)
    assert math.isclose(lax_wendroff_max_dt(*args), 0.11323807579381201, rel_tol=1e-12)
    # dD/dx = (2e-4 - 0) / 0.02 = 0.01 m/s lowers the effective velocity to 0.04 m/s:
    # |a|/h = 4, B = 2: 2 / (2 + sqrt(4 + 64)) = 0.195194 s beats 4^(-1) = 0.25 s (2-D)
    args = _single_cell(2, (0.05, 0), [(0, 1e-4, 2e-4), (0, 0, 0)], (0.01, 0.01))
    assert math.isclose(lax_wendroff_max_dt(*args), 0.1951941016011038, rel_tol=1e-12)
    # nothing moves, nothing diffuses
    args = _single_cell(3, (0, 0, 0), [(0, 0, 0)] * 3, (0.01,) * 3)
    assert lax_wendroff_max_dt(*args) == math.inf


def _wrap(c):
    """Fill the outermost layer periodically, so the kernel sees an unbounded medium."""
    for axis in range(c.ndim):
        view = np.moveaxis(c, axis, 0)
        view[0] = view[-2]
        view[-1] = view[1]


@pytest.mark.parametrize(
    "ndim, velocity, diffusivity, steps",
    [
        (2, (0.3, -0.3), (0.0, 0.0), 160),  # the |nu|^(2/3) law binds
        (3, (0.3, 0.3, -0.3), (0.0, 0.0, 0.0), 500),
        (3, (0.3, 0.0, 0.0), (4e-4, 4e-4, 4e-4), 60),  # the quadratic law binds
        (3, (0.0, 0.0, 0.0), (2e-4, 1e-4, 3e-4), 60),  # pure diffusion
    ],
)
def test_lax_wendroff_limit_is_sharp(ndim, velocity, diffusivity, steps):
    shape = (16,) * ndim
    spacing = (0.01,) * ndim
    vel = [np.full(shape, v) for v in velocity]
    dif = [np.full(shape, d) for d in diffusivity]
    material = np.ones(shape, dtype=np.uint8)
    limit = lax_wendroff_max_dt(vel, dif, spacing, material)
    step = reference.lw_step_2d if ndim == 2 else reference.lw_step_3d
    rng = np.random.default_rng(70)
    start = 0.5 + 0.01 * rng.standard_normal(shape)
    growth = {}
    for factor in (0.9, 1.5):
        c = start.copy()
        out = np.empty_like(c)
        for _ in range(steps):
            _wrap(c)
            step(c, out, *vel, *dif, material, factor * limit, *spacing, clip=False)
            c, out = out, c
        inner = (slice(1, -1),) * ndim
        growth[factor] = np.std(c[inner]) / np.std(start[inner])
    assert growth[0.9] <= 1.0
    assert growth[1.5] > 100.0


def test_finite_volume_max_dt_hand_value():
    shape = (5, 4)
    spacing = (0.1, 0.05)
    vessel = np.ones(shape, dtype=np.uint8)
    vessel[4, :] = 0
    vx = np.zeros(shape)
    vx[1, 1], vx[2, 1] = 0.2, 0.6  # x face mean 0.4 m/s over 0.1 m: 4 1/s
    vx[4, 2] = 5.0  # outside the vessel: its faces carry nothing
    vy = np.zeros(shape)
    vy[2, 1], vy[2, 2] = -0.1, -0.3  # y face mean -0.2 m/s over 0.05 m: 4 1/s
    # per-face Courant 1/2: 0.5 / 4 s
    assert math.isclose(finite_volume_max_dt((vx, vy), spacing, vessel), 0.125)
    vy[2, 2] = -0.7  # y face mean -0.4 m/s: 8 1/s
    assert math.isclose(finite_volume_max_dt((vx, vy), spacing, vessel), 0.0625)
    assert finite_volume_max_dt((0 * vx, 0 * vy), spacing, vessel) == math.inf


def test_diffusion_substeps():
    shape = (4, 4, 4)
    zero = np.zeros(shape)
    assert diffusion_substeps((zero, zero, zero), (0.01,) * 3, 1.0) == 0
    dxx = zero.copy()
    dxx[1, 2, 3] = 1e-4  # 1-D limit 0.5 * 0.01**2 / 1e-4 = 0.5 s
    dzz = np.full(shape, 1e-5)  # 0.5 * 0.02**2 / 1e-5 = 20 s
    assert diffusion_substeps((dxx, zero, dzz), (0.01, 0.01, 0.02), 0.1) == 1
    assert diffusion_substeps((dxx, zero, dzz), (0.01, 0.01, 0.02), 1.2) == 3
    flat = np.zeros((4, 4))
    assert diffusion_substeps((flat, flat), (0.01, 0.01), 5.0) == 0


def test_unsplit_diffusion_substeps():
    # all axes at once: dt_sub <= 1 / (2 (1e-4 / 0.01**2 + 1e-5 / 0.02**2)) = 1 / 2.05 s
    assert unsplit_diffusion_substeps((1e-4, 0.0, 1e-5), (0.01, 0.01, 0.02), 0.4) == 1
    assert unsplit_diffusion_substeps((1e-4, 0.0, 1e-5), (0.01, 0.01, 0.02), 1.0) == 3
    assert unsplit_diffusion_substeps((0.0, 0.0), (0.01, 0.01), 5.0) == 0


def test_finite_volume_diffusion_substep_limit_keeps_bounds(one_thread):
    """At the sub-step count from diffusion_substeps, strong diffusion stays bounded."""
    rng = np.random.default_rng(80)
    case = _fv_case(rng, 2, tiny=False)
    case["dif"] = [50.0 * d for d in case["dif"]]
    n_sub = diffusion_substeps(case["dif"], case["spacing"], case["dt"])
    assert n_sub > 3
    c0 = _concentration(case["m"], case["q"])
    for m, q in _fv_run(case, 20, n_diff_sub=n_sub):
        c = _concentration(m, q)
        assert np.nanmin(c) >= np.nanmin(c0) - 1e-12
        assert np.nanmax(c) <= np.nanmax(c0) + 1e-12
    # and the colour has mixed a lot
    assert np.nanstd(c) < 0.5 * np.nanstd(c0)


# ---------------------------------------------------------------------------------------
# shear diffusivity, eq. (5)
# ---------------------------------------------------------------------------------------


def test_simple_shear_2d():
    shape = (20, 16)
    h = (0.01, 0.02)
    g_rate = 3.0
    y = np.arange(shape[1]) * h[1]
    vx = np.broadcast_to(g_rate * y[None, :], shape).copy()
    vy = np.zeros(shape)
    fill = np.zeros(shape)
    fill[3:15, 2:11] = 1.0
    fill[3:15, 11] = 0.4  # partly filled surface row still counts as material
    gx, gy = shear_rates((vx, vy), fill, h)
    material = fill > 0
    np.testing.assert_allclose(gy[material], g_rate, rtol=1e-12)
    assert not gx.any()
    assert not gy[~material].any()
    k1, d = 0.01, 1e-3
    dxx, dyy = shear_diffusivity((vx, vy), fill, h, k1, 1.9 * k1, d)
    np.testing.assert_allclose(dxx[material], 1.9 * k1 * g_rate * d**2, rtol=1e-12)
    np.testing.assert_allclose(dyy[material], k1 * g_rate * d**2, rtol=1e-12)
    assert not dxx[~material].any() and not dyy[~material].any()


def test_linear_field_3d():
    rng = np.random.default_rng(90)
    grad = rng.normal(size=(3, 3))  # grad[a, b] = dv_a / dx_b
    shape = (9, 8, 7)
    h = (0.01, 0.015, 0.02)
    coords = np.meshgrid(*[np.arange(n) * s for n, s in zip(shape, h, strict=True)], indexing="ij")
    vel = tuple(sum(grad[a, b] * coords[b] for b in range(3)) for a in range(3))
    fill = np.zeros(shape)
    fill[1:8, 2:7, 1:6] = 0.8
    rates = shear_rates(vel, fill, h)
    material = fill > 0
    want = [
        abs(grad[1, 0]) + abs(grad[2, 0]),
        abs(grad[0, 1]) + abs(grad[2, 1]),
        abs(grad[0, 2]) + abs(grad[1, 2]),
    ]
    for got, value in zip(rates, want, strict=True):
        np.testing.assert_allclose(got[material], value, rtol=1e-10)
        assert not got[~material].any()
    k1, k2, d = 0.02, 0.05, 2e-3
    diffs = shear_diffusivity(vel, fill, h, k1, k2, d)
    for axis in range(3):
        others = sum(want) - want[axis]
        np.testing.assert_allclose(
            diffs[axis][material], (k1 * want[axis] + k2 * others) * d**2, rtol=1e-10
        )


def test_shear_rate_differences_central_inside_one_sided_at_surface():
    shape = (6, 10)
    h = (0.1, 0.1)
    y = np.arange(shape[1]) * h[1]
    vx = np.broadcast_to(y[None, :] ** 2, shape).copy()
    fill = np.zeros(shape)
    fill[:, 2:8] = 1.0
    _, gy = shear_rates((vx, np.zeros(shape)), fill, h)
    # central differences are exact for a parabola: 2 y
    np.testing.assert_allclose(gy[:, 3:7], np.tile(2.0 * y[3:7], (shape[0], 1)), rtol=1e-12)
    # at the surface rows only the inner neighbour holds material: one-sided
    np.testing.assert_allclose(gy[:, 2], np.full(shape[0], (y[3] ** 2 - y[2] ** 2) / h[1]))
    np.testing.assert_allclose(gy[:, 7], np.full(shape[0], (y[7] ** 2 - y[6] ** 2) / h[1]))
    assert not gy[:, :2].any() and not gy[:, 8:].any()


# ---------------------------------------------------------------------------------------
# Driver-side kernels: classification, blending, pair limits
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("ndim", [2, 3])
def test_lax_wendroff_classes_match_binary_erosion(ndim):
    from scipy import ndimage

    rng = np.random.default_rng(11)
    shape = (13, 11, 9)[:ndim]
    material = (rng.uniform(size=shape) > 0.25).astype(np.uint8)
    plan = kernels.LaxWendroffPlan(shape)
    plan.classify(material)
    box = np.ones((3,) * ndim, bool)
    interior = ndimage.binary_erosion(material.astype(bool), box, border_value=0)
    expected = np.where(interior, kernels.LW_INTERIOR, material * kernels.LW_SURFACE)
    np.testing.assert_array_equal(plan.cls, expected)
    # every material cell lies inside its row's range
    rows = plan.rows
    for index in np.argwhere(material):
        lo, hi = rows[tuple(index[:-1])]
        assert lo <= index[-1] < hi


def test_lerp_into_is_linear_interpolation():
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(2, 1000))
    out = np.empty(1000)
    kernels.lerp_into(out, a, b, 0.3)
    np.testing.assert_allclose(out, 0.7 * a + 0.3 * b, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("ndim", [2, 3])
def test_pair_limits_equal_numpy_limits_for_one_phase(ndim):
    rng = np.random.default_rng(5)
    shape = (9, 8, 7)[:ndim]
    vel = rng.normal(size=(ndim, *shape))
    dif = rng.uniform(0.0, 0.1, size=(ndim, *shape))
    material = (rng.uniform(size=shape) > 0.3).astype(np.uint8)
    spacing = tuple(rng.uniform(0.5, 1.5, ndim))
    pair = kernels.lw_max_dt_pair_3d if ndim == 3 else kernels.lw_max_dt_pair_2d
    got = pair(vel, dif, vel, dif, material, *spacing)
    want = stability.lax_wendroff_max_dt(tuple(vel), tuple(dif), spacing, material)
    assert got == pytest.approx(want, rel=1e-12)
    vessel = (rng.uniform(size=shape) > 0.2).astype(np.uint8)
    got = kernels.fv_max_dt_pair(vel, vel, vessel, np.asarray(spacing))
    want = stability.finite_volume_max_dt(tuple(vel), spacing, vessel)
    assert got == pytest.approx(want, rel=1e-12)


@pytest.mark.parametrize("ndim", [2, 3])
def test_pair_limits_bound_every_blend_of_two_phases(ndim):
    rng = np.random.default_rng(6)
    shape = (9, 8, 7)[:ndim]
    vel_a, vel_b = rng.normal(size=(2, ndim, *shape))
    dif_a, dif_b = rng.uniform(0.0, 0.1, size=(2, ndim, *shape))
    material = np.ones(shape, np.uint8)
    vessel = np.ones(shape, np.uint8)
    spacing = (1.0,) * ndim
    pair = kernels.lw_max_dt_pair_3d if ndim == 3 else kernels.lw_max_dt_pair_2d
    lw = pair(vel_a, dif_a, vel_b, dif_b, material, *spacing)
    fv = kernels.fv_max_dt_pair(vel_a, vel_b, vessel, np.asarray(spacing))
    for w in np.linspace(0.0, 1.0, 11):
        vel = (1 - w) * vel_a + w * vel_b
        dif = (1 - w) * dif_a + w * dif_b
        assert lw <= stability.lax_wendroff_max_dt(tuple(vel), tuple(dif), spacing, material)
        assert fv <= stability.finite_volume_max_dt(tuple(vel), spacing, vessel)


def _pair_limit_by_hand(vel_a, dif_a, vel_b, dif_b, material, spacing):
    """Every material cell's Lax-Wendroff limit for two phases, whole-array NumPy."""
    ndim = material.ndim
    s, b2 = [], 0.0
    for axis in range(ndim):
        h = spacing[axis]
        speeds = []
        for vel, dif in ((vel_a, dif_a), (vel_b, dif_b)):
            grad = np.zeros(material.shape)
            inner = [slice(None)] * ndim
            inner[axis] = slice(1, -1)
            up = np.take(dif[axis], np.arange(2, material.shape[axis]), axis=axis)
            down = np.take(dif[axis], np.arange(0, material.shape[axis] - 2), axis=axis)
            grad[tuple(inner)] = (up - down) / (2.0 * h)
            speeds.append(np.abs(vel[axis] - grad))
        s.append(np.maximum(*speeds) / h)
        b2 = b2 + np.maximum(dif_a[axis], dif_b[axis]) / (h * h)
    b2 = 2.0 * b2
    a1 = sum(s)
    a23 = sum(x ** (2.0 / 3.0) for x in s)
    with np.errstate(divide="ignore"):
        power = np.where(a23 > 0.0, a23**-1.5, np.inf)
        denom = b2 + np.sqrt(b2 * b2 + 4.0 * a1 * a1)
        quad = np.where(denom > 0.0, 2.0 / denom, np.inf)
    return np.minimum(power, quad)[material > 0]


@pytest.mark.parametrize("ndim", [2, 3])
def test_pair_limits_find_the_binding_cell(ndim):
    """The pair limit is the smallest cell limit, whichever cell and law bind."""
    pair = kernels.lw_max_dt_pair_3d if ndim == 3 else kernels.lw_max_dt_pair_2d
    shape = (14, 12, 10)[:ndim]
    for seed in range(12):
        rng = np.random.default_rng(200 + seed)
        vel_a, vel_b = rng.normal(size=(2, ndim, *shape)) * 10.0 ** rng.uniform(-2, 1)
        dif_a, dif_b = rng.uniform(0.0, 1.0, size=(2, ndim, *shape)) * 10.0 ** rng.uniform(-4, 0)
        # one fast cell somewhere, so that the minimum is not found in the first plane
        fast = tuple(rng.integers(1, n - 1) for n in shape)
        vel_b[(slice(None), *fast)] *= 1.0 + 3.0 * rng.uniform()
        material = (rng.uniform(size=shape) > 0.2).astype(np.uint8)
        spacing = tuple(rng.uniform(0.5, 1.5, ndim))
        want = _pair_limit_by_hand(vel_a, dif_a, vel_b, dif_b, material, spacing).min()
        got = pair(vel_a, dif_a, vel_b, dif_b, material, *spacing)
        assert got == pytest.approx(want, rel=1e-13)
