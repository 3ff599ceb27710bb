"""Plain NumPy twin of :mod:`blendxr.flow.mohr_coulomb`, for tests only.

The same stress update written for reading rather than speed: the spin rotation by solving
(I − dt W/2) Q = I + dt W/2, the principal axes from ``np.linalg.eigh`` for every stress
(no plane-strain shortcut), and the return with explicit vectors and a linear solve. See
the numba module's notes for the conventions and the choice of return region.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "elastic_trial",
    "jaumann_rotation",
    "principal_return",
    "update_stress",
    "update_stresses",
    "yield_value",
]

ELASTIC, PLANE, EDGE_COMPRESSION, EDGE_EXTENSION, APEX, TENSION_CAP = 0, 1, 2, 3, 4, 5


def jaumann_rotation(sig, L, dt):
    """Q σ Qᵀ with the Hughes–Winget rotation Q = (I − dt W/2)⁻¹ (I + dt W/2)."""
    W = 0.5 * (L - L.T)
    eye = np.eye(3)
    Q = np.linalg.solve(eye - 0.5 * dt * W, eye + 0.5 * dt * W)
    return Q @ sig @ Q.T


def elastic_trial(sig, L, dt, K, G):
    """Jaumann rotation followed by the hypoelastic increment dt (λ tr(D) I + 2 G D)."""
    lam = K - 2.0 * G / 3.0
    D = 0.5 * (L + L.T)
    return jaumann_rotation(sig, L, dt) + dt * (lam * np.trace(D) * np.eye(3) + 2.0 * G * D)


def _plane(i, j, sine):
    """Gradient of (1 + sin) σ_i − (1 − sin) σ_j: plane i max, j min."""
    v = np.zeros(3)
    v[i] = 1.0 + sine
    v[j] = -(1.0 - sine)
    return v


def principal_return(principal, K, G, sin_phi, cos_phi, cohesion, sin_psi):
    """Mohr–Coulomb return of sorted principal stresses σ1 ≥ σ2 ≥ σ3.

    Returns
    -------
    new : ndarray, shape (3,)
        Returned principal stresses, still sorted.
    code : int
        0 elastic, 1 plane, 2 compression edge, 3 extension edge, 4 apex.
    """
    s = np.asarray(principal, dtype=float)
    lam = K - 2.0 * G / 3.0
    C = lam * np.ones((3, 3)) + 2.0 * G * np.eye(3)
    k = 2.0 * cohesion * cos_phi

    a1, r1 = _plane(0, 2, sin_phi), C @ _plane(0, 2, sin_psi)
    f1 = a1 @ s - k
    if f1 <= 0.0:
        return s.copy(), ELASTIC

    p = s - f1 / (a1 @ r1) * r1
    if p[0] >= p[1] >= p[2]:
        return p, PLANE

    apex = cohesion * cos_phi / sin_phi if sin_phi > 0.0 else np.inf
    if p[0] < p[1] and p[1] < p[2] and sin_phi > 0.0:  # beyond both edges
        return np.full(3, apex), APEX
    compression = p[0] < p[1]

    if compression:
        aB, rB = _plane(1, 2, sin_phi), C @ _plane(1, 2, sin_psi)
    else:
        aB, rB = _plane(0, 1, sin_phi), C @ _plane(0, 1, sin_psi)
    matrix = np.array([[a1 @ r1, a1 @ rB], [aB @ r1, aB @ rB]])
    x, y = np.linalg.solve(matrix, [f1, aB @ s - k])
    e = s - x * r1 - y * rB

    if compression:
        pair = 0.5 * (e[0] + e[1])
        if pair < e[2]:
            return np.full(3, apex), APEX
        return np.array([pair, pair, e[2]]), EDGE_COMPRESSION
    pair = 0.5 * (e[1] + e[2])
    if e[0] < pair:
        return np.full(3, apex), APEX
    return np.array([e[0], pair, pair]), EDGE_EXTENSION


def update_stress(sig, L, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff):
    """One stress update; returns (new stress, code) and leaves ``sig`` alone."""
    trial = elastic_trial(np.asarray(sig, float), np.asarray(L, float), dt, K, G)
    values, vectors = np.linalg.eigh(trial)
    values, vectors = values[::-1], vectors[:, ::-1]  # σ1 ≥ σ2 ≥ σ3
    new, code = principal_return(values, K, G, sin_phi, cos_phi, cohesion, sin_psi)

    if tension_cutoff > 0.0:
        cap = tension_cutoff
        if sin_phi > 0.0:
            cap = min(cap, cohesion * cos_phi / sin_phi)
        if new[0] > cap:
            new = np.minimum(new, cap)
            code = TENSION_CAP

    if code == ELASTIC:
        return trial, code
    if new[0] == new[2]:
        return new[0] * np.eye(3), code
    return vectors @ np.diag(new) @ vectors.T, code


def update_stresses(stress, L, active, dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tc):
    """Loop of :func:`update_stress`; returns (new stresses, codes with −1 where inactive)."""
    new = np.array(stress, dtype=float)
    codes = np.full(len(new), -1, dtype=np.int8)
    for p in np.flatnonzero(active):
        new[p], codes[p] = update_stress(
            stress[p], L[p], dt, K, G, sin_phi, cos_phi, cohesion, sin_psi, tc
        )
    return new, codes


def yield_value(sig, sin_phi, cos_phi, cohesion):
    """f = (σ1 − σ3) + (σ1 + σ3) sin φ − 2 c cos φ of a 3×3 stress."""
    values = np.linalg.eigvalsh(sig)
    s1, s3 = values[-1], values[0]
    return (s1 - s3) + (s1 + s3) * sin_phi - 2.0 * cohesion * cos_phi
