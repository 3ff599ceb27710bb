"""Hypoelastic Mohr–Coulomb stress update of the material point solver (numba kernels).

Conventions
-----------
Tension is positive. Each particle carries a symmetric 3×3 Cauchy stress (rows of an
``(N, 3, 3)`` float64 array) and a velocity gradient ``L[i, j] = dv_i/dx_j`` of the same
layout; 2-D plane strain uses the same layout with the z row and column of ``L`` zero, so
σxz = σyz = 0 while σzz evolves. Strain rate D = sym(L), spin W = skew(L). Material
constants are plain floats: bulk modulus K, shear modulus G (λ = K − 2G/3), sin φ, cos φ,
cohesion c, sin ψ and a tension cutoff.

One step of :func:`update_stress`
---------------------------------
(a) Jaumann rotation. σ ← Q σ Qᵀ with the Hughes–Winget (Cayley) rotation
    Q = (I − dt W/2)⁻¹ (I + dt W/2), written in closed form as
    Q = I + 2 (Ω + Ω²) / (1 + |ω|²), Ω = dt W / 2 with axial vector ω. Q is exactly
    orthogonal, so a pure spin keeps the principal stresses to round-off, and
    Q σ Qᵀ = σ + dt (W σ − σ W) + O(dt²): a second-order accurate integration of the
    Jaumann rate (the rotation angle per step is 2 atan(|ω|) instead of 2 |ω|).
(b) Elastic trial. σ ← σ + dt (λ tr(D) I + 2 G D).
(c) Mohr–Coulomb return in principal stresses σ1 ≥ σ2 ≥ σ3 of the trial state::

        f = (σ1 − σ3) + (σ1 + σ3) sin φ − 2 c cos φ ≤ 0,
        g = (σ1 − σ3) + (σ1 + σ3) sin ψ          (plastic potential, non-associated).

    In the sorted sextant f = a·σ − 2c cos φ with a = (1 + sin φ, 0, −(1 − sin φ)) and
    ∂g/∂σ = b = (1 + sin ψ, 0, −(1 − sin ψ)). For an isotropic elastic tangent the
    eigenvectors stay fixed during the return, which is then a problem in the space of
    principal stresses with C = λ 1⊗1 + 2G I. Each plane i has its return direction
    R_i = C b_i; the stress leaves the trial along a non-negative combination of the R_i
    of the active planes (for ψ = φ this is the closest point in the energy norm of C).
    The neighbours of the main plane are plane "2" (σ2 max, σ3 min), meeting it on the
    triaxial-compression edge σ1 = σ2, and plane "6" (σ1 max, σ2 min), meeting it on the
    triaxial-extension edge σ2 = σ3; all six planes meet at the apex σ1 = σ2 = σ3 = c cot φ.

    Regions (after Clausen, Damkilde & Andersen, derived here for non-associated flow).
    Seen along the ray of R1, the trial states outside the yield surface split into
    wedges around it, in turn: plane (between the planes spanned by R1 and each edge
    line), compression edge (from span(R1, edge σ1 = σ2) to span(R1, R2)), apex (from
    span(R1, R2) to span(R1, R6)) and extension edge. The tests are signs of linear
    functions of the trial state that vanish on those boundary planes:

    1. Plane return σp = σ_t − (f_t / a·R1) R1. If σp is still ordered, done (code 1).
       σp1 < σp2 puts the trial past span(R1, edge σ1 = σ2), σp2 < σp3 past
       span(R1, edge σ2 = σ3).
    2. Both orders broken: apex (code 4). R2 lies on the unbroken side of the second
       boundary (its plane return has σ2 − σ3 = 2G (2 − (1 − sin ψ) a·R2 / a·R1) > 0, as
       a·R2 < a·R1), and R6 likewise, so the wedge past both boundaries lies between
       span(R1, R2) and span(R1, R6), inside the apex wedge.
    3. One order broken: edge return σe = σ_t − Δγ1 R1 − Δγ_B R_B with
       f1(σe) = f_B(σe) = 0 (a 2×2 system; B = plane 2 for σp1 < σp2, plane 6 for
       σp2 < σp3). If σe is on the compression side of the apex (the equal pair not below,
       resp. not above, the third stress) the trial lies before span(R1, R_B) and σe is the
       answer (code 2 or 3, the pair set to its mean so it is exactly equal); otherwise
       the apex, σ = c cot φ I (code 4).

    The Kuhn–Tucker conditions (non-negative Δγ of the active planes, f ≤ 0) hold for
    ψ > 0. With ψ = 0 the flow directions are deviatoric and cannot reach the apex from a
    trial whose mean stress exceeds c cot φ; such trials are still put on the apex (the
    mean stress is then projected, not flowed). For φ = 0 (Tresca) the edges are parallel
    and there is no apex: step 2 cannot occur and step 3 never leaves the edge, so cot φ
    is never formed.
(d) Tension cutoff. If ``tension_cutoff > 0`` the principal stresses are capped at
    t = min(tension_cutoff, c cot φ) (t = tension_cutoff when φ = 0): a Rankine cap
    applied after the Mohr–Coulomb return, in the same eigenbasis, not a joint
    closest-point return. It reports code 5 when it lowered a stress.
(e) Lost contact (:func:`close_gap`, :func:`open_gap`, used by the MPM kernels unless
    the scene turns ``solver.lost_contact`` off; the single-particle
    :func:`update_stress` has no gap). The volumetric plastic strain of
    an apex or cap return is kept as the particle's gap; a later compression closes the
    gap first, stress-free, and only the rest enters the elastic trial. Without it the
    volume of a flowing layer ratchets up (extension at the apex is free, compression
    elastic). The kernels cap each gap at the packing deficit of the node masses around
    the particle before its update (``kernels._bounded_gap``).

Eigen-decomposition without allocation: when σxz = σyz = 0 after the elastic trial (always
the case in plane strain, where W and D have no z coupling, since the Cayley rotation then
keeps exact zeros) σzz is principal and the in-plane 2×2 block is decomposed in closed
form; otherwise a closed-form decomposition of the 3×3 tensor (the cubic's most separated
root, its vector from cross products, one exact 2×2 rotation for the other pair; see
:func:`_eigh3`) gives eigenvalues and eigenvectors to round-off without iterating,
skipped when bounds from the invariants p and J2 already prove the trial elastic. The
corrected stress is σ_t + Σ_k (σk_new − σk_trial) v_k v_kᵀ, so an unchanged principal
stress costs no round-off.

Return codes (:data:`ELASTIC` ... :data:`TENSION_CAP`; :data:`INACTIVE` marks skipped
particles in :func:`update_stresses`) let tests and diagnostics count what happened.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

__all__ = [
    "APEX",
    "BATCH_BLOCK",
    "BATCH_ROWS",
    "EDGE_COMPRESSION",
    "EDGE_EXTENSION",
    "ELASTIC",
    "INACTIVE",
    "PLANE",
    "SAFE_RANGE",
    "TENSION_CAP",
    "batch_work",
    "close_gap",
    "eigh3_batch",
    "elastic_constants",
    "open_gap",
    "p_wave_speed",
    "principal_stresses",
    "rate_friction",
    "read_stress",
    "return_batch",
    "stress_step",
    "trial_stress",
    "update_stress",
    "update_stresses",
    "write_stress",
    "yield_value",
]

#: Return codes of :func:`update_stress`.
ELASTIC, PLANE, EDGE_COMPRESSION, EDGE_EXTENSION, APEX, TENSION_CAP = 0, 1, 2, 3, 4, 5
#: Code written by :func:`update_stresses` for particles it skipped.
INACTIVE = -1

# error_model="numpy": no zero-division checks in the hot path (no division can see a zero).
_JIT = {"cache": True, "fastmath": False, "error_model": "numpy"}

# --------------------------------------------------------------------------------------
# Elastic constants
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def elastic_constants(E, nu):
    """Bulk modulus, shear modulus and Lamé's λ of an isotropic linear material.

    Parameters
    ----------
    E : float
        Young's modulus, Pa.
    nu : float
        Poisson's ratio.

    Returns
    -------
    K, G, lam : float
        K = E / (3 (1 − 2ν)), G = E / (2 (1 + ν)), λ = K − 2G/3, Pa.
    """
    K = E / (3.0 * (1.0 - 2.0 * nu))
    G = E / (2.0 * (1.0 + nu))
    return K, G, K - 2.0 * G / 3.0


@njit(**_JIT)
def p_wave_speed(E, nu, rho):
    """P-wave speed c_p = √((K + 4G/3) / ρ), m/s, which bounds the explicit time step.

    Parameters
    ----------
    E : float
        Young's modulus, Pa.
    nu : float
        Poisson's ratio.
    rho : float
        Density, kg/m³.
    """
    K, G, _ = elastic_constants(E, nu)
    return math.sqrt((K + 4.0 * G / 3.0) / rho)


# --------------------------------------------------------------------------------------
# Small linear algebra on scalars. A symmetric tensor travels as the 6-tuple
# (s00, s11, s22, s01, s02, s12); nothing here allocates.
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def _read(sig):
    return (sig[0, 0], sig[1, 1], sig[2, 2], sig[0, 1], sig[0, 2], sig[1, 2])


@njit(**_JIT)
def _write(sig, s):
    sig[0, 0] = s[0]
    sig[1, 1] = s[1]
    sig[2, 2] = s[2]
    sig[0, 1] = s[3]
    sig[1, 0] = s[3]
    sig[0, 2] = s[4]
    sig[2, 0] = s[4]
    sig[1, 2] = s[5]
    sig[2, 1] = s[5]


@njit(**_JIT)
def _spin_rotation(l, dt):
    """Hughes–Winget rotation Q = (I − Ω)⁻¹ (I + Ω), Ω = dt skew(L) / 2, row by row.

    ``l`` is the velocity gradient as a 9-tuple, row by row.
    """
    h = 0.25 * dt
    w1 = h * (l[7] - l[5])
    w2 = h * (l[2] - l[6])
    w3 = h * (l[3] - l[1])
    ww = w1 * w1 + w2 * w2 + w3 * w3
    k = 2.0 / (1.0 + ww)
    # Q = I + k (Ω + ω ωᵀ − |ω|² I); the diagonal keeps an exact 1 for a spin about one axis.
    return (
        1.0 + k * (w1 * w1 - ww),
        k * (w1 * w2 - w3),
        k * (w1 * w3 + w2),
        k * (w1 * w2 + w3),
        1.0 + k * (w2 * w2 - ww),
        k * (w2 * w3 - w1),
        k * (w1 * w3 - w2),
        k * (w2 * w3 + w1),
        1.0 + k * (w3 * w3 - ww),
    )


@njit(**_JIT)
def _rotate(q, s):
    """Q σ Qᵀ for Q given row by row (9-tuple) and symmetric σ (6-tuple)."""
    q00, q01, q02, q10, q11, q12, q20, q21, q22 = q
    s00, s11, s22, s01, s02, s12 = s
    # T = Q σ
    t00 = q00 * s00 + q01 * s01 + q02 * s02
    t01 = q00 * s01 + q01 * s11 + q02 * s12
    t02 = q00 * s02 + q01 * s12 + q02 * s22
    t10 = q10 * s00 + q11 * s01 + q12 * s02
    t11 = q10 * s01 + q11 * s11 + q12 * s12
    t12 = q10 * s02 + q11 * s12 + q12 * s22
    t20 = q20 * s00 + q21 * s01 + q22 * s02
    t21 = q20 * s01 + q21 * s11 + q22 * s12
    t22 = q20 * s02 + q21 * s12 + q22 * s22
    return (
        t00 * q00 + t01 * q01 + t02 * q02,
        t10 * q10 + t11 * q11 + t12 * q12,
        t20 * q20 + t21 * q21 + t22 * q22,
        t00 * q10 + t01 * q11 + t02 * q12,
        t00 * q20 + t01 * q21 + t02 * q22,
        t10 * q20 + t11 * q21 + t12 * q22,
    )


@njit(**_JIT)
def _elastic_increment(s, l, dt, lam, G):
    """σ + dt (λ tr(D) I + 2 G D) with D = sym(L), L the 9-tuple ``l`` row by row."""
    iso = dt * lam * (l[0] + l[4] + l[8])
    g2 = 2.0 * G * dt
    gs = G * dt  # 2 G D_ij = G (L_ij + L_ji)
    return (
        s[0] + iso + g2 * l[0],
        s[1] + iso + g2 * l[4],
        s[2] + iso + g2 * l[8],
        s[3] + gs * (l[1] + l[3]),
        s[4] + gs * (l[2] + l[6]),
        s[5] + gs * (l[5] + l[7]),
    )


@njit(inline="always", **_JIT)
def _sym_apply(a00, a11, a22, a01, a02, a12, u0, u1, u2):
    return (
        a00 * u0 + a01 * u1 + a02 * u2,
        a01 * u0 + a11 * u1 + a12 * u2,
        a02 * u0 + a12 * u1 + a22 * u2,
    )


#: x(r) = cos(acos(r) / 3) on [0, 1], the largest root of 4x³ − 3x = r: a degree-7
#: least-squares (Chebyshev) fit, largest error 2.8e-8; one Newton step on the cubic
#: (f' = 12x² − 3 ≥ 6 there, so the root is simple) brings it to 1.4e-15.
_CUBIC_ROOT_FIT = (
    0.866025431808084,
    0.166664556427006,
    -0.048073327457577794,
    0.024379220194368757,
    -0.014271708953769615,
    0.007659054070378099,
    -0.002930990987853107,
    0.0005477855432569341,
)

# The closed-form eigen-decomposition in four steps. Each is free of branches (the
# choices are selects), so a loop over many matrices that calls them compiles to SIMD
# code (eigh3_batch); _eigh3 calls them for one matrix. They are inlined where they are
# called (inline="always"): a call left in a loop body would stop the vectorisation.


@njit(inline="always", **_JIT)
def _far_root(a00, a11, a22, a01, a02, a12):
    """The eigenvalue farthest from the other two (at least √3 p from both).

    Trigonometric solution of the characteristic cubic of the deviator B = A − qI,
    p² = tr(B²)/6, r = det(B)/(2p³): the largest eigenvalue q + 2p x(r) when r ≥ 0, the
    smallest q − 2p x(−r) when r < 0 (the cubic is odd), x the largest root of
    4x³ − 3x = r (a polynomial fit and a Newton step, no acos or cos).
    """
    q = (a00 + a11 + a22) * (1.0 / 3.0)
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) * (
        1.0 / 6.0
    )
    p = math.sqrt(p2)
    det_b = (
        b00 * (b11 * b22 - a12 * a12)
        - a01 * (a01 * b22 - a12 * a02)
        + a02 * (a01 * a12 - b11 * a02)
    )
    r = min(1.0, max(-1.0, 0.5 * det_b / (p2 * p if p2 > 0.0 else 1.0)))
    ra = abs(r)
    c = _CUBIC_ROOT_FIT
    x = ((((((c[7] * ra + c[6]) * ra + c[5]) * ra + c[4]) * ra + c[3]) * ra + c[2]) * ra
         + c[1]) * ra + c[0]  # fmt: skip
    x = x - (4.0 * x * x * x - 3.0 * x - ra) / (12.0 * x * x - 3.0)
    return q + math.copysign(2.0 * p * x, r)


@njit(inline="always", **_JIT)
def _far_eigenvector(a00, a11, a22, a01, a02, a12, alpha):
    """Unit eigenvector of a symmetric 3×3 for its most separated eigenvalue ``alpha``.

    The rows of A − αI span the plane orthogonal to the eigenvector; the largest of their
    three cross products is the best-conditioned normal of that plane (A = αI: e_x).
    """
    m00, m11, m22 = a00 - alpha, a11 - alpha, a22 - alpha
    x0, x1, x2 = a01 * a12 - a02 * m11, a02 * a01 - m00 * a12, m00 * m11 - a01 * a01
    y0, y1, y2 = a01 * m22 - a02 * a12, a02 * a02 - m00 * m22, m00 * a12 - a01 * a02
    z0, z1, z2 = m11 * m22 - a12 * a12, a12 * a02 - a01 * m22, a01 * a12 - m11 * a02
    nx = x0 * x0 + x1 * x1 + x2 * x2
    ny = y0 * y0 + y1 * y1 + y2 * y2
    nz = z0 * z0 + z1 * z1 + z2 * z2
    take = ny > nx
    x0, x1, x2, nx = (y0 if take else x0), (y1 if take else x1), (y2 if take else x2), max(nx, ny)
    take = nz > nx
    x0, x1, x2, nx = (z0 if take else x0), (z1 if take else x1), (z2 if take else x2), max(nx, nz)
    some = nx > 0.0
    inv = 1.0 / math.sqrt(nx if some else 1.0)
    return (x0 * inv if some else 1.0), (x1 * inv if some else 0.0), (x2 * inv if some else 0.0)


@njit(inline="always", **_JIT)
def _plane_basis(e0, e1, e2):
    """An orthonormal pair (u, w) spanning the plane orthogonal to the unit vector e."""
    first = abs(e0) > abs(e1)
    k = 1.0 / math.sqrt(e0 * e0 + e2 * e2 if first else e1 * e1 + e2 * e2)
    u0 = -e2 * k if first else 0.0
    u1 = 0.0 if first else e2 * k
    u2 = e0 * k if first else -e1 * k
    return u0, u1, u2, e1 * u2 - e2 * u1, e2 * u0 - e0 * u2, e0 * u1 - e1 * u0


@njit(inline="always", **_JIT)
def _pair_rotation(a00, a11, a22, a01, a02, a12, e0, e1, e2, u0, u1, u2, w0, w1, w2):
    """Eigenvalues (far, larger, smaller) and the rotation (c, s) of the 2×2 block.

    A restricted to span(u, w) is [[m00, m01], [m01, m11]]: eigenvalues mean ± radius,
    the larger one's vector c u + s w with (c, s) along (m01, big − m00) or
    (big − m11, m01), whichever is longer (the other may be all cancellation); the
    smaller one's is c w − s u. The far eigenvalue is the Rayleigh quotient eᵀAe.
    """
    au0, au1, au2 = _sym_apply(a00, a11, a22, a01, a02, a12, u0, u1, u2)
    aw0, aw1, aw2 = _sym_apply(a00, a11, a22, a01, a02, a12, w0, w1, w2)
    ae0, ae1, ae2 = _sym_apply(a00, a11, a22, a01, a02, a12, e0, e1, e2)
    m00 = u0 * au0 + u1 * au1 + u2 * au2
    m11 = w0 * aw0 + w1 * aw1 + w2 * aw2
    m01 = 0.5 * (u0 * aw0 + u1 * aw1 + u2 * aw2 + w0 * au0 + w1 * au1 + w2 * au2)
    mean = 0.5 * (m00 + m11)
    half = 0.5 * (m00 - m11)
    radius = math.sqrt(half * half + m01 * m01)
    big = mean + radius
    c0, c1, d0, d1 = m01, big - m00, big - m11, m01
    nc = c0 * c0 + c1 * c1
    nd = d0 * d0 + d1 * d1
    take = nd > nc
    c0, c1, nc = (d0 if take else c0), (d1 if take else c1), max(nc, nd)
    some = nc > 0.0  # else the block is mean I: any pair
    k = 1.0 / math.sqrt(nc if some else 1.0)
    far = e0 * ae0 + e1 * ae1 + e2 * ae2
    return far, big, mean - radius, (c0 * k if some else 1.0), (c1 * k if some else 0.0)


@njit(inline="always", **_JIT)
def _vectors(e0, e1, e2, u0, u1, u2, w0, w1, w2, c, s):
    """The 9 components of the eigenvector columns e, c u + s w, c w − s u."""
    return (
        e0, e1, e2,
        c * u0 + s * w0, c * u1 + s * w1, c * u2 + s * w2,
        c * w0 - s * u0, c * w1 - s * u1, c * w2 - s * u2,
    )  # fmt: skip


#: Largest-entry magnitudes the closed form takes without rescaling: p³ ~ |A|³ must
#: neither over- nor underflow. Stresses in Pa are always inside.
SAFE_RANGE = (1e-90, 1e90)


@njit(**_JIT)
def _eigh3(s):
    """Eigenvalues (e0, e1, e2) and eigenvector columns v0, v1, v2 of a symmetric 3×3.

    Closed form, no iteration: the most separated eigenvalue from the characteristic
    cubic (:func:`_far_root`), its eigenvector from the rows of A − αI, then the other
    two from the exact 2×2 diagonalisation in the plane orthogonal to it. The cubic's
    roots lose digits next to a double root, so only the far one is taken from it, and
    all eigenvalues come from the orthonormal vectors (a Rayleigh quotient and the exact
    2×2 eigenvalues): accurate to round-off of |A|, also for repeated eigenvalues (the
    pair is resolved by the 2×2 step, which is exact for any gap). Tested against
    LAPACK. A matrix outside :data:`SAFE_RANGE` is scaled by its largest entry first.

    Returns a 12-tuple: e0, e1, e2 (unsorted), then v0, v1, v2 (3 each).
    """
    a00, a11, a22, a01, a02, a12 = s
    size = max(abs(a00), abs(a11), abs(a22), abs(a01), abs(a02), abs(a12))
    if not size > 0.0:
        return a00, a11, a22, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0
    unscale = 1.0
    if size < SAFE_RANGE[0] or size > SAFE_RANGE[1]:
        unscale = size
        inv = 1.0 / size
        a00, a11, a22, a01, a02, a12 = (
            a00 * inv, a11 * inv, a22 * inv, a01 * inv, a02 * inv, a12 * inv
        )  # fmt: skip
    alpha = _far_root(a00, a11, a22, a01, a02, a12)
    e0, e1, e2 = _far_eigenvector(a00, a11, a22, a01, a02, a12, alpha)
    u0, u1, u2, w0, w1, w2 = _plane_basis(e0, e1, e2)
    far, big, small, c, sn = _pair_rotation(
        a00, a11, a22, a01, a02, a12, e0, e1, e2, u0, u1, u2, w0, w1, w2
    )
    return (unscale * far, unscale * big, unscale * small) + _vectors(
        e0, e1, e2, u0, u1, u2, w0, w1, w2, c, sn
    )


@njit(**_JIT)
def _eigvals_2x2(s):
    """Eigenvalues of a stress with σxz = σyz = 0: in-plane m ± r, then σzz; and m, h, r."""
    m = 0.5 * (s[0] + s[1])
    h = 0.5 * (s[0] - s[1])
    r = math.hypot(h, s[3])
    return m + r, m - r, s[2], h, r


@njit(**_JIT)
def _order3(e0, e1, e2):
    """Indices (i1, i2, i3) with e[i1] ≥ e[i2] ≥ e[i3]; ties keep index order."""
    i1, i2, i3 = 0, 1, 2
    a, b, c = e0, e1, e2
    if b > a:
        a, b = b, a
        i1, i2 = i2, i1
    if c > b:
        b, c = c, b
        i2, i3 = i3, i2
    if b > a:
        a, b = b, a
        i1, i2 = i2, i1
    return i1, i2, i3


@njit(**_JIT)
def _pick(i, x0, x1, x2):
    if i == 0:
        return x0
    if i == 1:
        return x1
    return x2


@njit(**_JIT)
def _slot(k, i1, i2, x1, x2, x3):
    """The value of sorted position 1, 2 or 3 that belongs to unsorted slot k."""
    if k == i1:
        return x1
    if k == i2:
        return x2
    return x3


@njit(**_JIT)
def principal_stresses(sig):
    """Principal stresses σ1 ≥ σ2 ≥ σ3 of one symmetric 3×3 stress (tension positive).

    Parameters
    ----------
    sig : ndarray, shape (3, 3)
        Symmetric stress, Pa.

    Returns
    -------
    s1, s2, s3 : float
        Sorted principal stresses, Pa.
    """
    s = _read(sig)
    if s[4] == 0.0 and s[5] == 0.0:
        e0, e1, e2, _, _ = _eigvals_2x2(s)
    else:
        e = _eigh3(s)
        e0, e1, e2 = e[0], e[1], e[2]
    i1, i2, i3 = _order3(e0, e1, e2)
    return _pick(i1, e0, e1, e2), _pick(i2, e0, e1, e2), _pick(i3, e0, e1, e2)


@njit(**_JIT)
def yield_value(sig, sin_phi, cos_phi, cohesion):
    """Mohr–Coulomb yield function f = (σ1 − σ3) + (σ1 + σ3) sin φ − 2 c cos φ, Pa.

    Parameters
    ----------
    sig : ndarray, shape (3, 3)
        Symmetric stress, Pa, tension positive.
    sin_phi, cos_phi : float
        Sine and cosine of the friction angle.
    cohesion : float
        Cohesion c, Pa.

    Returns
    -------
    float
        f ≤ 0 inside the yield surface.
    """
    s1, _, s3 = principal_stresses(sig)
    return (s1 - s3) + (s1 + s3) * sin_phi - 2.0 * cohesion * cos_phi


# --------------------------------------------------------------------------------------
# The return in principal stresses
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(**_JIT)
def _elastic_direction(b, lam, G):
    """C b = λ tr(b) (1, 1, 1) + 2G b in principal space."""
    iso = lam * (b[0] + b[1] + b[2])
    return (iso + 2.0 * G * b[0], iso + 2.0 * G * b[1], iso + 2.0 * G * b[2])


@njit(**_JIT)
def _edge_return(s, a1, r1, f1, aB, bB, k, lam, G):
    """σ_t − x R1 − y R_B with f1 = f_B = 0 after the step (2×2 system for x, y)."""
    rB = _elastic_direction(bB, lam, G)
    fB = _dot(aB, s) - k
    m11 = _dot(a1, r1)
    m12 = _dot(a1, rB)
    m21 = _dot(aB, r1)
    m22 = _dot(aB, rB)
    det = m11 * m22 - m12 * m21  # > 0: the diagonal dominates for any ψ, φ ≥ 0
    x = (f1 * m22 - m12 * fB) / det
    y = (m11 * fB - m21 * f1) / det
    return (
        s[0] - x * r1[0] - y * rB[0],
        s[1] - x * r1[1] - y * rB[1],
        s[2] - x * r1[2] - y * rB[2],
    )


@njit(**_JIT)
def _mohr_coulomb_return(s1, s2, s3, lam, G, sin_phi, cos_phi, cohesion, sin_psi):
    """Return of sorted trial principal stresses; (n1, n2, n3, code) with n1 ≥ n2 ≥ n3."""
    k = 2.0 * cohesion * cos_phi
    a1 = (1.0 + sin_phi, 0.0, -(1.0 - sin_phi))
    s = (s1, s2, s3)
    f1 = _dot(a1, s) - k
    if f1 <= 0.0:
        return s1, s2, s3, ELASTIC
    r1 = _elastic_direction((1.0 + sin_psi, 0.0, -(1.0 - sin_psi)), lam, G)
    g = f1 / _dot(a1, r1)
    p1, p2, p3 = s1 - g * r1[0], s2 - g * r1[1], s3 - g * r1[2]
    if p1 >= p2 and p2 >= p3:
        return p1, p2, p3, PLANE
    if p1 < p2 and p2 < p3 and sin_phi > 0.0:
        # Past both edge boundaries: that wedge lies inside the apex wedge (module notes).
        apex = cohesion * cos_phi / sin_phi
        return apex, apex, apex, APEX
    compression = p1 < p2
    if compression:  # plane "2": σ2 max, σ3 min; edge σ1 = σ2
        aB = (0.0, 1.0 + sin_phi, -(1.0 - sin_phi))
        bB = (0.0, 1.0 + sin_psi, -(1.0 - sin_psi))
    else:  # plane "6": σ1 max, σ2 min; edge σ2 = σ3
        aB = (1.0 + sin_phi, -(1.0 - sin_phi), 0.0)
        bB = (1.0 + sin_psi, -(1.0 - sin_psi), 0.0)
    e1, e2, e3 = _edge_return(s, a1, r1, f1, aB, bB, k, lam, G)
    if compression:
        pair = 0.5 * (e1 + e2)
        if sin_phi > 0.0 and pair < e3:
            apex = cohesion * cos_phi / sin_phi
            return apex, apex, apex, APEX
        return pair, pair, e3, EDGE_COMPRESSION
    pair = 0.5 * (e2 + e3)
    if sin_phi > 0.0 and e1 < pair:
        apex = cohesion * cos_phi / sin_phi
        return apex, apex, apex, APEX
    return e1, pair, pair, EDGE_EXTENSION


@njit(**_JIT)
def _principal_update(s1, s2, s3, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """Mohr–Coulomb return, then the optional Rankine cap; (n1, n2, n3, code)."""
    n1, n2, n3, code = _mohr_coulomb_return(s1, s2, s3, lam, G, sin_phi, cos_phi, cohesion, sin_psi)
    if tension_cutoff > 0.0:
        cap = tension_cutoff
        if sin_phi > 0.0:
            cap = min(cap, cohesion * cos_phi / sin_phi)
        if n1 > cap:
            n1, n2, n3 = cap, min(n2, cap), min(n3, cap)
            code = TENSION_CAP
    return n1, n2, n3, code


@njit(**_JIT)
def _return_plane_strain(s, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """Return of a stress with σxz = σyz = 0 (σzz principal, in-plane block in closed form)."""
    e0, e1, e2, h, r = _eigvals_2x2(s)
    i1, i2, i3 = _order3(e0, e1, e2)
    n1, n2, n3, code = _principal_update(
        _pick(i1, e0, e1, e2),
        _pick(i2, e0, e1, e2),
        _pick(i3, e0, e1, e2),
        lam,
        G,
        sin_phi,
        cos_phi,
        cohesion,
        sin_psi,
        tension_cutoff,
    )
    if code == ELASTIC:
        return s, code
    u0 = _slot(0, i1, i2, n1, n2, n3)  # new in-plane major
    u1 = _slot(1, i1, i2, n1, n2, n3)  # new in-plane minor
    u2 = _slot(2, i1, i2, n1, n2, n3)  # new σzz
    mean = 0.5 * (u0 + u1)
    half = 0.5 * (u0 - u1)
    if r > 0.0:
        # Same eigenvectors: scale the in-plane deviator by the new radius of Mohr's circle.
        ratio = half / r
        return (mean + ratio * h, mean - ratio * h, u2, ratio * s[3], 0.0, 0.0), code
    return (u0, u1, u2, 0.0, 0.0, 0.0), code


@njit(**_JIT)
def _invariant_bounds(s, sin_phi, cos_phi, cohesion):
    """Upper bounds of f and of σ1 from the mean stress p and J2, without eigenvalues.

    With the deviatoric principal stresses (2/√3) √J2 cos(θ − 2πk/3) one has
    σ1 − σ3 ≤ 2 √J2, σ1 + σ3 = 2p − s2 with |s2| ≤ √(J2/3), and σ1 ≤ p + (2/√3) √J2.
    """
    p = (s[0] + s[1] + s[2]) / 3.0
    d0, d1, d2 = s[0] - p, s[1] - p, s[2] - p
    root = math.sqrt(0.5 * (d0 * d0 + d1 * d1 + d2 * d2) + s[3] * s[3] + s[4] * s[4] + s[5] * s[5])
    f_bound = 2.0 * root + (2.0 * p + root / math.sqrt(3.0)) * sin_phi - 2.0 * cohesion * cos_phi
    return f_bound, p + 2.0 * root / math.sqrt(3.0)


@njit(**_JIT)
def _return_with_eigen(s, eig, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """Return of a symmetric trial stress, given its eigen-decomposition (a 12-tuple)."""
    e0, e1, e2, x0, x1, x2, y0, y1, y2, z0, z1, z2 = eig
    i1, i2, i3 = _order3(e0, e1, e2)
    t1, t2, t3 = _pick(i1, e0, e1, e2), _pick(i2, e0, e1, e2), _pick(i3, e0, e1, e2)
    n1, n2, n3, code = _principal_update(
        t1, t2, t3, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff
    )
    if code == ELASTIC:
        return s, code
    if n1 == n3:  # hydrostatic (apex): exact, and independent of the eigenvectors
        return (n1, n1, n1, 0.0, 0.0, 0.0), code
    d0 = _slot(0, i1, i2, n1 - t1, n2 - t2, n3 - t3)
    d1 = _slot(1, i1, i2, n1 - t1, n2 - t2, n3 - t3)
    d2 = _slot(2, i1, i2, n1 - t1, n2 - t2, n3 - t3)
    return _changed_along(s, d0, d1, d2, eig[3:]), code


@njit(inline="always", **_JIT)
def _changed_along(s, d0, d1, d2, vectors):
    """σ + d0 x xᵀ + d1 y yᵀ + d2 z zᵀ for the eigenvectors (x, y, z) given as 9 numbers."""
    x0, x1, x2, y0, y1, y2, z0, z1, z2 = vectors
    return (
        s[0] + d0 * x0 * x0 + d1 * y0 * y0 + d2 * z0 * z0,
        s[1] + d0 * x1 * x1 + d1 * y1 * y1 + d2 * z1 * z1,
        s[2] + d0 * x2 * x2 + d1 * y2 * y2 + d2 * z2 * z2,
        s[3] + d0 * x0 * x1 + d1 * y0 * y1 + d2 * z0 * z1,
        s[4] + d0 * x0 * x2 + d1 * y0 * y2 + d2 * z0 * z2,
        s[5] + d0 * x1 * x2 + d1 * y1 * y2 + d2 * z1 * z2,
    )


@njit(**_JIT)
def _return_general(s, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """Return of a general symmetric stress through its eigen-decomposition."""
    # Most of a resting bed is clearly elastic: skip the eigen-decomposition there.
    f_bound, s1_bound = _invariant_bounds(s, sin_phi, cos_phi, cohesion)
    if f_bound <= 0.0 and (tension_cutoff <= 0.0 or s1_bound <= tension_cutoff):
        return s, ELASTIC
    return _return_with_eigen(
        s, _eigh3(s), lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff
    )


# --------------------------------------------------------------------------------------
# Rate-dependent friction: the mu(I) rheology as a friction angle for the return
# --------------------------------------------------------------------------------------
# A rate-independent Mohr-Coulomb continuum has no length of its own: a flowing layer
# thins with the grid that resolves it (the surface speed of a rolling drum does not
# converge over cells, measured). The mu(I) rheology (GDR MiDi 2004; Jop, Forterre and
# Pouliquen 2006) brings the grain size in: the friction coefficient rises with the
# inertial number I = |gamma_dot| d / sqrt(p / rho_s) from mu_s = tan(phi) towards
# mu_2 = mu_s + rise, mu(I) = mu_s + rise I / (I0 + I). The return then uses the friction
# angle atan(mu(I)) of the particle's strain rate this step and pressure before it (an
# explicit rate: the elastic trial bounds the correction, so the elastic time step stays
# the only limit). |gamma_dot| = sqrt(2 D':D'), the deviatoric rate, which is the shear
# rate in simple shear; at zero or tensile pressure I is infinite and mu = mu_2.


@njit(**_JIT)
def rate_friction(l, s, sin_phi, cos_phi, rise, i0, inertial_scale):
    """(sin, cos) of the μ(I) friction angle for a velocity gradient and a stress.

    ``l`` the velocity gradient 9-tuple, ``s`` the stress 6-tuple (tension positive),
    ``sin_phi, cos_phi`` the quasi-static angle (μs = tan φ), ``rise`` = μ2 − μs (0: the
    rate-independent model, returned unchanged), ``i0`` the inertial number scale I0,
    ``inertial_scale`` = d sqrt(ρs) (grain diameter times the root of the grain
    density), so that I = |γ̇| inertial_scale / sqrt(p).
    """
    if not rise > 0.0:
        return sin_phi, cos_phi
    third = (l[0] + l[4] + l[8]) / 3.0
    a, b, c = l[0] - third, l[4] - third, l[8] - third
    d01 = 0.5 * (l[1] + l[3])
    d02 = 0.5 * (l[2] + l[6])
    d12 = 0.5 * (l[5] + l[7])
    rate = math.sqrt(2.0 * (a * a + b * b + c * c + 2.0 * (d01 * d01 + d02 * d02 + d12 * d12)))
    pressure = -(s[0] + s[1] + s[2]) / 3.0
    mu = sin_phi / cos_phi
    if pressure > 0.0:
        inertial = rate * inertial_scale / math.sqrt(pressure)
        mu += rise * inertial / (i0 + inertial)
    else:
        mu += rise
    norm = math.sqrt(1.0 + mu * mu)
    return mu / norm, 1.0 / norm


# --------------------------------------------------------------------------------------
# Batched eigen-decomposition: the steps of _eigh3 as four loops over a block of trial
# stresses in structure-of-arrays layout. Each loop body is a branch-free step, so LLVM
# turns the loop into SIMD code (AVX2 / AVX-512: 4 or 8 matrices an instruction) and the
# long chain of divisions and square roots of one decomposition overlaps with the
# others': a decomposition takes about a tenth of the scalar _eigh3's time. No
# rescaling: return_batch sends matrices outside SAFE_RANGE to _eigh3.
# --------------------------------------------------------------------------------------

#: Particles per block of the batched stress update (the 3-D G2P's; the fastest of 64,
#: 128 and 256, docs/flow.md). Blocks of this width take the SIMD loop of
#: :func:`return_batch`'s returns; other widths the same steps unvectorised.
BATCH_BLOCK = 128

#: Rows of each work array of :func:`batch_work`: trials, far eigenvalue, its vector,
#: plane pair, eigenvalues and rotation, gradients (then eigenvectors), returns.
BATCH_ROWS = (7, 1, 3, 6, 5, 9, 7)  # the trials' 7th row: each particle's sin(phi)


def batch_work(threads, block):
    """Work arrays of the batched stress update (:func:`trial_batch`, :func:`eigh3_batch`,
    :func:`return_batch`) for ``threads`` chunks of ``block`` particles.

    Returns a tuple of seven float64 arrays of shape (threads, rows, block): the trial
    stresses (6 rows: xx, yy, zz, xy, xz, yz, then a 7th for the particle's sin φ under
    a rate-dependent friction, :func:`rate_friction`), the far eigenvalue, its eigenvector, the
    orthonormal pair spanning the plane orthogonal to it, the eigenvalues with the
    2×2 rotation (far, larger, smaller, c, s), the velocity gradients (9 rows, row by
    row) from which :func:`trial_batch` forms the trials (then the eigenvectors that
    :func:`return_batch` assembles there), and the returned stresses (6 rows, then their
    codes) of :func:`return_batch`.
    """
    return tuple(np.zeros((threads, rows, block)) for rows in BATCH_ROWS)


@njit(**_JIT)
def _batch_far_root(a, alpha, n):
    for i in range(n):
        alpha[0, i] = _far_root(a[0, i], a[1, i], a[2, i], a[3, i], a[4, i], a[5, i])


@njit(**_JIT)
def _batch_far_vector(a, alpha, e, n):
    for i in range(n):
        e[0, i], e[1, i], e[2, i] = _far_eigenvector(
            a[0, i], a[1, i], a[2, i], a[3, i], a[4, i], a[5, i], alpha[0, i]
        )


@njit(**_JIT)
def _batch_plane(e, uw, n):
    for i in range(n):
        uw[0, i], uw[1, i], uw[2, i], uw[3, i], uw[4, i], uw[5, i] = _plane_basis(
            e[0, i], e[1, i], e[2, i]
        )


@njit(**_JIT)
def _batch_pair(a, e, uw, out, n):
    for i in range(n):
        out[0, i], out[1, i], out[2, i], out[3, i], out[4, i] = _pair_rotation(
            a[0, i], a[1, i], a[2, i], a[3, i], a[4, i], a[5, i],
            e[0, i], e[1, i], e[2, i],
            uw[0, i], uw[1, i], uw[2, i], uw[3, i], uw[4, i], uw[5, i],
        )  # fmt: skip


@njit(**_JIT)
def eigh3_batch(trial, alpha, e, uw, out, n):
    """Eigen-decompositions of the first ``n`` trial stresses of a block (SIMD loops).

    ``trial`` (6, B) holds the stresses as rows xx, yy, zz, xy, xz, yz; the other arrays
    are work space and results (see :func:`batch_work`, one thread's slice each). After
    the call, eigenvalue k of particle i is ``out[k, i]`` for k = 0, 1, 2 with the
    vectors ``e[:, i]``, ``c u + s w`` and ``c w - s u`` (``c, s = out[3:5, i]``,
    ``u, w = uw[:3, i], uw[3:, i]``); :func:`return_batch` reads them. The same steps
    as :func:`_eigh3`, for matrices inside :data:`SAFE_RANGE`.
    """
    _batch_far_root(trial, alpha, n)
    _batch_far_vector(trial, alpha, e, n)
    _batch_plane(e, uw, n)
    _batch_pair(trial, e, uw, out, n)


@njit(**_JIT)
def _batch_close_gaps(grad, gap, lo, n, dt):
    for i in range(n):
        l = (
            grad[0, i], grad[1, i], grad[2, i], grad[3, i], grad[4, i], grad[5, i],
            grad[6, i], grad[7, i], grad[8, i],
        )  # fmt: skip
        l, gap[lo + i] = close_gap(l, dt, gap[lo + i])
        grad[0, i], grad[4, i], grad[8, i] = l[0], l[4], l[8]


@njit(**_JIT)
def _batch_trial(old, grad, trial, n, dt, lam, G):
    for i in range(n):
        l = (
            grad[0, i], grad[1, i], grad[2, i], grad[3, i], grad[4, i], grad[5, i],
            grad[6, i], grad[7, i], grad[8, i],
        )  # fmt: skip
        s = (old[0, i], old[1, i], old[2, i], old[3, i], old[4, i], old[5, i])
        t = _elastic_increment(_rotate(_spin_rotation(l, dt), s), l, dt, lam, G)
        trial[0, i], trial[1, i], trial[2, i] = t[0], t[1], t[2]
        trial[3, i], trial[4, i], trial[5, i] = t[3], t[4], t[5]


@njit(**_JIT)
def trial_batch(old, grad, trial, gap, lo, n, dt, lam, G, contact):
    """Elastic trials of a block (a SIMD loop, as :func:`eigh3_batch`).

    ``old`` (6, B) holds the stresses of particles ``lo`` .. ``lo + n - 1`` and ``grad``
    (9, B) their velocity gradients row by row; rows 0..5 of ``trial`` receive
    :func:`trial_stress` of each, the same values. With ``contact`` a compression first
    closes the particle's gap ``gap[lo + i]`` (:func:`close_gap`; ``grad`` is changed as
    the trial sees it). Inputs and outputs are different arrays, so that LLVM can
    vectorise the loop (in place, it cannot tell the rows apart).
    """
    if contact:
        _batch_close_gaps(grad, gap, lo, n, dt)
    _batch_trial(old, grad, trial, n, dt, lam, G)


@njit(**_JIT)
def read_stress(stress, p):
    """Particle p's symmetric stress from an (N, 3, 3) array as a 6-tuple."""
    return _read(stress[p])


@njit(**_JIT)
def write_stress(stress, p, s):
    """Store the 6-tuple ``s`` as particle p's symmetric stress in an (N, 3, 3) array."""
    _write(stress[p], s)


@njit(**_JIT)
def _batch_vectors(e, uw, out, vec, n):
    for i in range(n):
        (vec[0, i], vec[1, i], vec[2, i], vec[3, i], vec[4, i], vec[5, i], vec[6, i], vec[7, i],
         vec[8, i]) = _vectors(
            e[0, i], e[1, i], e[2, i], uw[0, i], uw[1, i], uw[2, i],
            uw[3, i], uw[4, i], uw[5, i], out[3, i], out[4, i],
        )  # fmt: skip


@njit(inline="always", **_JIT)
def _block_returns(trial, vec, out, ret, width, n, lam, G, sin_phi, cos_phi, cohesion, sin_psi,
                   tension_cutoff, rate_dependent):  # fmt: skip
    """The Mohr–Coulomb returns of a block, without a branch (a SIMD loop).

    The steps and values of :func:`_return_with_eigen` (through
    :func:`_mohr_coulomb_return`: elastic, main plane, either edge, apex), every outcome
    computed and the scalar path's one selected: row 0..5 of ``ret`` receive the stress
    and row 6 the code. A trial that meets the tension cap or lies outside
    :data:`SAFE_RANGE` gets code -1 and is returned by the scalar path. The sort of
    :func:`_order3` is written out, as selects, for eigenvalues (far, larger, smaller)
    with larger >= smaller, as :func:`eigh3_batch` gives them (checked here too).

    The work arrays come flat, row r of each at ``r * width``: with ``width`` a constant
    where the function is inlined, LLVM sees that the rows of an array do not overlap
    and vectorises the loop (with the rows' stride known only at run time it cannot
    tell them apart and gives up).
    """
    r1 = _elastic_direction((1.0 + sin_psi, 0.0, -(1.0 - sin_psi)), lam, G)
    for i in range(n):
        sp = trial[6 * width + i] if rate_dependent else sin_phi
        cp = math.sqrt(1.0 - sp * sp) if rate_dependent else cos_phi
        s = (
            trial[i], trial[width + i], trial[2 * width + i], trial[3 * width + i],
            trial[4 * width + i], trial[5 * width + i],
        )  # fmt: skip
        size = max(abs(s[0]), abs(s[1]), abs(s[2]), abs(s[3]), abs(s[4]), abs(s[5]))
        x0, x1, x2 = vec[i], vec[width + i], vec[2 * width + i]
        y0, y1, y2 = vec[3 * width + i], vec[4 * width + i], vec[5 * width + i]
        z0, z1, z2 = vec[6 * width + i], vec[7 * width + i], vec[8 * width + i]
        e0, e1, e2 = out[i], out[width + i], out[2 * width + i]
        # _order3 on (far, larger, smaller): the far one first, second or last
        far_first = e0 >= e1
        far_last = (not far_first) & (e2 > e0)
        t = (
            e0 if far_first else e1,
            e1 if far_first else (e2 if far_last else e0),
            e0 if far_last else e2,
        )
        # _mohr_coulomb_return, every branch
        k = 2.0 * cohesion * cp
        a1 = (1.0 + sp, 0.0, -(1.0 - sp))
        f1 = _dot(a1, t) - k
        elastic = f1 <= 0.0
        g = f1 / _dot(a1, r1)
        p1, p2, p3 = t[0] - g * r1[0], t[1] - g * r1[1], t[2] - g * r1[2]
        plane = (p1 >= p2) & (p2 >= p3)
        both = (p1 < p2) & (p2 < p3) & (sp > 0.0)
        apex = cohesion * cp / sp
        compression = p1 < p2
        a_b = (
            0.0 if compression else 1.0 + sp,
            1.0 + sp if compression else -(1.0 - sp),
            -(1.0 - sp) if compression else 0.0,
        )
        b_b = (
            0.0 if compression else 1.0 + sin_psi,
            1.0 + sin_psi if compression else -(1.0 - sin_psi),
            -(1.0 - sin_psi) if compression else 0.0,
        )
        q1, q2, q3 = _edge_return(t, a1, r1, f1, a_b, b_b, k, lam, G)
        pair_c = 0.5 * (q1 + q2)
        pair_x = 0.5 * (q2 + q3)
        apex_c = (sp > 0.0) & (pair_c < q3)
        apex_x = (sp > 0.0) & (q1 < pair_x)
        to_apex = both | (apex_c if compression else apex_x)
        on_edge = not (elastic | plane | to_apex)
        n1 = p1 if plane else (apex if to_apex else (pair_c if compression else q1))
        n2 = p2 if plane else (apex if to_apex else (pair_c if compression else pair_x))
        n3 = p3 if plane else (apex if to_apex else (q3 if compression else pair_x))
        n1, n2, n3 = (t[0] if elastic else n1), (t[1] if elastic else n2), (t[2] if elastic else n3)
        edge = float(EDGE_COMPRESSION) if compression else float(EDGE_EXTENSION)
        code = float(ELASTIC) if elastic else (float(PLANE) if plane else float(APEX))
        code = edge if on_edge else code
        # _principal_update's tension cap: left to the scalar path
        cap = (apex if apex < tension_cutoff else tension_cutoff) if sp > 0.0 else tension_cutoff
        capped = (tension_cutoff > 0.0) & (n1 > cap)
        in_range = (SAFE_RANGE[0] <= size) & (size <= SAFE_RANGE[1]) & (e1 >= e2)
        fast = (not capped) & in_range
        # _return_with_eigen: unchanged, hydrostatic, or the trial plus the change along
        # each eigenvector
        hydrostatic = (not elastic) & (n1 == n3)
        d1, d2, d3 = n1 - t[0], n2 - t[1], n3 - t[2]
        dx = d1 if far_first else (d3 if far_last else d2)  # the far eigenvector's
        dy = d2 if far_first else d1  # the larger one's
        dz = d2 if far_last else d3  # the smaller one's
        new = _changed_along(s, dx, dy, dz, (x0, x1, x2, y0, y1, y2, z0, z1, z2))
        for r in range(6):
            iso = n1 if r < 3 else 0.0
            ret[r * width + i] = s[r] if elastic else (iso if hydrostatic else new[r])
        ret[6 * width + i] = code if fast else -1.0


@njit(**_JIT)
def return_batch(lo, n, trial, e, uw, out, vec, ret, stress, codes, gap, contact, lam, G, sin_phi,
                 cos_phi, cohesion, sin_psi, tension_cutoff, rate_dependent=False):  # fmt: skip
    """Mohr–Coulomb return of the block decomposed by :func:`eigh3_batch`.

    Particle ``lo + i`` of ``stress`` (N, 3, 3) receives the returned trial ``i``,
    ``codes`` its return code and, if ``contact``, ``gap`` (N) what an apex or cap return
    adds to it (:func:`open_gap`). The work array ``vec`` (9, B) receives the eigenvectors
    (x, y, z components of the far, larger and smaller one's). The returns are computed
    for the whole block at once (:func:`_block_returns`, into the work array ``ret``
    (7, B)), and those at the tension cap one by one. Trials outside :data:`SAFE_RANGE` are
    decomposed again by the scalar, rescaling :func:`_eigh3`. With ``rate_dependent``
    each particle's sin φ is ``trial[6, i]`` (:func:`rate_friction`) instead of
    ``sin_phi``.
    """
    _batch_vectors(e, uw, out, vec, n)
    flat_trial, flat_vec = trial.reshape(-1), vec.reshape(-1)
    flat_out, flat_ret = out.reshape(-1), ret.reshape(-1)
    if trial.shape[1] == BATCH_BLOCK:  # a constant width: the SIMD loop
        _block_returns(
            flat_trial, flat_vec, flat_out, flat_ret, BATCH_BLOCK, n, lam, G, sin_phi,
            cos_phi, cohesion, sin_psi, tension_cutoff, rate_dependent,
        )  # fmt: skip
    else:
        _block_returns(
            flat_trial, flat_vec, flat_out, flat_ret, trial.shape[1], n, lam, G, sin_phi,
            cos_phi, cohesion, sin_psi, tension_cutoff, rate_dependent,
        )  # fmt: skip
    for i in range(n):
        s = (trial[0, i], trial[1, i], trial[2, i], trial[3, i], trial[4, i], trial[5, i])
        if ret[6, i] >= 0.0:
            new = (ret[0, i], ret[1, i], ret[2, i], ret[3, i], ret[4, i], ret[5, i])
            code = np.int8(ret[6, i])
        else:
            sp, cp = sin_phi, cos_phi
            if rate_dependent:
                sp = trial[6, i]
                cp = math.sqrt(1.0 - sp * sp)
            size = max(abs(s[0]), abs(s[1]), abs(s[2]), abs(s[3]), abs(s[4]), abs(s[5]))
            if SAFE_RANGE[0] <= size <= SAFE_RANGE[1]:
                eig = (
                    out[0, i], out[1, i], out[2, i], vec[0, i], vec[1, i], vec[2, i],
                    vec[3, i], vec[4, i], vec[5, i], vec[6, i], vec[7, i], vec[8, i],
                )  # fmt: skip
            else:
                eig = _eigh3(s)
            new, code = _return_with_eigen(
                s, eig, lam, G, sp, cp, cohesion, sin_psi, tension_cutoff
            )
        write_stress(stress, lo + i, new)
        codes[lo + i] = code
        if contact:
            gap[lo + i] = open_gap(
                gap[lo + i], code, s[0] + s[1] + s[2], new[0] + new[1] + new[2],
                lam + 2.0 * G / 3.0,
            )  # fmt: skip


# --------------------------------------------------------------------------------------
# Lost contact: the volume a granular material gains at the apex or the tension cap
# --------------------------------------------------------------------------------------
# At the apex (and at the tension cap) a volumetric extension is plastic: the trial's
# extra mean stress is returned, the volume gained is kept. Compressing again would be
# elastic from there on, and the pressure it builds would hold the material at the
# larger volume: the volume ratchets up with every extension (measured: +8 % a
# revolution of a Tote bed, +40 % in five). A cohesionless granular material gains that
# volume by losing contacts, and gives it back without stress when the grains close up
# again. ``gap`` is that volume per unit volume (the volumetric plastic strain taken at
# the apex or cap, >= 0): close_gap lets a compression first close the gap, stress-free,
# and only the rest of it build pressure; open_gap adds what a step's apex or cap
# return took. Shear, rotation and the dense material's elasticity are unchanged, and a
# particle that never reaches the apex never has a gap.


@njit(**_JIT)
def close_gap(l, dt, gap):
    """Velocity gradient for the elastic trial, and the gap left, after a compression.

    ``l`` is the velocity gradient 9-tuple, ``dt`` the step, ``gap`` >= 0. A volumetric
    compression ``dt tr(L) < 0`` first closes the gap: ``closed = min(gap, -dt tr L)``;
    the trial then sees ``L + closed / (3 dt) I`` (the deviatoric part and the spin as
    they were). Returns ``(l, gap - closed)``.
    """
    squeeze = -dt * (l[0] + l[4] + l[8])
    if not (gap > 0.0 and squeeze > 0.0):
        return l, gap
    closed = min(gap, squeeze)
    d = closed / (3.0 * dt)
    return (l[0] + d, l[1], l[2], l[3], l[4] + d, l[5], l[6], l[7], l[8] + d), gap - closed


@njit(**_JIT)
def open_gap(gap, code, trial_trace, new_trace, K):
    """Gap after a step's return: plus the volumetric plastic strain of an apex or cap
    return, ``(tr σ_trial − tr σ_new) / (3K)`` (the trace of C:Δε_p is 3K tr Δε_p)."""
    if code == APEX or code == TENSION_CAP:
        return gap + max(0.0, (trial_trace - new_trace) / (3.0 * K))
    return gap


# --------------------------------------------------------------------------------------
# Public kernels
# --------------------------------------------------------------------------------------


@njit(**_JIT)
def trial_stress(s, l, dt, lam, G, gap, contact):
    """Elastic trial: Jaumann (Hughes–Winget) rotation, then the hypoelastic increment.

    ``s`` the stress 6-tuple (xx, yy, zz, xy, xz, yz), ``l`` the velocity gradient
    9-tuple row by row, ``lam`` and ``G`` Lamé's constants. With ``contact`` a
    compression first closes the particle's ``gap`` (:func:`close_gap`). Returns the
    trial 6-tuple and the gap left.
    """
    if contact:
        l, gap = close_gap(l, dt, gap)
    return _elastic_increment(_rotate(_spin_rotation(l, dt), s), l, dt, lam, G), gap


@njit(**_JIT)
def stress_step(s, l, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff, gap,
                contact):  # fmt: skip
    """One step of the stress update on scalars, for kernels that hold L in registers.

    As :func:`update_stress`, with the symmetric stress as the 6-tuple
    (σxx, σyy, σzz, σxy, σxz, σyz) and the velocity gradient as the 9-tuple
    (L00, L01, L02, L10, ..., L22); with ``contact``, the particle's ``gap`` closes and
    opens (:func:`close_gap`, :func:`open_gap`). Returns ``(new stress, code, gap)``.
    """
    lam = K - 2.0 * G / 3.0
    trial, gap = trial_stress(s, l, dt, lam, G, gap, contact)
    if trial[4] == 0.0 and trial[5] == 0.0:
        new, code = _return_plane_strain(
            trial, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff
        )
    else:
        new, code = _return_general(
            trial, lam, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff
        )
    if contact:
        gap = open_gap(gap, code, trial[0] + trial[1] + trial[2], new[0] + new[1] + new[2], K)
    return new, code, gap


@njit(**_JIT)
def update_stress(sig, L, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """Advance one particle's stress by one step, in place; see the module notes.

    Jaumann (Hughes–Winget) rotation, elastic trial, Mohr–Coulomb return in principal
    stresses, optional tension cap. Allocation-free.

    Parameters
    ----------
    sig : ndarray, shape (3, 3), float64
        Symmetric Cauchy stress, Pa, tension positive; overwritten.
    L : ndarray, shape (3, 3), float64
        Velocity gradient ``L[i, j] = dv_i/dx_j``, 1/s (z row and column zero in 2-D).
    dt : float
        Time step, s.
    K, G : float
        Bulk and shear moduli, Pa.
    sin_phi, cos_phi : float
        Sine and cosine of the friction angle φ (φ = 0 is Tresca).
    cohesion : float
        Cohesion c, Pa.
    sin_psi : float
        Sine of the dilatancy angle ψ (the plastic potential's friction angle).
    tension_cutoff : float
        If > 0, principal stresses are capped at min(tension_cutoff, c cot φ), Pa.

    Returns
    -------
    int
        :data:`ELASTIC` (0), :data:`PLANE` (1), :data:`EDGE_COMPRESSION` (2, σ1 = σ2),
        :data:`EDGE_EXTENSION` (3, σ2 = σ3), :data:`APEX` (4) or :data:`TENSION_CAP` (5).
    """
    l = (L[0, 0], L[0, 1], L[0, 2], L[1, 0], L[1, 1], L[1, 2], L[2, 0], L[2, 1], L[2, 2])
    s, code, _ = stress_step(
        _read(sig), l, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff, 0.0, False
    )
    _write(sig, s)
    return code


@njit(parallel=True, **_JIT)
def update_stresses(
    stress, L, active, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff, codes
):
    """Advance every active particle's stress by one step, in place (parallel over particles).

    Parameters
    ----------
    stress : ndarray, shape (N, 3, 3), float64
        Symmetric stresses, Pa, tension positive; overwritten for active particles.
    L : ndarray, shape (N, 3, 3), float64
        Velocity gradients ``L[p, i, j] = dv_i/dx_j``, 1/s.
    active : ndarray, shape (N,), uint8 or bool
        Particles to update; the others keep their stress.
    dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff : float
        As in :func:`update_stress`.
    codes : ndarray, shape (N,), int8
        Receives the return code of each particle, :data:`INACTIVE` (−1) where skipped.
    """
    for p in prange(stress.shape[0]):
        if active[p]:
            codes[p] = update_stress(
                stress[p],
                L[p],
                dt,
                K,
                G,
                sin_phi,
                cos_phi,
                cohesion,
                sin_psi,
                tension_cutoff,
            )
        else:
            codes[p] = INACTIVE
