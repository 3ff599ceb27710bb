"""Shear-rate dependent self-diffusivity of the powder, eq. (5) of the model.

Runs once per stored flow phase on the (coarse) flow grid, so plain NumPy is enough.
"""

import numpy as np

__all__ = ["shear_diffusivity", "shear_rates"]


def _masked_derivative(v, has, axis, h):
    """dv/dx_axis using only cells with material.

    Central difference where both neighbours along ``axis`` hold material, one-sided where
    only one does, zero where neither does; cells beyond the array count as empty. Using
    empty cells would differentiate across the free surface, where the flow solver's
    velocity is meaningless.
    """
    n = v.shape[axis]
    out = np.zeros_like(v)
    if n < 2:
        return out
    vp = np.zeros_like(v)
    vm = np.zeros_like(v)
    hp = np.zeros(v.shape, dtype=bool)
    hm = np.zeros(v.shape, dtype=bool)

    def sl(a, b):
        idx = [slice(None)] * v.ndim
        idx[axis] = slice(a, b)
        return tuple(idx)

    vp[sl(0, n - 1)] = v[sl(1, n)]
    hp[sl(0, n - 1)] = has[sl(1, n)]
    vm[sl(1, n)] = v[sl(0, n - 1)]
    hm[sl(1, n)] = has[sl(0, n - 1)]
    both = hp & hm
    only_p = hp & ~hm
    only_m = hm & ~hp
    out[both] = (vp[both] - vm[both]) / (2.0 * h)
    out[only_p] = (vp[only_p] - v[only_p]) / h
    out[only_m] = (v[only_m] - vm[only_m]) / h
    return out


def shear_rates(velocities, fill, spacing):
    """Directional shear rates of eq. (5).

    3-D: ``g_x = |dv_y/dx| + |dv_z/dx|``, ``g_y = |dv_x/dy| + |dv_z/dy|``,
    ``g_z = |dv_x/dz| + |dv_y/dz|``. 2-D: ``g_x = |dv_y/dx|``, ``g_y = |dv_x/dy|``.
    Derivatives are central where both neighbours hold material (``fill > 0``), one-sided
    where only one does and zero where neither does; the rates are zero where
    ``fill == 0``.

    Parameters
    ----------
    velocities : tuple of ndarray
        (vx, vy) or (vx, vy, vz) in m/s on one grid, axis order x, y(, z).
    fill : ndarray
        Material volume fraction on the same grid.
    spacing : tuple of float
        Cell sizes (m) per axis.

    Returns
    -------
    tuple of ndarray
        ``(g_x, g_y)`` or ``(g_x, g_y, g_z)`` in 1/s.
    """
    vel = tuple(np.asarray(v, dtype=np.float64) for v in velocities)
    fill = np.asarray(fill, dtype=np.float64)
    ndim = len(vel)
    if ndim not in (2, 3) or len(spacing) != ndim:
        raise ValueError("need 2 or 3 velocity components and as many spacings")
    if any(v.shape != fill.shape for v in vel) or fill.ndim != ndim:
        raise ValueError("velocities and fill must share one grid")
    has = fill > 0.0
    rates = []
    for axis in range(ndim):
        g = np.zeros_like(fill)
        for comp in range(ndim):
            if comp != axis:
                g += np.abs(_masked_derivative(vel[comp], has, axis, float(spacing[axis])))
        g[~has] = 0.0
        rates.append(g)
    return tuple(rates)


def shear_diffusivity(velocities, fill, spacing, k1, k2, d):
    """Diagonal self-diffusivity of eq. (5).

    ``D_kk = k1 g_k d**2 + k2 sum_{l != k} g_l d**2`` with the shear rates ``g`` of
    :func:`shear_rates`; in 2-D ``D_xx = k1 g_x d**2 + k2 g_y d**2`` and
    ``D_yy = k1 g_y d**2 + k2 g_x d**2``. Zero where ``fill == 0``.

    Parameters
    ----------
    velocities : tuple of ndarray
        (vx, vy) or (vx, vy, vz) in m/s.
    fill : ndarray
        Material volume fraction on the same grid.
    spacing : tuple of float
        Cell sizes (m) per axis.
    k1, k2 : float
        Dimensionless diffusion constants (the model uses ``k2 = 1.9 k1``).
    d : float
        Mean particle diameter (m).

    Returns
    -------
    tuple of ndarray
        ``(D_xx, D_yy)`` or ``(D_xx, D_yy, D_zz)`` in m^2/s.
    """
    rates = shear_rates(velocities, fill, spacing)
    d2 = float(d) ** 2
    total = sum(rates)
    return tuple(k1 * d2 * g + k2 * d2 * (total - g) for g in rates)
