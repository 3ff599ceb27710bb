"""MPM kernels: numba kernels against their NumPy twins and against independent facts.

Facts checked: conservation of mass, momentum and angular momentum by the APIC/MLS-MPM
transfers, exactness of the transfers for affine velocity fields, the exact Coriolis
rotation, Coulomb wall friction (including the block on an incline, DESIGN section 7), the
bulk viscosity's silence in isochoric motion, the stress update inside G2P against the
twins of both kernels, and the B-spline volume deposit onto the output cells. Grids are
tiny, and every kernel sees one argument signature per dimension, so numba compiles each
once.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from blendxr.flow import kernels, mohr_coulomb, reference

SHAPES = {2: (9, 8), 3: (7, 6, 8)}
H = 0.05
INV_H = 1.0 / H
ORIGIN = {2: np.array([-0.2, -0.15]), 3: np.array([-0.2, -0.15, -0.17])}
DIMS = pytest.mark.parametrize("d", [2, 3], ids=["2d", "3d"])

P2G = {2: kernels.p2g_2d, 3: kernels.p2g_3d}
REDUCE = {2: kernels.reduce_grids_2d, 3: kernels.reduce_grids_3d}
GRID_UPDATE = {2: kernels.grid_update_2d, 3: kernels.grid_update_3d}
G2P = {2: kernels.g2p_2d, 3: kernels.g2p_3d}
DEPOSIT = {2: kernels.deposit_2d, 3: kernels.deposit_3d}


def _particles(d, n=60, seed=0, stress=True):
    """Random particles whose stencils are on the grid, with random C and stress."""
    rng = np.random.default_rng(seed)
    shape = np.array(SHAPES[d])
    x = rng.uniform(ORIGIN[d] + 0.5 * H, ORIGIN[d] + (shape - 1.5) * H, (n, d))
    v = rng.normal(0.0, 0.3, (n, d))
    C = rng.normal(0.0, 2.0, (n, d, d))
    m = rng.uniform(0.5, 1.5, n) * 1e-3
    vol = m / 1500.0
    sigma = rng.normal(0.0, 1e3, (n, 3, 3)) if stress else np.zeros((n, 3, 3))
    sigma = sigma + sigma.transpose(0, 2, 1)
    return x, v, C, m, vol, sigma


def _p2g(d, x, v, C, m, vol, sigma, dt, n_chunks=2, bulk=(0.0, 0.0)):
    """Run the numba P2G with ``n_chunks`` private grids and reduce; return (m, p)."""
    shape = SHAPES[d]
    grids = np.full((n_chunks, *shape, d + 1), np.nan)  # NaN: the kernel must zero them
    starts = kernels.chunk_starts(len(m), n_chunks)
    P2G[d](x, v, C, m, vol, sigma, ORIGIN[d], INV_H, dt, bulk, grids, starts)
    out_m = np.empty(shape)
    out_p = np.empty((*shape, d))
    REDUCE[d](grids, out_m, out_p)
    return out_m, out_p


def _no_walls(d):
    """Node SDF and normals of a vessel larger than the grid (no node feels a wall)."""
    shape = SHAPES[d]
    normal = np.zeros((*shape, d))
    normal[..., 0] = 1.0
    return np.full(shape, -1.0), normal


def _velocities(d, grid_m, grid_p):
    """Node velocities p / m through the grid-update kernel with no force at all."""
    sdf, normal = _no_walls(d)
    vel = np.empty_like(grid_p)
    args = (0.0, np.zeros(d), 0.0, 0.0, sdf, normal, 0.0, 0.0)
    GRID_UPDATE[d](grid_m, grid_p, vel, ORIGIN[d], H, *args)
    return vel


_PHI, _PSI = math.radians(27.1), math.radians(0.1)
#: (K, G, sin phi, cos phi, c, sin psi, tension cutoff): Table 1 with E / 100
MATERIAL = (
    *(float(k) for k in mohr_coulomb.elastic_constants(3.65e4, 0.065)[:2]),
    math.sin(_PHI), math.cos(_PHI), 87.0, math.sin(_PSI), 87.0 / math.tan(_PHI),
)  # fmt: skip
#: The G2P kernels' material: MATERIAL, lost contact on (the inverse of a node's mass at
#: the seeded packing, 1 kg: the tests' grids hold no mass, or what they say), no mu(I)
G2P_MATERIAL = (*MATERIAL, 1.0, 0.0, 1.0, 0.0)
#: mu(I) with mu_2 - mu_s = 0.26, I0 = 0.279 (Jop et al. 2006) and d sqrt(rho_s) = 1 (a
#: 20 mm grain of 2500 kg/m3): at the test's rates and pressures I is of order I0, so
#: the friction angle moves far from phi
RATE = (0.26, 0.279, 1.0)


def _g2p(
    d, x, v, C, vol, J, vel, dt, stress=None, material=G2P_MATERIAL, gap=None, mass=None, block=16
):
    """Run the numba G2P on copies; return (x, v, C, vol, J, stress, codes, gap).

    ``mass``: the node masses (default none: no packing bounds the contact gap);
    ``block``: particles per block of the batched 3-D stress update (16: full and
    partial blocks; ``G2P_BLOCK``: the vectorised returns)."""
    if stress is None:
        stress = np.zeros((len(x), 3, 3))
    if gap is None:
        gap = np.zeros(len(x))
    if mass is None:
        mass = np.zeros(vel.shape[:-1])
    x, v, C, vol, J, stress, gap = (a.copy() for a in (x, v, C, vol, J, stress, gap))
    codes = np.full(len(x), -9, np.int8)
    # two chunks in blocks of the batched 3-D stress update
    starts = kernels.chunk_starts(len(x), 2)
    work = tuple(np.full(w.shape, np.nan) for w in kernels.g2p_work(2, block))
    G2P[d](
        x, v, C, vol, J, gap, stress, codes, vel, mass, ORIGIN[d], INV_H, dt, material, starts,
        work,
    )  # fmt: skip
    return x, v, C, vol, J, stress, codes, gap


def _close(actual, expected, rtol=1e-12):
    scale = max(np.max(np.abs(expected)), 1e-300)
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=rtol * scale)


# ---------------------------------------------------------------------------------------
# P2G
# ---------------------------------------------------------------------------------------


@DIMS
def test_p2g_matches_twin_for_one_and_two_private_grids(d):
    x, v, C, m, vol, sigma = _particles(d)
    ref_m, ref_p = reference.p2g(x, v, C, m, vol, sigma, ORIGIN[d], INV_H, 1e-3, SHAPES[d])
    one = _p2g(d, x, v, C, m, vol, sigma, 1e-3, n_chunks=1)
    two = _p2g(d, x, v, C, m, vol, sigma, 1e-3, n_chunks=2)
    three = _p2g(d, x, v, C, m, vol, sigma, 1e-3, n_chunks=3)  # more chunks than threads
    for got in (one, two, three):
        _close(got[0], ref_m)
        _close(got[1], ref_p)
    _close(two[0], one[0], rtol=1e-14)
    _close(two[1], one[1], rtol=1e-14)


@DIMS
@pytest.mark.parametrize("stress", [False, True], ids=["no-stress", "stress"])
def test_p2g_conserves_mass_and_momentum(d, stress):
    # the affine and stress terms carry sum_i w_ip (x_i - x_p) = 0: they move momentum
    # between nodes and add none
    x, v, C, m, vol, sigma = _particles(d, seed=1, stress=stress)
    grid_m, grid_p = _p2g(d, x, v, C, m, vol, sigma, 1e-3)
    assert grid_m.sum() == pytest.approx(m.sum(), rel=1e-14)
    total = grid_p.reshape(-1, d).sum(axis=0)
    np.testing.assert_allclose(total, m @ v, rtol=0, atol=1e-14 * np.abs(m[:, None] * v).sum())


# ---------------------------------------------------------------------------------------
# Transfers: affine exactness and angular momentum (P2G -> p / m -> G2P)
# ---------------------------------------------------------------------------------------


@DIMS
def test_affine_velocity_field_transfers_exactly(d):
    rng = np.random.default_rng(2)
    x, _, _, m, vol, sigma = _particles(d, seed=2, stress=False)
    a = rng.normal(size=d)
    A = rng.normal(size=(d, d))
    v = a + x @ A.T
    C = np.broadcast_to(A, (len(x), d, d)).copy()
    grid_m, grid_p = _p2g(d, x, v, C, m, vol, sigma, 1e-3)
    vel = _velocities(d, grid_m, grid_p)
    _, v_back, C_back, *_ = _g2p(d, x, v, C, vol, np.ones(len(x)), vel, 0.0)
    _close(v_back, v)
    _close(C_back, C)


def _angular_momentum(x, v, C, m):
    """APIC angular momentum: orbital plus the affine spin m eps : (C D)^T, D = h^2/4 I."""
    spin = 0.25 * H * H * m
    if x.shape[1] == 2:
        return np.sum(
            m * (x[:, 0] * v[:, 1] - x[:, 1] * v[:, 0]) + spin * (C[:, 1, 0] - C[:, 0, 1])
        )
    skew = np.stack([C[:, 2, 1] - C[:, 1, 2], C[:, 0, 2] - C[:, 2, 0], C[:, 1, 0] - C[:, 0, 1]], 1)
    return np.sum(m[:, None] * np.cross(x, v) + spin[:, None] * skew, axis=0)


def _grid_angular_momentum(d, grid_p):
    axes = [ORIGIN[d][a] + H * np.arange(n) for a, n in enumerate(SHAPES[d])]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, d)
    p = grid_p.reshape(-1, d)
    if d == 2:
        return np.sum(pos[:, 0] * p[:, 1] - pos[:, 1] * p[:, 0])
    return np.cross(pos, p).sum(axis=0)


@DIMS
@pytest.mark.parametrize("motion", ["rigid-rotation", "random"])
def test_transfers_conserve_angular_momentum(d, motion):
    x, v, C, m, vol, sigma = _particles(d, seed=3, stress=False)
    if motion == "rigid-rotation":
        w = (0.3, -0.7, 1.1)  # about z only in 2-D: the in-plane block
        spin = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])[:d, :d]
        v = x @ spin.T
        C = np.broadcast_to(spin, (len(x), d, d)).copy()
    before = _angular_momentum(x, v, C, m)
    grid_m, grid_p = _p2g(d, x, v, C, m, vol, sigma, 1e-3)
    on_grid = _grid_angular_momentum(d, grid_p)
    vel = _velocities(d, grid_m, grid_p)
    _, v_after, C_after, *_ = _g2p(d, x, v, C, vol, np.ones(len(x)), vel, 0.0)
    after = _angular_momentum(x, v_after, C_after, m)
    scale = np.sum(m * np.linalg.norm(x, axis=1) * np.linalg.norm(v, axis=1))
    np.testing.assert_allclose(on_grid, before, rtol=0, atol=1e-13 * scale)
    np.testing.assert_allclose(after, before, rtol=0, atol=1e-13 * scale)


# ---------------------------------------------------------------------------------------
# Grid update
# ---------------------------------------------------------------------------------------


def _random_grid(d, seed=4):
    rng = np.random.default_rng(seed)
    shape = SHAPES[d]
    grid_m = rng.uniform(0.1, 1.0, shape) * 1e-3
    grid_m[rng.random(shape) < 0.2] = 0.0
    grid_p = grid_m[..., None] * rng.normal(0.0, 0.5, (*shape, d))
    return grid_m, grid_p


def _run_grid_update(d, grid_m, grid_p, args):
    vel = np.full_like(grid_p, np.nan)
    GRID_UPDATE[d](grid_m, grid_p, vel, ORIGIN[d], H, *args)
    return vel


@DIMS
def test_grid_update_matches_twin(d):
    rng = np.random.default_rng(5)
    grid_m, grid_p = _random_grid(d)
    shape = SHAPES[d]
    sdf = rng.uniform(-2 * H, 2 * H, shape)
    normal = rng.normal(size=(*shape, d))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    gravity = np.array([1.5, -9.81, 0.7][:d])
    args = (0.01, gravity, 1.3, 0.05, sdf, normal, 0.324, H)
    got = _run_grid_update(d, grid_m, grid_p, args)
    _close(got, reference.grid_update(grid_m, grid_p, ORIGIN[d], H, *args))
    assert np.all(got[grid_m == 0.0] == 0.0)


@DIMS
def test_gravity_alone_adds_g_dt(d):
    grid_m, grid_p = _random_grid(d)
    sdf, normal = _no_walls(d)
    gravity = np.array([0.4, -9.81, 0.3][:d])
    vel = _run_grid_update(d, grid_m, grid_p, (0.02, gravity, 0.0, 0.0, sdf, normal, 0.3, H))
    mass = grid_m > 0
    _close(vel[mass], grid_p[mass] / grid_m[mass][:, None] + 0.02 * gravity)


@DIMS
def test_coriolis_is_an_exact_rotation(d):
    grid_m, grid_p = _random_grid(d)
    sdf, normal = _no_walls(d)
    omega, dt = 2.5, 0.04
    vel = _run_grid_update(d, grid_m, grid_p, (dt, np.zeros(d), omega, 0.0, sdf, normal, 0.0, 0.0))
    mass = grid_m > 0
    axes = [ORIGIN[d][a] + H * np.arange(n) for a, n in enumerate(SHAPES[d])]
    pos = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    before = grid_p[mass] / grid_m[mass][:, None] + dt * omega**2 * pos[mass]
    if d == 3:
        before[:, 2] = grid_p[mass][:, 2] / grid_m[mass]  # centrifugal has no z part
    after = vel[mass]
    _close(np.linalg.norm(after, axis=1), np.linalg.norm(before, axis=1), rtol=1e-14)
    turned = np.angle((after[:, 0] + 1j * after[:, 1]) / (before[:, 0] + 1j * before[:, 1]))
    np.testing.assert_allclose(turned, -2.0 * omega * dt, rtol=0, atol=1e-13)
    if d == 3:
        _close(after[:, 2], before[:, 2], rtol=1e-15)


def _one_node_wall(d, velocity, normal, mu):
    """Grid update of nodes all sitting on a wall with the given normal, no forces."""
    shape = SHAPES[d]
    grid_m = np.ones(shape)
    grid_p = np.broadcast_to(np.asarray(velocity, float), (*shape, d)).copy()
    normals = np.broadcast_to(np.asarray(normal, float), (*shape, d)).copy()
    args = (0.0, np.zeros(d), 0.0, 0.0, np.zeros(shape), normals, mu, 0.5 * H)
    return _run_grid_update(d, grid_m, grid_p, args).reshape(-1, d)[0]


@DIMS
def test_wall_removes_inward_normal_velocity_with_coulomb_friction(d):
    rng = np.random.default_rng(6)
    n = rng.normal(size=d)
    n /= np.linalg.norm(n)
    t = rng.normal(size=d)
    t -= (t @ n) * n
    t /= np.linalg.norm(t)
    mu = 0.324
    # into the wall, sliding: normal part gone, tangential speed down by mu * vn
    v = _one_node_wall(d, 0.8 * n + 1.5 * t, n, mu)
    _close(v, (1.5 - mu * 0.8) * t, rtol=1e-14)
    # into the wall, friction wins: the node sticks
    v = _one_node_wall(d, 2.0 * n + 0.5 * t, n, mu)
    assert np.all(v == 0.0)
    # away from the wall: untouched
    v = _one_node_wall(d, -0.8 * n + 1.5 * t, n, mu)
    _close(v, -0.8 * n + 1.5 * t, rtol=1e-15)


def test_block_on_incline_accelerates_at_g_sin_minus_mu_cos():
    # DESIGN section 7: 30 degrees, mu 0.324 -> a = g (sin - mu cos) = 2.15 m/s^2
    theta, mu, g, dt = math.radians(30.0), 0.324, 9.81, 1e-3
    shape = SHAPES[2]
    normal = np.broadcast_to([math.sin(theta), -math.cos(theta)], (*shape, 2)).copy()
    downhill = np.array([-math.cos(theta), -math.sin(theta)])
    grid_m = np.ones(shape)
    vel = np.zeros((*shape, 2))
    args = (dt, np.array([0.0, -g]), 0.0, 0.0, np.zeros(shape), normal, mu, H)
    for _ in range(20):
        vel = _run_grid_update(2, grid_m, vel.copy(), args)
    expected = 20 * dt * g * (math.sin(theta) - mu * math.cos(theta))
    _close(vel[0, 0], expected * downhill, rtol=1e-12)
    assert expected / (20 * dt) == pytest.approx(2.15, abs=0.005)


# ---------------------------------------------------------------------------------------
# G2P
# ---------------------------------------------------------------------------------------


@DIMS
@pytest.mark.parametrize("block", [16, kernels.G2P_BLOCK])
@pytest.mark.parametrize("rate", [None, RATE], ids=["mohr-coulomb", "mu-of-I"])
def test_g2p_matches_twin_with_the_stress_update(d, rate, block):
    rng = np.random.default_rng(7)
    x, v, C, _, vol, _ = _particles(d, seed=7)
    vel = rng.normal(0.0, 0.5, (*SHAPES[d], d))
    J = rng.uniform(0.9, 1.1, len(x))
    dt = 0.01
    # settled-bed stresses (compression, a few kPa) with a spread of shear: the node
    # velocities make L of order 10/s, so elastic, plane, edge and apex returns all occur
    stress = np.zeros((len(x), 3, 3))
    stress[:, [0, 1, 2], [0, 1, 2]] = -rng.uniform(500.0, 3000.0, (len(x), 3))
    shear = rng.normal(0.0, 300.0, (len(x), 3, 3))
    stress += shear + shear.transpose(0, 2, 1)
    if d == 2:
        stress[:, 2, :2] = stress[:, :2, 2] = 0.0  # plane strain: no out-of-plane shear
    material = G2P_MATERIAL[:8] + (RATE if rate else (0.0, 1.0, 0.0))
    got = _g2p(d, x, v, C, vol, J, vel, dt, stress, material=material, block=block)
    expected = reference.g2p(
        x, v, C, vol, J, vel, ORIGIN[d], INV_H, dt, stress, MATERIAL, rate=rate
    )
    for a, b in zip(got[:6], expected[:6], strict=True):
        _close(a, b)
    np.testing.assert_array_equal(got[6], expected[6])
    assert len(set(got[6].tolist()) & {0, 1}) == 2  # elastic and plastic particles both
    if rate:
        # the plane returns land on the surface of the rate's own angle, beyond the
        # quasi-static one (mu(I) > tan phi)
        L = np.zeros((len(x), 3, 3))
        L[:, :d, :d] = got[2]
        sin_i, cos_i = reference.rate_friction(L, stress, *MATERIAL[2:4], *rate)
        plane = np.flatnonzero(got[6] == mohr_coulomb.PLANE)
        assert len(plane) > 3 and np.all(sin_i[plane] > MATERIAL[2] + 0.02)
        for p in plane:
            f = mohr_coulomb.yield_value(got[5][p], sin_i[p], cos_i[p], MATERIAL[4])
            assert abs(f) < 1e-9 * np.abs(got[5][p]).max()
            assert mohr_coulomb.yield_value(got[5][p], *MATERIAL[2:5]) > 0.0


@DIMS
def test_contact_gap_is_bounded_by_the_packing_on_the_grid(d):
    # at rest and stress-free nothing opens or closes a gap; what G2P does to it is the
    # cap at the packing deficit 1 - sum w m_i / (rho h^d) of the node masses around it
    rng = np.random.default_rng(21)
    x, *_ = _particles(d, n=200, seed=21)
    n = len(x)
    packed = 2.5e-3  # kg at a node at the seeded packing
    mass = packed * rng.uniform(0.0, 1.3, SHAPES[d])  # holes, loose and over-packed nodes
    mass[: SHAPES[d][0] // 2] = 1.1 * packed  # and a region denser than the seeded packing
    gap = rng.uniform(0.0, 0.6, n)
    gap[::4] = 0.0  # closed gaps, which the kernel leaves without gathering the masses
    material = G2P_MATERIAL[:7] + (1.0 / packed,) + G2P_MATERIAL[8:]
    zero = np.zeros((*SHAPES[d], d))
    state = (x, np.zeros((n, d)), np.zeros((n, d, d)), np.full(n, 1e-6), np.ones(n))
    *_, stress, codes, got = _g2p(d, *state, zero, 1e-3, material=material, gap=gap, mass=mass)
    expected = reference.bounded_gap(x, gap, mass, ORIGIN[d], INV_H, 1.0 / packed)
    _close(got, expected, rtol=1e-13)
    assert np.all(codes == mohr_coulomb.ELASTIC) and np.all(stress == 0.0)
    capped = expected < gap
    assert 0 < capped.sum() < n and np.any(expected == 0.0)  # all three cases occur
    # where the nodes hold no mass the gap is kept; with lost contact off it is kept too
    kept = _g2p(d, *state, zero, 1e-3, material=material, gap=gap)[-1]
    np.testing.assert_array_equal(kept, gap)
    off = G2P_MATERIAL[:7] + (0.0,) + G2P_MATERIAL[8:]
    off_run = _g2p(d, *state, zero, 1e-3, material=off, gap=gap, mass=mass)
    np.testing.assert_array_equal(off_run[-1], gap)


# ---------------------------------------------------------------------------------------
# Deposit, sort and range check
# ---------------------------------------------------------------------------------------


def _deposit(d, x, v, vol, origin_out, h_out, inside, mirror=False):
    acc_vol = np.zeros(inside.shape)
    acc_mom = np.zeros((*inside.shape, d))
    extra = (mirror,) if d == 3 else ()
    DEPOSIT[d](x, v, vol, origin_out, 1.0 / h_out, inside, *extra, acc_vol, acc_mom)
    return acc_vol, acc_mom


@DIMS
def test_deposit_keeps_every_volume_inside_and_matches_twin(d):
    rng = np.random.default_rng(9)
    shape_out = (5, 4, 6)[:d]
    origin_out = np.array([-0.1, -0.05, 0.0][:d])
    h_out = 0.04
    n = 300
    x = rng.uniform(origin_out - 2 * h_out, origin_out + (np.array(shape_out) + 2) * h_out, (n, d))
    v = rng.normal(size=(n, d))
    vol = rng.integers(1, 64, n) / 1024.0
    inside = (rng.uniform(size=shape_out) < 0.8).astype(np.int8)
    acc_vol, acc_mom = _deposit(d, x, v, vol, origin_out, h_out, inside)
    ref_vol, ref_mom = reference.deposit(x, v, vol, origin_out, 1.0 / h_out, inside)
    _close(acc_vol, ref_vol)
    _close(acc_mom, ref_mom)
    # nothing lands outside, and a particle with any inside cell in its stencil
    # deposits its whole volume (its weights renormalised over those cells)
    assert (acc_vol[inside == 0] == 0.0).all()
    kept = np.array([reference.deposit(x[p : p + 1], v[p : p + 1], vol[p : p + 1],
                                       origin_out, 1.0 / h_out, inside)[0].sum() > 0
                     for p in range(n)])  # fmt: skip
    assert 0 < kept.sum() < n
    assert acc_vol.sum() == pytest.approx(vol[kept].sum(), rel=1e-13)


@DIMS
def test_deposit_of_a_uniform_lattice_is_exactly_its_packing_away_from_the_edges(d):
    # quadratic B-splines reproduce constants: two particles per cell and axis, each of
    # volume (h/2)^d, give fill 1 in every cell whose stencil sees only whole stencils
    h, cells = 0.1, 6
    axis = (np.arange(2 * cells) + 0.5) * h / 2
    x = np.stack(np.meshgrid(*[axis] * d, indexing="ij"), -1).reshape(-1, d)
    vol = np.full(len(x), (h / 2) ** d)
    v = np.tile(np.array([0.3, -1.2, 0.7][:d]), (len(x), 1))
    inside = np.ones((cells,) * d, np.int8)
    acc_vol, acc_mom = _deposit(d, x, v, vol, np.zeros(d), h, inside)
    fill = acc_vol / h**d
    # the grid's edge renormalises the weights of the particles in its outer cells,
    # which moves volume into the next cells in: the cells two in are exact
    core = (slice(2, -2),) * d
    np.testing.assert_allclose(fill[core], 1.0, rtol=1e-13)
    assert acc_vol.sum() == pytest.approx(vol.sum(), rel=1e-13)
    np.testing.assert_allclose(acc_mom / acc_vol[..., None], np.broadcast_to(v[0], acc_mom.shape),
                               rtol=1e-13)  # fmt: skip


def test_deposit_folded_at_the_mirror_plane_is_the_upper_half_of_bed_and_image():
    rng = np.random.default_rng(4)
    h = 0.05
    lower = np.array([-0.1, -0.125, -0.15])
    x = rng.uniform([-0.1, -0.125, 0.0], [0.1, 0.125, 0.15], (200, 3))
    v = rng.normal(size=(200, 3))
    vol = rng.uniform(1.0, 2.0, 200)
    inside = (rng.uniform(size=(4, 5, 3)) < 0.85).astype(np.int8)
    whole_inside = np.concatenate([inside[..., ::-1], inside], axis=-1)
    image = x * [1.0, 1.0, -1.0]
    whole_vol, whole_mom = _deposit(3, np.concatenate([x, image]),
                                    np.concatenate([v, v * [1.0, 1.0, -1.0]]),
                                    np.tile(vol, 2), lower, h, whole_inside)  # fmt: skip
    half_vol, half_mom = _deposit(3, x, v, vol, np.array([-0.1, -0.125, 0.0]), h, inside, True)
    _close(half_vol, whole_vol[..., 3:])
    _close(half_mom, whole_mom[..., 3:, :])
    ref_vol, ref_mom = reference.deposit(x, v, vol, np.array([-0.1, -0.125, 0.0]), 1 / h,
                                         inside, mirror_z=True)  # fmt: skip
    _close(half_vol, ref_vol)
    _close(half_mom, ref_mom)


@DIMS
@pytest.mark.parametrize("parts", [1, 2, 3])
def test_deposit_in_parts_is_the_serial_deposit_of_each_strided_part(d, parts):
    # the parallel deposit of the phase averager's halves: part q takes particles
    # q, q + P, ...; each part is the serial kernel's sum in the same order, bit for bit
    rng = np.random.default_rng(11)
    shape_out = (6, 5, 4)[:d]
    n = 1001
    x = rng.uniform(-0.05, 0.3, (n, d))
    v = rng.normal(size=(n, d))
    vol = rng.uniform(1.0, 2.0, n)
    inside = (rng.uniform(size=shape_out) < 0.8).astype(np.int8)
    origin_out, h_out = np.zeros(d), 0.05
    acc_vol = np.zeros((parts, 2, *shape_out))
    acc_mom = np.zeros((parts, 2, *shape_out, d))
    extra = (True,) if d == 3 else ()  # 3-D: folded at the mirror plane z = 0
    parallel = kernels.deposit_parts_3d if d == 3 else kernels.deposit_parts_2d
    parallel(x, v, vol, origin_out, 1.0 / h_out, inside, *extra, acc_vol[:, 1], acc_mom[:, 1])
    assert (acc_vol[:, 0] == 0.0).all()
    for q in range(parts):
        part = (np.ascontiguousarray(a[q::parts]) for a in (x, v, vol))
        ref_vol, ref_mom = _deposit(d, *part, origin_out, h_out, inside, mirror=d == 3)
        np.testing.assert_array_equal(acc_vol[q, 1], ref_vol)
        np.testing.assert_array_equal(acc_mom[q, 1], ref_mom)


@DIMS
def test_sort_by_cell_matches_twin_and_orders_cells_x_major(d):
    x, *_ = _particles(d, n=200, seed=10)
    x[:20] = x[20:40]  # ties keep their order
    shape = SHAPES[d]
    perm = kernels.sort_by_cell(x, ORIGIN[d], INV_H, shape)
    np.testing.assert_array_equal(perm, reference.sort_by_cell(x, ORIGIN[d], INV_H, shape))
    cell = np.floor((x[perm] - ORIGIN[d]) * INV_H).astype(np.int64)
    key = np.ravel_multi_index(tuple(cell.T), shape)
    assert np.all(np.diff(key) >= 0)
    assert sorted(perm) == list(range(len(x)))


def test_gather_rows_applies_the_permutation_like_fancy_indexing():
    rng = np.random.default_rng(12)
    order = rng.permutation(57)
    for source in (rng.standard_normal((57, 3, 3)), rng.standard_normal(57)):
        out = np.full_like(source, np.nan)
        kernels.gather_rows(source.reshape(57, -1), order, out.reshape(57, -1))
        np.testing.assert_array_equal(out, source[order])


@pytest.mark.parametrize("chunks", [1, 2, 5])
def test_fastest_particle_is_numpys_argmax_with_non_finite_speeds_first(chunks):
    rng = np.random.default_rng(13)
    v = rng.standard_normal((40, 3))
    starts = kernels.chunk_starts(40, chunks)
    scratch = np.zeros((chunks, 4))
    numpy_twin = reference.fastest_particle
    v[9] *= 10.0
    v[31] = v[9]  # a tie of the fastest: the first wins
    assert kernels.fastest_particle(v, starts, scratch) == numpy_twin(v) == 9
    for bad in (np.nan, np.inf):
        w = v.copy()
        w[[17, 33], 1] = bad
        assert kernels.fastest_particle(w, starts, scratch) == numpy_twin(w) == 17
    none = v[:0]
    assert kernels.fastest_particle(none, kernels.chunk_starts(0, chunks), scratch) == -1
    assert numpy_twin(none) == -1


@DIMS
def test_particles_in_range_finds_the_first_offender(d):
    x, *_ = _particles(d, n=30, seed=11)
    shape = SHAPES[d]
    assert kernels.particles_in_range(x, ORIGIN[d], INV_H, shape) == -1
    for index, axis, f in [(7, 0, 0.4999), (5, d - 1, shape[d - 1] - 1.5), (3, 1, np.nan)]:
        bad = x.copy()
        bad[index, axis] = ORIGIN[d][axis] + f * H
        assert kernels.particles_in_range(bad, ORIGIN[d], INV_H, shape) == index
        assert reference.particles_in_range(bad, ORIGIN[d], INV_H, shape) == index
    edge = x.copy()
    edge[4] = ORIGIN[d] + (0.5 + 1e-9) * H  # just above the lowest position allowed
    assert kernels.particles_in_range(edge, ORIGIN[d], INV_H, shape) == -1


@DIMS
def test_p2g_bulk_viscosity_matches_twin_and_leaves_isochoric_motion_alone(d):
    x, v, C, m, vol, sigma = _particles(d, seed=12)
    bulk = (3.0, 0.7)
    got = _p2g(d, x, v, C, m, vol, sigma, 1e-3, bulk=bulk)
    ref = reference.p2g(x, v, C, m, vol, sigma, ORIGIN[d], INV_H, 1e-3, SHAPES[d], bulk)
    _close(got[0], ref[0])
    _close(got[1], ref[1])
    plain = _p2g(d, x, v, C, m, vol, sigma, 1e-3)
    assert np.abs(got[1] - plain[1]).max() > 1e-6 * np.abs(plain[1]).max()  # it acts
    # shear and spin (trace-free C) change nothing: no volume change, no viscous pressure
    C = C - np.trace(C, axis1=1, axis2=2)[:, None, None] * np.eye(d) / d
    got = _p2g(d, x, v, C, m, vol, sigma, 1e-3, bulk=bulk)
    plain = _p2g(d, x, v, C, m, vol, sigma, 1e-3)
    _close(got[1], plain[1], rtol=1e-13)


@DIMS
def test_volume_gained_at_the_apex_is_given_back_without_stress(d):
    # extend a bed at the apex (hydrostatic c cot phi), then compress it by as much: the
    # gap opens by dt tr(L) a step and closes again, the stress stays at the apex all the
    # way instead of dropping by `drop` a step, and only the next compression builds
    # pressure. In 3-D the motion is isotropic and all of it exact; in plane strain the
    # compression has a deviatoric part (sigma_zz is held), which yields on the edge next
    # to the apex: the stress moves off it by O(sin psi) of a step's increment
    K, G, sin_phi, cos_phi, c = MATERIAL[:5]
    lam = K - 2 * G / 3
    apex = c * cos_phi / sin_phi
    x, *_ = _particles(d, n=40, seed=13)
    n, rate, dt, steps = len(x), 0.5, 1e-3, 5
    drop = (lam * d + 2 * G) * rate * dt  # dt (lam tr D + 2 G D_xx) with tr D = -d rate
    near = 1e-9 * apex if d == 3 else 1e-2 * drop
    stress = np.tile(apex * np.eye(3), (n, 1, 1))
    axes = [ORIGIN[d][a] + H * np.arange(k) for a, k in enumerate(SHAPES[d])]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    gap = np.zeros(n)
    state = (x, np.zeros((n, d)), np.zeros((n, d, d)), np.full(n, 1e-6), np.ones(n))
    eye = np.broadcast_to(np.eye(d), (n, d, d))
    for sign in (1.0, -1.0):
        vel = sign * rate * nodes  # isotropic in the plane (2-D) or in space (3-D)
        for k in range(1, steps + 1):
            *state, stress, codes, gap = _g2p(d, *state, vel, dt, stress, gap=gap)
            state = state[:5]
            np.testing.assert_allclose(stress[:, :d, :d], apex * eye, rtol=0, atol=near)
            if sign > 0:
                assert np.all(codes == mohr_coulomb.APEX)
                np.testing.assert_allclose(gap, k * d * rate * dt, rtol=1e-9)
    np.testing.assert_allclose(gap, 0.0, rtol=0, atol=1e-15)
    *_, stress, codes, gap = _g2p(d, *state, vel, dt, stress, gap=gap)
    assert np.all(gap == 0.0)
    if d == 3:
        assert np.all(codes == mohr_coulomb.ELASTIC)
        np.testing.assert_allclose(stress[:, 0, 0], apex - drop, rtol=1e-9)
    else:
        assert np.all(apex - stress[:, 0, 0] > 0.5 * drop)  # pressure builds again
