"""Mohr–Coulomb stress update: numba kernels against the NumPy twin and independent truths.

Independent truths used here: trial states built as a point of the yield surface plus a
non-negative combination of the return directions of its active planes (so the exact
return is known in advance); the Kuhn–Tucker conditions checked by non-negative least
squares; the matrix exponential for a pure spin; the classical Mohr–Coulomb strength of a
biaxial test; closed-form elastic constants and the P-wave speed of the paper's material.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import nnls

from blendxr.flow import mohr_coulomb as mc
from blendxr.flow import mohr_coulomb_reference as ref

# Paper Table 1
RHO, E, NU = 1500.0, 3.65e6, 0.065
PHI, COHESION, PSI = 27.1, 87.0, 0.1
K = E / (3.0 * (1.0 - 2.0 * NU))
G = E / (2.0 * (1.0 + NU))
LAM = K - 2.0 * G / 3.0
DT = 1e-3


def material(phi=PHI, psi=PSI, cohesion=COHESION, cutoff=0.0):
    """Arguments K ... tension_cutoff of update_stress, as floats."""
    p, s = np.radians(phi), np.radians(psi)
    return (K, G, float(np.sin(p)), float(np.cos(p)), float(cohesion), float(np.sin(s)), cutoff)


MATERIALS = {
    "table1": material(),
    "dilatant": material(psi=10.0),
    "associated": material(psi=PHI),
    "steep-cohesionless": material(phi=40.0, psi=5.0, cohesion=0.0),
}
PAIRS = [(i, j) for i in range(3) for j in range(3) if i != j]


# --------------------------------------------------------------------------------------
# Principal-space geometry, written independently of both implementations
# --------------------------------------------------------------------------------------


def normal(i, j, sine):
    """Gradient of (1 + sin) σ_i − (1 − sin) σ_j."""
    v = np.zeros(3)
    v[i], v[j] = 1.0 + sine, -(1.0 - sine)
    return v


def direction(b):
    """C b for the isotropic elastic tangent."""
    return LAM * b.sum() + 2.0 * G * b


def apex_stress(mat):
    _, _, sphi, cphi, c, _, _ = mat
    return c * cphi / sphi


def surface_and_trial(rng, region, mat):
    """A sorted point on the yield surface in ``region`` and a trial that returns to it."""
    _, _, s, _, _, spsi, _ = mat
    apex = apex_stress(mat)
    compression_edge = -np.array([1.0, 1.0, (1.0 + s) / (1.0 - s)])  # σ1 = σ2
    extension_edge = -np.array([(1.0 - s) / (1.0 + s), 1.0, 1.0])  # σ2 = σ3

    def multiplier(b):  # a return of 10 Pa ... 3 kPa
        return rng.uniform(10.0, 3000.0) / np.linalg.norm(direction(b))

    t, u = rng.uniform(1.0, 3000.0, 2)
    if region == mc.ELASTIC:
        surface = apex + t * compression_edge + u * extension_edge
        inside = surface - rng.uniform(1.0, 2000.0)  # hydrostatic compression lowers all f
        return inside, inside
    if region == mc.PLANE:
        surface = apex + t * compression_edge + u * extension_edge
        planes = [(0, 2)]
    elif region == mc.EDGE_COMPRESSION:
        surface = apex + t * compression_edge
        planes = [(0, 2), (1, 2)]
    elif region == mc.EDGE_EXTENSION:
        surface = apex + u * extension_edge
        planes = [(0, 2), (0, 1)]
    else:
        surface = np.full(3, apex)
        planes = PAIRS
    trial = surface.copy()
    for i, j in planes:
        b = normal(i, j, spsi)
        trial += multiplier(b) * direction(b)
    return surface, trial


def random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def plane_strain_axes(rng):
    """In-plane rotation with a random principal stress along z."""
    a = rng.uniform(0.0, 2.0 * np.pi)
    rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return rz @ np.eye(3)[:, rng.permutation(3)]


def constructed_states(rng, n_per_region, mat, plane_strain):
    """Trial stresses of every region with their exact return and expected code."""
    trials, expected, codes = [], [], []
    for region in range(5):
        for _ in range(n_per_region):
            surface, trial = surface_and_trial(rng, region, mat)
            V = plane_strain_axes(rng) if plane_strain else random_rotation(rng)
            trials.append(V @ np.diag(trial) @ V.T)
            expected.append(V @ np.diag(surface) @ V.T)
            codes.append(region)
    trials, expected = np.array(trials), np.array(expected)
    symmetric = [0.5 * (x + x.transpose(0, 2, 1)) for x in (trials, expected)]  # round-off
    return *symmetric, np.array(codes)


def random_states(rng, n, plane_strain):
    """Random stresses around the apex scale and random velocity gradients."""
    A = rng.normal(size=(n, 3, 3)) * rng.uniform(10.0, 3000.0, (n, 1, 1))
    sig = 0.5 * (A + A.transpose(0, 2, 1)) - rng.uniform(-1000.0, 3000.0, (n, 1, 1)) * np.eye(3)
    L = rng.normal(size=(n, 3, 3)) * 0.5
    if plane_strain:
        for x in (sig, L):
            x[:, :2, 2] = 0.0
            x[:, 2, :2] = 0.0
        L[:, 2, 2] = 0.0
    return sig, L


def run(stress, L, mat, dt=DT):
    """The parallel kernel on copies; returns (new stresses, codes)."""
    new = np.array(stress, dtype=float)
    codes = np.zeros(len(new), dtype=np.int8)
    active = np.ones(len(new), dtype=np.uint8)
    mc.update_stresses(new, np.ascontiguousarray(L, dtype=float), active, dt, *mat, codes)
    return new, codes


def scale_of(x):
    return np.maximum(np.abs(x).max(axis=(-2, -1)), COHESION)


# --------------------------------------------------------------------------------------
# Elastic constants
# --------------------------------------------------------------------------------------


def test_elastic_constants_and_p_wave_speed():
    k, g, lam = mc.elastic_constants(E, NU)
    assert k == pytest.approx(E / (3 * (1 - 2 * NU)), rel=1e-14)
    assert g == pytest.approx(E / (2 * (1 + NU)), rel=1e-14)
    assert lam == pytest.approx(E * NU / ((1 + NU) * (1 - 2 * NU)), rel=1e-12)
    # DESIGN §7: about 49.6 m/s for the paper's material
    assert mc.p_wave_speed(E, NU, RHO) == pytest.approx(49.6, abs=0.1)


# --------------------------------------------------------------------------------------
# Exact returns of constructed trial states, all five regions
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("plane_strain", [False, True], ids=["3d", "plane-strain"])
@pytest.mark.parametrize("name", list(MATERIALS))
def test_constructed_trials_return_to_their_surface_point(name, plane_strain):
    mat = MATERIALS[name]
    rng = np.random.default_rng(11)
    trials, expected, codes = constructed_states(rng, 12, mat, plane_strain)
    new, got = run(trials, np.zeros_like(trials), mat)
    np.testing.assert_array_equal(got, codes)
    err = np.abs(new - expected).max(axis=(1, 2)) / scale_of(trials)
    assert err.max() <= 1e-10

    principal = np.linalg.eigvalsh(new)[:, ::-1]
    edge_c, edge_e, apex = (codes == c for c in (2, 3, 4))
    pair = np.abs(principal[:, 0] - principal[:, 1]) / scale_of(trials)
    assert pair[edge_c].max() <= 1e-12
    pair = np.abs(principal[:, 1] - principal[:, 2]) / scale_of(trials)
    assert pair[edge_e].max() <= 1e-12
    np.testing.assert_array_equal(
        new[apex], np.broadcast_to(apex_stress(mat) * np.eye(3), new[apex].shape)
    )
    assert np.all(new[codes == 0] == trials[codes == 0])  # elastic: untouched when L = 0


# --------------------------------------------------------------------------------------
# numba against the NumPy twin
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("plane_strain", [False, True], ids=["3d", "plane-strain"])
def test_numba_matches_reference(plane_strain):
    rng = np.random.default_rng(5 + plane_strain)
    seen = set()
    for mat in MATERIALS.values():
        built, _, _ = constructed_states(rng, 10, mat, plane_strain)
        sig, L = random_states(rng, 150, plane_strain)
        sig = np.concatenate([built, sig])
        L = np.concatenate([rng.normal(size=built.shape) * 0.05, L])
        if plane_strain:
            L[:, :2, 2] = L[:, 2, :2] = L[:, 2, 2] = 0.0
        new, codes = run(sig, L, mat)
        active = np.ones(len(sig), dtype=bool)
        expect, expect_codes = ref.update_stresses(sig, L, active, DT, *mat)
        np.testing.assert_array_equal(codes, expect_codes)
        err = np.abs(new - expect).max(axis=(1, 2)) / scale_of(sig)
        assert err.max() <= 1e-10
        if plane_strain:
            assert np.all(new[:, :2, 2] == 0.0) and np.all(new[:, 2, :2] == 0.0)
        assert np.all(new == new.transpose(0, 2, 1))
        seen |= set(codes.tolist())
    assert seen == {0, 1, 2, 3, 4}


def test_single_particle_matches_parallel_loop_and_skips_inactive():
    rng = np.random.default_rng(3)
    mat = MATERIALS["table1"]
    sig, L = random_states(rng, 40, plane_strain=False)
    new = sig.copy()
    codes = np.zeros(40, dtype=np.int8)
    active = (np.arange(40) % 3 != 0).astype(np.uint8)
    mc.update_stresses(new, L, active, DT, *mat, codes)
    for p in range(40):
        one = sig[p].copy()
        if active[p]:
            assert mc.update_stress(one, L[p], DT, *mat) == codes[p]
            np.testing.assert_array_equal(one, new[p])
        else:
            assert codes[p] == mc.INACTIVE
            np.testing.assert_array_equal(new[p], sig[p])


# --------------------------------------------------------------------------------------
# Kuhn–Tucker conditions of the return, by non-negative least squares
# --------------------------------------------------------------------------------------


def kuhn_tucker_residual(trial, new, mat):
    """Check coaxiality, f ≤ 0 and Δσ in the cone of the active planes' C:∂g/∂σ."""
    _, _, sphi, cphi, c, spsi, _ = mat
    values, V = np.linalg.eigh(trial)
    scale = max(np.abs(values).max(), c, 1.0)
    in_axes = V.T @ new @ V
    assert np.abs(in_axes - np.diag(np.diag(in_axes))).max() <= 1e-10 * scale
    n = np.diag(in_axes)
    f = np.array([normal(i, j, sphi) @ n - 2 * c * cphi for i, j in PAIRS])
    assert f.max() <= 1e-9 * scale  # admissible
    step = values - n
    if np.abs(step).max() <= 1e-12 * scale:  # elastic (up to the twin's round-off)
        return 0.0, f
    assert np.abs(f.max()) <= 1e-9 * scale  # plastic: on the surface
    active = [k for k, (i, j) in enumerate(PAIRS) if f[k] >= -1e-9 * scale]
    R = np.column_stack([direction(normal(*PAIRS[k], spsi)) for k in active])
    _, residual = nnls(R, step)
    return residual / np.abs(step).max(), f


@pytest.mark.parametrize("name", list(MATERIALS))
def test_return_satisfies_kuhn_tucker(name):
    mat = MATERIALS[name]
    rng = np.random.default_rng(21)
    sig, L = random_states(rng, 150, plane_strain=False)
    built, _, _ = constructed_states(rng, 10, mat, plane_strain=False)
    sig, L = np.concatenate([sig, built]), np.concatenate([L, np.zeros_like(built)])
    new, codes = run(sig, L, mat)
    for p in range(len(sig)):
        trial = ref.elastic_trial(sig[p], L[p], DT, K, G)
        residual, _ = kuhn_tucker_residual(trial, new[p], mat)
        assert residual <= 1e-9
        f_new = mc.yield_value(new[p], *mat[2:5])
        assert f_new <= 1e-9 * scale_of(trial)
        if codes[p] == mc.ELASTIC:
            assert ref.yield_value(trial, *mat[2:5]) <= 0.0
            np.testing.assert_allclose(new[p], trial, rtol=0, atol=1e-12 * scale_of(trial))
        else:
            assert abs(f_new) <= 1e-9 * scale_of(trial)


def test_plane_return_follows_the_plastic_potential_not_the_yield_normal():
    mat = MATERIALS["dilatant"]  # ψ = 10° ≠ φ = 27.1°
    _, _, sphi, _, _, spsi, _ = mat
    rng = np.random.default_rng(8)
    trials, _, codes = constructed_states(rng, 30, mat, plane_strain=False)
    trials = trials[codes == mc.PLANE]
    new, got = run(trials, np.zeros_like(trials), mat)
    assert np.all(got == mc.PLANE)

    def elastic_image(values, V, sine):  # C : ∂/∂σ of (1 + sin) σ1 − (1 − sin) σ3
        N = (1 + sine) * np.outer(V[:, 2], V[:, 2]) - (1 - sine) * np.outer(V[:, 0], V[:, 0])
        return LAM * np.trace(N) * np.eye(3) + 2 * G * N

    for trial, sig in zip(trials, new, strict=True):
        values, V = np.linalg.eigh(trial)  # ascending: column 2 is σ1, column 0 is σ3
        step = (trial - sig).ravel()
        for sine, parallel in ((spsi, True), (sphi, False)):
            m = elastic_image(values, V, sine).ravel()
            cosine = step @ m / (np.linalg.norm(step) * np.linalg.norm(m))
            if parallel:
                assert cosine == pytest.approx(1.0, abs=1e-12)
            else:
                assert cosine < 1.0 - 1e-4


# --------------------------------------------------------------------------------------
# Objectivity and rotation
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["table1", "dilatant"])
def test_update_is_objective(name):
    mat = MATERIALS[name]
    rng = np.random.default_rng(17)
    sig, L = random_states(rng, 200, plane_strain=False)
    Q = np.array([random_rotation(rng) for _ in range(len(sig))])
    new, codes = run(sig, L, mat)
    turned, turned_codes = run(Q @ sig @ Q.transpose(0, 2, 1), Q @ L @ Q.transpose(0, 2, 1), mat)
    np.testing.assert_array_equal(codes, turned_codes)
    assert set(codes.tolist()) >= {0, 1, 2, 3, 4}
    err = np.abs(turned - Q @ new @ Q.transpose(0, 2, 1)).max(axis=(1, 2)) / scale_of(sig)
    assert err.max() <= 1e-10


def test_pure_spin_keeps_principal_stresses_and_converges_second_order():
    rng = np.random.default_rng(2)
    mat = MATERIALS["table1"]
    V = random_rotation(rng)
    sig0 = V @ np.diag([-1500.0, -2000.0, -2600.0]) @ V.T  # well inside the yield surface
    axis = rng.normal(size=3)
    w = axis / np.linalg.norm(axis) * 2.0  # 2 rad/s
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    total = 1.0
    exact = expm(W * total) @ sig0 @ expm(W * total).T
    errors = []
    for n in (20, 40, 80):
        sig = sig0.copy()
        for _ in range(n):
            assert mc.update_stress(sig, W, total / n, *mat) == mc.ELASTIC
        np.testing.assert_allclose(
            np.linalg.eigvalsh(sig), [-2600.0, -2000.0, -1500.0], rtol=0, atol=1e-10
        )
        errors.append(np.abs(sig - exact).max())
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    np.testing.assert_allclose(ratios, 4.0, rtol=0.02)


# --------------------------------------------------------------------------------------
# Material response
# --------------------------------------------------------------------------------------


def test_biaxial_compression_reaches_mohr_coulomb_strength():
    """Plane strain: lateral σxx held at −p, axial strain rate along y, z fixed."""
    mat = MATERIALS["table1"]
    _, _, sphi, cphi, c, _, _ = mat
    p_lateral, rate, dt = 1000.0, 0.02, 1e-3
    sig = -p_lateral * np.eye(3)

    def trial(dxx):
        s = sig.copy()
        code = mc.update_stress(s, np.diag([dxx, -rate, 0.0]), dt, *mat)
        return s[0, 0] + p_lateral, s, code

    axial = []
    for _ in range(150):
        x = LAM / (LAM + 2 * G) * rate  # elastic guess of the lateral stretching rate
        for _ in range(30):  # Newton on a piecewise-linear function
            g0, s, code = trial(x)
            if abs(g0) <= 1e-10 * p_lateral:
                break
            g1, _, _ = trial(x + 1e-3 * rate)
            x -= g0 * 1e-3 * rate / (g1 - g0)
        else:
            raise AssertionError("lateral stress control did not converge")
        sig = s
        axial.append(-sig[1, 1])

    strength = (p_lateral * (1 + sphi) + 2 * c * cphi) / (1 - sphi)  # compression positive
    assert code == mc.PLANE
    assert axial[-1] == pytest.approx(strength, rel=1e-6)
    assert np.ptp(axial[-20:]) <= 1e-6 * strength  # steady
    assert -strength < sig[2, 2] < -p_lateral  # σzz stays the intermediate stress
    assert strength == pytest.approx(2957.9, abs=0.1)


def test_tension_cutoff_caps_the_largest_principal_stress():
    base = MATERIALS["table1"][:-1]
    elastic = np.diag([50.0, -20.0, -100.0])  # f < 0 with 50 Pa tension
    one = elastic.copy()
    assert mc.update_stress(one, np.zeros((3, 3)), DT, *base, 10.0) == mc.TENSION_CAP
    np.testing.assert_array_equal(one, np.diag([10.0, -20.0, -100.0]))
    one = elastic.copy()  # a cutoff above c cot φ = 170.0 Pa changes nothing here
    assert mc.update_stress(one, np.zeros((3, 3)), DT, *base, 1e6) == mc.ELASTIC
    np.testing.assert_array_equal(one, elastic)

    apex = apex_stress(MATERIALS["table1"])
    assert apex == pytest.approx(170.0, abs=0.1)
    for cutoff, code, value in ((50.0, mc.TENSION_CAP, 50.0), (500.0, mc.APEX, apex)):
        one = 1000.0 * np.eye(3)
        assert mc.update_stress(one, np.zeros((3, 3)), DT, *base, cutoff) == code
        np.testing.assert_array_equal(one, value * np.eye(3))
        twin, twin_code = ref.update_stress(1000.0 * np.eye(3), np.zeros((3, 3)), DT, *base, cutoff)
        assert twin_code == code
        np.testing.assert_array_equal(twin, one)


def test_tresca_has_no_apex_and_no_division_by_zero():
    mat = material(phi=0.0, psi=0.0)  # sin φ = 0: cot φ is never formed
    zero = np.zeros((3, 3))
    cases = [
        (1e4 * np.eye(3), mc.ELASTIC, 1e4 * np.eye(3)),  # no limit on hydrostatic tension
        (np.diag([500.0, 0.0, -500.0]), mc.PLANE, np.diag([87.0, 0.0, -87.0])),
        # edges: (x, x, x − 2c) and (y + 2c, y, y) with the trace kept
        (np.diag([500.0, 500.0, -500.0]), mc.EDGE_COMPRESSION, np.diag([674, 674, 152]) / 3),
        (np.diag([500.0, -500.0, -500.0]), mc.EDGE_EXTENSION, np.diag([-152, -674, -674]) / 3),
    ]
    for sig, code, expected in cases:
        one = sig.copy()
        assert mc.update_stress(one, zero, DT, *mat) == code
        # deviatoric flow (ψ = 0) keeps the mean stress
        assert np.trace(one) == pytest.approx(np.trace(sig), rel=1e-12)
        np.testing.assert_allclose(one, expected, rtol=0, atol=1e-9)
        values = np.linalg.eigvalsh(one)
        assert values[-1] - values[0] == pytest.approx(min(2 * 87.0, np.ptp(np.diag(sig))))
    one = 1e4 * np.eye(3)
    assert mc.update_stress(one, zero, DT, *mat[:-1], 30.0) == mc.TENSION_CAP
    np.testing.assert_array_equal(one, 30.0 * np.eye(3))

    rng = np.random.default_rng(4)
    sig, L = random_states(rng, 200, plane_strain=False)
    new, codes = run(sig, L, mat)
    expect, expect_codes = ref.update_stresses(sig, L, np.ones(200, bool), DT, *mat)
    assert np.all(np.isfinite(new))
    np.testing.assert_array_equal(codes, expect_codes)
    assert np.abs(new - expect).max() <= 1e-10 * np.abs(sig).max()
    spread = np.ptp(np.linalg.eigvalsh(new), axis=1)
    assert spread.max() <= 2 * 87.0 * (1 + 1e-12)


def test_yield_value_and_principal_stresses():
    rng = np.random.default_rng(9)
    sig, _ = random_states(rng, 50, plane_strain=False)
    flat, _ = random_states(rng, 50, plane_strain=True)
    for s in np.concatenate([sig, flat]):
        values = np.linalg.eigvalsh(s)[::-1]
        np.testing.assert_allclose(mc.principal_stresses(s), values, rtol=0, atol=1e-11 * 1e4)
        f = mc.yield_value(s, *MATERIALS["table1"][2:5])
        assert f == pytest.approx(ref.yield_value(s, *MATERIALS["table1"][2:5]), abs=1e-8)
    # the invariant bounds that let the 3-D path skip the eigen-decomposition are bounds
    sphi, cphi, c = MATERIALS["table1"][2:5]
    for s in sig:
        f_bound, s1_bound = mc._invariant_bounds(
            tuple(s[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]), sphi, cphi, c
        )
        assert f_bound >= mc.yield_value(s, sphi, cphi, c) - 1e-9
        assert s1_bound >= np.linalg.eigvalsh(s)[-1] - 1e-9
    # the paper's material: f at the apex and on the Tresca-like uniaxial state
    _, _, sphi, cphi, c, _, _ = MATERIALS["table1"]
    assert mc.yield_value(apex_stress(MATERIALS["table1"]) * np.eye(3), sphi, cphi, c) == (
        pytest.approx(0.0, abs=1e-12)
    )


@pytest.mark.parametrize(
    "spectrum",
    ["distinct", "double-root", "near-double", "near-hydrostatic", "rank-one", "diagonal"],
)
def test_closed_form_eigensolver_is_accurate_to_round_off(spectrum):
    # the closed form must match LAPACK to round-off of |A| also where the cubic's roots
    # are ill-conditioned (repeated and nearly repeated eigenvalues)
    rng = np.random.default_rng(21)
    for _ in range(400):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        d = {
            "distinct": rng.normal(size=3) * 1e3,
            "double-root": np.array([-2e3, -2e3, -5e2]),
            "near-double": np.array([-2e3, -2e3 * (1 + 10.0 ** rng.uniform(-15, -4)), -5e2]),
            "near-hydrostatic": -1e4 + rng.normal(size=3) * 10.0 ** rng.uniform(-10, 0),
            "rank-one": np.array([0.0, 0.0, rng.normal()]),
            "diagonal": rng.normal(size=3),
        }[spectrum]
        a = q @ np.diag(d) @ q.T if spectrum != "diagonal" else np.diag(d)
        a = 0.5 * (a + a.T)
        out = mc._eigh3((a[0, 0], a[1, 1], a[2, 2], a[0, 1], a[0, 2], a[1, 2]))
        values = np.array(out[:3])
        vectors = np.array(out[3:]).reshape(3, 3).T  # columns
        scale = np.abs(a).max()
        np.testing.assert_allclose(
            np.sort(values), np.linalg.eigvalsh(a), rtol=0, atol=1e-14 * scale
        )
        np.testing.assert_allclose(vectors.T @ vectors, np.eye(3), rtol=0, atol=1e-14)
        np.testing.assert_allclose(a @ vectors, vectors * values, rtol=0, atol=1e-14 * scale)


@pytest.mark.parametrize("contact", [False, True], ids=["no-contact", "lost-contact"])
def test_batched_trial_is_the_scalar_trial_bit_for_bit(contact):
    # trial_batch (the SIMD loop of the 3-D G2P) against trial_stress particle by
    # particle: the same operations in the same order, so the same bits, with gaps that
    # a compression closes in part, closes completely, or that an extension leaves open
    rng = np.random.default_rng(29)
    n = 50
    sig, L = random_states(rng, n, False)
    L[: n // 2] -= np.eye(3) * rng.uniform(0.0, 3.0, (n // 2, 1, 1))  # compressions
    gaps = rng.choice([0.0, 1e-5, 1e-3, 0.5], n)
    old = np.array([[s[i, j] for s in sig] for i, j in STRESS_ROWS])
    grad = L.reshape(n, 9).T.copy()
    trial = np.full((7, n), np.nan)
    gap = gaps.copy()
    mc.trial_batch(old, grad, trial, gap, 0, n, DT, LAM, G, contact)
    for p in range(n):
        s = tuple(old[:, p])
        want, want_gap = mc.trial_stress(s, tuple(L[p].reshape(-1)), DT, LAM, G, gaps[p], contact)
        assert tuple(trial[:6, p]) == want
        assert gap[p] == want_gap
    closed = gap < gaps
    assert contact == closed.any() and np.all(gap >= 0.0)


def _batched_returns(trials, width, mat, cutoff):
    """Stresses and codes of eigh3_batch + return_batch over blocks of ``width`` trials."""
    K, G, sin_phi, cos_phi, c, sin_psi, _ = mat
    lam = K - 2.0 * G / 3.0
    n = len(trials)
    stress = np.zeros((n, 3, 3))
    codes = np.full(n, -9, np.int8)
    gap = np.zeros(n)
    work = tuple(w[0] for w in mc.batch_work(1, width))
    for lo in range(0, n, width):
        m = min(width, n - lo)
        for w in work:
            w[...] = np.nan  # nothing may be read that this block did not write
        for r, (i, j) in enumerate(STRESS_ROWS):
            work[0][r, :m] = trials[lo : lo + m, i, j]
        mc.eigh3_batch(*work[:5], m)
        mc.return_batch(lo, m, work[0], work[2], work[3], work[4], work[5], work[6], stress,
                        codes, gap, False, lam, G, sin_phi, cos_phi, c, sin_psi,
                        cutoff)  # fmt: skip
    return stress, codes, gap


STRESS_ROWS = [(0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2)]


@pytest.mark.parametrize("width", [mc.BATCH_BLOCK, 37])
@pytest.mark.parametrize("name", list(MATERIALS))
def test_batched_return_matches_the_scalar_return(name, width):
    # the SIMD block path of the 3-D G2P (eigh3_batch + return_batch) against the scalar
    # general return, on every region's trials and random ones, and on trials beyond
    # SAFE_RANGE, which return_batch must send to the rescaling scalar decomposition;
    # blocks of BATCH_BLOCK take the vectorised elastic and plane returns, blocks of
    # another width the same steps unvectorised, and both end in partial blocks
    mat = MATERIALS[name]
    K, G, sin_phi, cos_phi, c, sin_psi, cutoff = mat
    lam = K - 2.0 * G / 3.0
    rng = np.random.default_rng(17)
    built, _, _ = constructed_states(rng, 8, mat, False)
    sig, _ = random_states(rng, 100 + mc.BATCH_BLOCK, False)
    trials = np.concatenate([built, sig, sig[:5] * 1e95])
    n = len(trials)
    rows = STRESS_ROWS
    stress, codes, gap = _batched_returns(trials, width, mat, cutoff)
    for p in range(n):
        s = tuple(trials[p][i, j] for i, j in rows)
        want, code = mc._return_general(s, lam, G, sin_phi, cos_phi, c, sin_psi, cutoff)
        assert codes[p] == code
        got = tuple(stress[p][i, j] for i, j in rows)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(trials[p]).max())
    assert set(codes.tolist()) >= {0, 1, 2, 3, 4}
    assert np.all(gap == 0.0)  # no lost contact asked for
