"""Stable time-step limits of the ADE schemes (pure NumPy).

All functions take per-axis tuples: ``velocities`` and ``diffusivities`` hold 2 or 3 arrays
of one grid shape (axis order x, y(, z)), ``spacing`` the matching cell sizes in metres.
"""

import math

import numpy as np

__all__ = ["diffusion_substeps", "finite_volume_max_dt", "lax_wendroff_max_dt"]


def _check(arrays, spacing, name):
    arrays = tuple(np.asarray(a, dtype=np.float64) for a in arrays)
    if len(arrays) not in (2, 3) or len(arrays) != len(spacing):
        raise ValueError(f"{name}: need 2 or 3 arrays and as many spacings")
    shape = arrays[0].shape
    if any(a.shape != shape for a in arrays) or len(shape) != len(arrays):
        raise ValueError(f"{name}: arrays must share one {len(arrays)}-D shape")
    return arrays


def _central_difference(a, axis, h):
    """Central difference along ``axis`` in the interior, zero on the outermost layer."""
    out = np.zeros_like(a)
    if a.shape[axis] < 3:
        return out
    inner = [slice(None)] * a.ndim
    plus = [slice(None)] * a.ndim
    minus = [slice(None)] * a.ndim
    inner[axis] = slice(1, -1)
    plus[axis] = slice(2, None)
    minus[axis] = slice(None, -2)
    out[tuple(inner)] = (a[tuple(plus)] - a[tuple(minus)]) / (2.0 * h)
    return out


def lax_wendroff_max_dt(velocities, diffusivities, spacing, material):
    """Largest stable time step of the Lax-Wendroff scheme (eq. (6)).

    With ``nu_k = (v_k - dD_kk/dx_k) dt / h_k`` (the effective advection velocity of
    eq. (4), ``dD/dx`` by central differences as in the kernel) and
    ``mu_k = D_kk dt / h_k**2``, von Neumann analysis of the scheme with its cross terms
    gives, per cell, the two conditions

    * ``sum_k |nu_k|**(2/3) <= 1``, i.e. ``dt <= (sum_k |a_k / h_k|**(2/3))**(-3/2)``;
    * ``(sum_k |nu_k|)**2 + 2 sum_k mu_k <= 1``, a quadratic in dt:
      ``A**2 dt**2 + B dt <= 1`` with ``A = sum_k |a_k| / h_k``,
      ``B = 2 sum_k D_kk / h_k**2``, so ``dt <= 2 / (B + sqrt(B**2 + 4 A**2))``.

    The first is the advective limit (for one axis it reduces to ``|nu| <= 1``), the second
    combines advection and diffusion (pure diffusion: ``sum_k mu_k <= 1/2``). The same
    conditions hold in 2-D with two axes.

    Parameters
    ----------
    velocities : tuple of ndarray
        (vx, vy) or (vx, vy, vz) in m/s.
    diffusivities : tuple of ndarray
        (D_xx, D_yy) or (D_xx, D_yy, D_zz) in m^2/s.
    spacing : tuple of float
        Cell sizes (m) per axis.
    material : ndarray
        Nonzero where the cell holds material; only these cells constrain dt.

    Returns
    -------
    float
        The limit in seconds, the minimum over material cells; ``inf`` without motion and
        diffusion.
    """
    vel = _check(velocities, spacing, "velocities")
    dif = _check(diffusivities, spacing, "diffusivities")
    mask = np.asarray(material) != 0
    if not mask.any():
        return math.inf
    adv_23 = np.zeros(int(mask.sum()))
    adv_1 = np.zeros_like(adv_23)
    dif_2 = np.zeros_like(adv_23)
    for axis, h in enumerate(spacing):
        h = float(h)
        a = np.abs(vel[axis] - _central_difference(dif[axis], axis, h))[mask] / h
        adv_23 += a ** (2.0 / 3.0)
        adv_1 += a
        dif_2 += 2.0 * dif[axis][mask] / (h * h)
    with np.errstate(divide="ignore"):
        dt_adv = np.where(adv_23 > 0.0, adv_23 ** (-1.5), np.inf)
        denom = dif_2 + np.sqrt(dif_2 * dif_2 + 4.0 * adv_1 * adv_1)
        dt_mix = np.where(denom > 0.0, 2.0 / denom, np.inf)
    return float(min(dt_adv.min(), dt_mix.min()))


def finite_volume_max_dt(velocities, spacing, vessel):
    """Largest time step of the finite-volume advection (per-face Courant <= 1/2).

    The face velocity is the mean of the two adjacent cell velocities (faces with a cell
    outside the vessel carry nothing). The scheme needs ``|u_f| dt / h <= 1/2`` on every
    face: then a cell loses at most what it holds during a 1-D sweep even when both of its
    faces take material away (non-divergence-free flow), which keeps the donor-cell
    solution, and with it the limited one, positive and bounded. At exactly the limit a
    cell may empty completely, where ``c = q / m`` is ill-conditioned: apply a safety
    factor below 1.

    Parameters
    ----------
    velocities : tuple of ndarray
        (vx, vy) or (vx, vy, vz) in m/s, cell-centred.
    spacing : tuple of float
        Cell sizes (m) per axis.
    vessel : ndarray
        Nonzero inside the vessel.

    Returns
    -------
    float
        The limit in seconds; ``inf`` when nothing moves.
    """
    vel = _check(velocities, spacing, "velocities")
    inside = np.asarray(vessel) != 0
    rate = 0.0
    for axis, h in enumerate(spacing):
        n = vel[axis].shape[axis]
        lo = [slice(None)] * len(spacing)
        hi = [slice(None)] * len(spacing)
        lo[axis] = slice(0, n - 1)
        hi[axis] = slice(1, n)
        lo, hi = tuple(lo), tuple(hi)
        open_face = inside[lo] & inside[hi]
        if not open_face.any():
            continue
        u_face = 0.5 * (vel[axis][lo] + vel[axis][hi])
        rate = max(rate, float(np.abs(u_face[open_face]).max()) / float(h))
    return math.inf if rate == 0.0 else 0.5 / rate


def diffusion_substeps(diffusivities, spacing, dt):
    """Number of explicit diffusion sub-steps per finite-volume sweep.

    Each sweep diffuses along one axis with the flux ``-D_f m_f (c_R - c_L) / h``
    (``D_f`` the face mean, ``m_f = min(m_L, m_R) <= m`` of either cell), so the 1-D
    explicit limit ``D dt_sub / h**2 <= 1/2`` needs no reduction for ``m_f / m``:
    ``dt_diff = min_k h_k**2 / (2 max D_kk)``.

    Parameters
    ----------
    diffusivities : tuple of ndarray
        (D_xx, D_yy) or (D_xx, D_yy, D_zz) in m^2/s.
    spacing : tuple of float
        Cell sizes (m) per axis.
    dt : float
        Step of the finite-volume scheme (s).

    Returns
    -------
    int
        0 when every diffusivity is zero, else ``ceil(dt / dt_diff)`` (at least 1).
    """
    dif = _check(diffusivities, spacing, "diffusivities")
    dt_diff = math.inf
    for axis, h in enumerate(spacing):
        dmax = float(np.max(dif[axis])) if dif[axis].size else 0.0
        if dmax > 0.0:
            dt_diff = min(dt_diff, 0.5 * float(h) ** 2 / dmax)
    if math.isinf(dt_diff):
        return 0
    return max(1, math.ceil(float(dt) / dt_diff))


def unsplit_diffusion_substeps(dmax, spacing, dt):
    """Number of explicit sub-steps of an unsplit flux-form diffusion step.

    All axes diffuse in one update, each face with the mean diffusivity of its two cells,
    so the update is a convex combination when ``dt_sub * sum_k 2 max(D_kk) / h_k**2 <= 1``.

    Parameters
    ----------
    dmax : sequence of float
        The largest D_xx, D_yy (, D_zz) over the cells (m^2/s).
    spacing : tuple of float
        Cell sizes (m) per axis.
    dt : float
        The step to cover (s).

    Returns
    -------
    int
        0 when every diffusivity is zero, else the least count that keeps the bound (at
        least 1).
    """
    rate = sum(2.0 * float(d) / float(h) ** 2 for d, h in zip(dmax, spacing, strict=True))
    if rate == 0.0:
        return 0
    return max(1, math.ceil(float(dt) * rate))
