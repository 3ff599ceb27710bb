"""Numba kernels of the advection-diffusion (ADE) stepper.

Two schemes are provided, each with a 2-D and a 3-D kernel:

``lax-wendroff``
    The paper's second-order Taylor (Lax-Wendroff) finite-difference scheme, eq. (6)-(24),
    for the colour concentration ``c``, clipped to [0, 1], with the free-surface rule that a
    surface cell copies the value one cell inward along the surface normal.

``finite-volume``
    A conservative, bounded finite-volume scheme that transports the material volume
    fraction ``m`` and the species content ``q = m c`` in flux form (dimension-split
    sweeps; m by Lax-Wendroff fluxes limited with Zalesak flux-corrected transport, q by
    the same m fluxes times an MC-limited colour of the leaving material), so the colour
    ``c = q / m`` stays bounded without clipping. See :func:`fv_step_3d`.

All kernels take plain C-contiguous float64 arrays of shape (nx, ny) or (nx, ny, nz) in axis
order (x, y, z) and write into caller-provided output arrays; they never allocate inside
their loops and run ``prange`` over one outermost loop only (grid planes; for the
finite-volume sweeps, the worker threads, each taking blocks of grid lines in turn). The
outermost layer of cells (index 0 and n - 1 on every axis) is never updated: it is copied
unchanged.
"""

import numpy as np
from numba import get_num_threads, njit, prange

__all__ = [
    "LW_EMPTY",
    "LW_INTERIOR",
    "LW_SURFACE",
    "LaxWendroffPlan",
    "fv_max_dt_pair",
    "fv_support",
    "fv_transport_velocity",
    "lerp_into",
    "lw_max_dt_pair_2d",
    "lw_max_dt_pair_3d",
    "lw_apply_2d",
    "lw_apply_3d",
    "lw_classify_2d",
    "lw_classify_3d",
    "lw_coefficients_2d",
    "lw_coefficients_3d",
    "lw_surface_2d",
    "lw_surface_3d",
    "FV_MASS_MARGIN",
    "FV_M_TINY",
    "FV_WORK_FIELDS",
    "concentration",
    "fv_step_2d",
    "fv_step_3d",
    "fv_workspace",
    "lw_free_surface_2d",
    "lw_free_surface_3d",
    "lw_step_2d",
    "lw_step_3d",
]

#: Number of scratch fields the finite-volume kernels need (see :func:`fv_workspace`).
FV_WORK_FIELDS = 7

#: Antidiffusion may not make a cell's outflow exceed ``(1 - FV_MASS_MARGIN) m`` (or the
#: donor-cell outflow, if that is already larger). Every cell then keeps at least this
#: share of its material through a sweep, so ``m`` never cancels to round-off and
#: ``c = q / m`` stays accurate even where ``m`` is tiny.
FV_MASS_MARGIN = 0.125

#: Cells holding no more material than this send nothing and carry no colour information
#: (neighbours ignore them for slopes and bounds, diffusion does not reach them). Material
#: can be squeezed out of a cell geometrically by a compressible flow, and once ``q = m c``
#: reaches the subnormal range its colour is meaningless; freezing such cells keeps the
#: bounds exact and costs nothing in conservation (they keep what they have).
FV_M_TINY = 1e-250

# Every division is guarded, so the NumPy error model (no per-division exception path)
# changes no result and gives leaner code.
_JIT = {"parallel": True, "cache": True, "fastmath": False, "error_model": "numpy"}
_JIT_SCALAR = {"cache": True, "fastmath": False, "error_model": "numpy"}
# Helpers that take arrays are inlined at numba-IR level: a call passes every array as a
# multi-field struct and is not inlined by LLVM, which made the finite-volume cell loop
# about five times slower. Scalar helpers stay ordinary calls (cheap, and they compile once
# for both dimensions).
_JIT_INLINE = {"cache": True, "fastmath": False, "error_model": "numpy", "inline": "always"}


# ---------------------------------------------------------------------------------------
# Lax-Wendroff (the paper's scheme)
#
# The hot loop is split from everything that changes only when the flow fields change:
# ``lw_classify_*`` marks interior / surface / empty cells and the k-range of material in
# each (i, j) row, ``lw_coefficients_*`` folds velocity, diffusivity, its gradient and dt
# into six per-cell numbers, and ``lw_apply_*`` is the stencil alone, touching only interior
# cells inside their row ranges. The driver refreshes the first two a few times per stored
# phase interval and calls the last every step. ``lw_step_*`` composes them for callers
# (and tests) that want one call per step.
# ---------------------------------------------------------------------------------------

#: Cell classes written by :func:`lw_classify_2d` / :func:`lw_classify_3d`.
LW_EMPTY, LW_SURFACE, LW_INTERIOR = 0, 1, 2
#: Coefficients per cell: nu_x, nu_y(, nu_z), then A_k = nu_k**2 / 2 + mu_k per axis.
LW_COEFFICIENTS_2D, LW_COEFFICIENTS_3D = 4, 6


@njit(**_JIT)
def _erode_axis_2d(src, dst, axis):
    """dst = 1 where src and both neighbours along ``axis`` are nonzero (0 on the edge)."""
    nx, ny = src.shape
    for i in prange(nx):
        for j in range(ny):
            if axis == 0:
                edge = i == 0 or i == nx - 1
                ok = not edge and src[i - 1, j] != 0 and src[i + 1, j] != 0
            else:
                edge = j == 0 or j == ny - 1
                ok = not edge and src[i, j - 1] != 0 and src[i, j + 1] != 0
            dst[i, j] = 1 if (ok and src[i, j] != 0) else 0


@njit(**_JIT)
def _erode_axis_3d(src, dst, axis):
    """dst = 1 where src and both neighbours along ``axis`` are nonzero (0 on the edge)."""
    nx, ny, nz = src.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                if src[i, j, k] == 0:
                    dst[i, j, k] = 0
                    continue
                if axis == 0:
                    ok = 0 < i < nx - 1 and src[i - 1, j, k] != 0 and src[i + 1, j, k] != 0
                elif axis == 1:
                    ok = 0 < j < ny - 1 and src[i, j - 1, k] != 0 and src[i, j + 1, k] != 0
                else:
                    ok = 0 < k < nz - 1 and src[i, j, k - 1] != 0 and src[i, j, k + 1] != 0
                dst[i, j, k] = 1 if ok else 0


@njit(**_JIT)
def _classes_from_box_2d(material, box, cls, rows):
    nx, ny = material.shape
    for i in prange(nx):
        lo, hi = ny, 0
        for j in range(ny):
            if material[i, j] == 0:
                cls[i, j] = LW_EMPTY
                continue
            cls[i, j] = LW_INTERIOR if box[i, j] != 0 else LW_SURFACE
            lo = min(lo, j)
            hi = j + 1
        rows[i, 0] = lo if hi > 0 else 0
        rows[i, 1] = hi


@njit(**_JIT)
def _classes_from_box_3d(material, box, cls, rows):
    nx, ny, nz = material.shape
    for i in prange(nx):
        for j in range(ny):
            lo, hi = nz, 0
            for k in range(nz):
                if material[i, j, k] == 0:
                    cls[i, j, k] = LW_EMPTY
                    continue
                cls[i, j, k] = LW_INTERIOR if box[i, j, k] != 0 else LW_SURFACE
                lo = min(lo, k)
                hi = k + 1
            rows[i, j, 0] = lo if hi > 0 else 0
            rows[i, j, 1] = hi


def lw_classify_2d(material, cls, rows, scratch=None):
    """Classify cells and find each row's material range (2-D).

    A cell is interior when all 9 cells of its box are material: the box test is the
    erosion of the mask by a 3x3 square, done as one 1-D erosion per axis (3 reads per cell
    and axis instead of 9).

    Parameters
    ----------
    material : ndarray of uint8, shape (nx, ny)
        1 where the cell holds material.
    cls : ndarray of uint8, shape (nx, ny)
        Receives LW_INTERIOR, LW_SURFACE (material, not interior) or LW_EMPTY.
    rows : ndarray of int64, shape (nx, 2)
        Receives, per row i, the half-open j-range holding every material cell ((0, 0)
        for a row without material).
    scratch : ndarray of uint8, shape (2, nx, ny), optional
        Work space (allocated when not given).
    """
    if scratch is None:
        scratch = np.empty((2, *material.shape), np.uint8)
    _erode_axis_2d(material, scratch[0], 0)
    _erode_axis_2d(scratch[0], scratch[1], 1)
    _classes_from_box_2d(material, scratch[1], cls, rows)


def lw_classify_3d(material, cls, rows, scratch=None):
    """Classify cells and find each (i, j) row's material range (3-D).

    As :func:`lw_classify_2d`, with the 27-cell box (three 1-D erosions) and ``rows`` of
    shape (nx, ny, 2) holding the half-open k-range per (i, j).
    """
    if scratch is None:
        scratch = np.empty((2, *material.shape), np.uint8)
    _erode_axis_3d(material, scratch[0], 0)
    _erode_axis_3d(scratch[0], scratch[1], 1)
    _erode_axis_3d(scratch[1], scratch[0], 2)
    _classes_from_box_3d(material, scratch[0], cls, rows)


@njit(**_JIT_INLINE)
def _mix(a, b, w):
    """The blend a + w (b - a) of two phases' values (w = 0: exactly a)."""
    return a + w * (b - a)


@njit(**_JIT)
def lw_coefficients_2d(vel_a, vel_b, dif_a, dif_b, w, cls, dt, dx, dy, coef):
    """Per-cell coefficients of eq. (6) for interior cells (2-D), of the flow blended at
    weight ``w`` between two phases (``vel_*``, ``dif_*`` of shape (2, nx, ny)).

    ``coef[0:2]`` = nu_k = (w_k - dt/2 (w . grad) v_k) dt / h_k with the effective velocity
    w_k = v_k - dD_kk/dx_k of eq. (4) (eq. 7-8 as they should read, gradients by central
    differences, eq. 22-23), and ``coef[2:4]`` = (w_k dt / h_k)**2 / 2 + mu_k with
    mu_k = D_kk dt / h_k**2 (eq. 10-11). The ``(w . grad) v`` term is the part of
    c_tt = w.grad(w.grad c) that eq. (6) omits when the velocity varies in space; without
    it the scheme is only first-order in time on such flows (docs/numerics.md).
    The blend is formed where it is read, so no blended field is written; ``w = 0``
    gives phase a's values bit for bit. Other cells are left as they are (never read).
    """
    nx, ny = cls.shape
    xa, ya, xb, yb = vel_a[0], vel_a[1], vel_b[0], vel_b[1]
    pa, qa, pb, qb = dif_a[0], dif_a[1], dif_b[0], dif_b[1]
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            if cls[i, j] != LW_INTERIOR:
                continue
            vx = _mix(xa[i, j], xb[i, j], w)
            vy = _mix(ya[i, j], yb[i, j], w)
            dvx_x = _mix(xa[i + 1, j], xb[i + 1, j], w) - _mix(xa[i - 1, j], xb[i - 1, j], w)
            dvx_y = _mix(xa[i, j + 1], xb[i, j + 1], w) - _mix(xa[i, j - 1], xb[i, j - 1], w)
            dvy_x = _mix(ya[i + 1, j], yb[i + 1, j], w) - _mix(ya[i - 1, j], yb[i - 1, j], w)
            dvy_y = _mix(ya[i, j + 1], yb[i, j + 1], w) - _mix(ya[i, j - 1], yb[i, j - 1], w)
            ddx = _mix(pa[i + 1, j], pb[i + 1, j], w) - _mix(pa[i - 1, j], pb[i - 1, j], w)
            ddy = _mix(qa[i, j + 1], qb[i, j + 1], w) - _mix(qa[i, j - 1], qb[i, j - 1], w)
            wx = vx - ddx / (2.0 * dx)
            wy = vy - ddy / (2.0 * dy)
            adv_x = wx * dvx_x / (2.0 * dx) + wy * dvx_y / (2.0 * dy)
            adv_y = wx * dvy_x / (2.0 * dx) + wy * dvy_y / (2.0 * dy)
            nux = wx * dt / dx
            nuy = wy * dt / dy
            coef[0, i, j] = (wx - 0.5 * dt * adv_x) * dt / dx
            coef[1, i, j] = (wy - 0.5 * dt * adv_y) * dt / dy
            coef[2, i, j] = 0.5 * nux * nux + _mix(pa[i, j], pb[i, j], w) * dt / (dx * dx)
            coef[3, i, j] = 0.5 * nuy * nuy + _mix(qa[i, j], qb[i, j], w) * dt / (dy * dy)


@njit(**_JIT_INLINE)
def _rows_3d(v, i, j):
    """Rows (along k) of field ``v`` at (i, j) and one off along x and y."""
    return v[i, j], v[i + 1, j], v[i - 1, j], v[i, j + 1], v[i, j - 1]


@njit(**_JIT_INLINE)
def _lw_axis_coefficients(
    wk, w0, w1, w2, adv, v_a, v_b, v_a_xp, v_b_xp, v_a_xm, v_b_xm, v_a_yp, v_b_yp,
    v_a_ym, v_b_ym, d_a, d_b, w, gx, gy, gz, dt, t, m, nu_out, a_out, klo, khi,
):  # fmt: skip
    """nu_k and A_k of one axis along a row, from the row's blended effective velocity
    (``w0``, ``w1``, ``w2``; ``wk`` the axis's own) and the blended gradient of v_k.

    Five loops of at most six loads and one store each, so that LLVM vectorises every
    one (one loop with all of them had more pointers than its alias checks take). The
    sums are formed in the order of the single expression they replace, so the
    coefficients are the same bits.
    """
    for k in range(klo, khi):
        adv[k] = w0[k] * (_mix(v_a_xp[k], v_b_xp[k], w) - _mix(v_a_xm[k], v_b_xm[k], w)) * gx
    for k in range(klo, khi):
        dv = _mix(v_a_yp[k], v_b_yp[k], w) - _mix(v_a_ym[k], v_b_ym[k], w)
        adv[k] = adv[k] + w1[k] * dv * gy
    for k in range(klo, khi):
        kp = k + _U1
        km = k - _U1
        adv[k] = adv[k] + w2[k] * (_mix(v_a[kp], v_b[kp], w) - _mix(v_a[km], v_b[km], w)) * gz
    for k in range(klo, khi):
        nu_out[k] = (wk[k] - 0.5 * dt * adv[k]) * t
    for k in range(klo, khi):
        nu = wk[k] * t
        a_out[k] = 0.5 * nu * nu + _mix(d_a[k], d_b[k], w) * m


@njit(**_JIT)
def lw_coefficients_3d(vel_a, vel_b, dif_a, dif_b, w, cls, rows, dt, dx, dy, dz, coef, scratch):
    """Per-cell coefficients of eq. (6) (3-D), of the flow blended at weight ``w`` between
    two phases (``vel_*``, ``dif_*`` of shape (3, nx, ny, nz)); see the 2-D version.

    Written like the stencil (:func:`lw_apply_3d`): along each (i, j) row's material
    range, with unsigned indices. The row's blended effective velocity goes to
    ``scratch[i]`` (shape (nx, 4, nz), float64: three components and the advective
    correction of the axis at hand), and each coefficient is made from it in short
    loops that LLVM vectorises. Cells of the range that are not interior get
    coefficients too (from whatever the fields hold there); the stencil never uses them.
    """
    nx, ny, nz = cls.shape
    # reciprocals once: the divisions were most of this loop's arithmetic
    gx, gy, gz = 0.5 / dx, 0.5 / dy, 0.5 / dz
    tx, ty, tz = dt / dx, dt / dy, dt / dz
    mx, my, mz = dt / (dx * dx), dt / (dy * dy), dt / (dz * dz)
    for i in prange(1, nx - 1):
        wx, wy, wz, adv = scratch[i, 0], scratch[i, 1], scratch[i, 2], scratch[i, 3]
        for j in range(1, ny - 1):
            lo = max(rows[i, j, 0], 1)
            hi = min(rows[i, j, 1], nz - 1)
            if hi <= lo:
                continue
            klo = np.uint64(lo)
            khi = np.uint64(hi)
            xa, xa_xp, xa_xm, xa_yp, xa_ym = _rows_3d(vel_a[0], i, j)
            xb, xb_xp, xb_xm, xb_yp, xb_ym = _rows_3d(vel_b[0], i, j)
            ya, ya_xp, ya_xm, ya_yp, ya_ym = _rows_3d(vel_a[1], i, j)
            yb, yb_xp, yb_xm, yb_yp, yb_ym = _rows_3d(vel_b[1], i, j)
            za, za_xp, za_xm, za_yp, za_ym = _rows_3d(vel_a[2], i, j)
            zb, zb_xp, zb_xm, zb_yp, zb_ym = _rows_3d(vel_b[2], i, j)
            pa, pa_xp, pa_xm = dif_a[0, i, j], dif_a[0, i + 1, j], dif_a[0, i - 1, j]
            pb, pb_xp, pb_xm = dif_b[0, i, j], dif_b[0, i + 1, j], dif_b[0, i - 1, j]
            qa, qa_yp, qa_ym = dif_a[1, i, j], dif_a[1, i, j + 1], dif_a[1, i, j - 1]
            qb, qb_yp, qb_ym = dif_b[1, i, j], dif_b[1, i, j + 1], dif_b[1, i, j - 1]
            ra, rb = dif_a[2, i, j], dif_b[2, i, j]
            # the effective velocity w_k = v_k - dD_kk/dx_k of the blend, one loop a component
            for k in range(klo, khi):
                dd = _mix(pa_xp[k], pb_xp[k], w) - _mix(pa_xm[k], pb_xm[k], w)
                wx[k] = _mix(xa[k], xb[k], w) - dd * gx
            for k in range(klo, khi):
                dd = _mix(qa_yp[k], qb_yp[k], w) - _mix(qa_ym[k], qb_ym[k], w)
                wy[k] = _mix(ya[k], yb[k], w) - dd * gy
            for k in range(klo, khi):
                kp = k + _U1
                km = k - _U1
                dd = _mix(ra[kp], rb[kp], w) - _mix(ra[km], rb[km], w)
                wz[k] = _mix(za[k], zb[k], w) - dd * gz
            _lw_axis_coefficients(
                wx, wx, wy, wz, adv, xa, xb, xa_xp, xb_xp, xa_xm, xb_xm, xa_yp, xb_yp, xa_ym,
                xb_ym, pa, pb, w, gx, gy, gz, dt, tx, mx, coef[0, i, j], coef[3, i, j], klo, khi,
            )  # fmt: skip
            _lw_axis_coefficients(
                wy, wx, wy, wz, adv, ya, yb, ya_xp, yb_xp, ya_xm, yb_xm, ya_yp, yb_yp, ya_ym,
                yb_ym, qa, qb, w, gx, gy, gz, dt, ty, my, coef[1, i, j], coef[4, i, j], klo, khi,
            )  # fmt: skip
            _lw_axis_coefficients(
                wz, wx, wy, wz, adv, za, zb, za_xp, zb_xp, za_xm, zb_xm, za_yp, zb_yp, za_ym,
                zb_ym, ra, rb, w, gx, gy, gz, dt, tz, mz, coef[2, i, j], coef[5, i, j], klo, khi,
            )  # fmt: skip


# The stencil loops index rows with unsigned integers: numba wraps negative signed indices
# around (a select per access), which keeps LLVM from vectorising the loop; an unsigned
# index needs no such check and the row loop becomes SIMD (about twice as fast). The class
# test is a select, not a branch, for the same reason: cells of a row's material range
# that are not interior are computed too (from coefficients that may be stale) and their
# old value is stored back unchanged.
_U1 = np.uint64(1)


@njit(**_JIT)
def lw_apply_2d(c, out, coef, cls, rows):
    """The Lax-Wendroff stencil on interior cells only (2-D).

    ``out = c - sum_k [nu_k D0_k c - A_k d2_k c] + nu_x nu_y D0_x D0_y c``, clipped to
    [0, 1]. Cells that are not interior keep their value in ``out``: the caller keeps them
    equal in both buffers (surface cells are set by :func:`lw_surface_2d` every step).
    """
    nx, ny = c.shape
    for i in prange(1, nx - 1):
        lo = max(rows[i, 0], 1)
        hi = min(rows[i, 1], ny - 1)
        if hi <= lo:
            continue
        cc, cxp, cxm = c[i], c[i + 1], c[i - 1]
        nu_x, nu_y, a_x, a_y = coef[0, i], coef[1, i], coef[2, i], coef[3, i]
        cl = cls[i]
        o = out[i]
        for j in range(np.uint64(lo), np.uint64(hi)):
            jp = j + _U1
            jm = j - _U1
            c0 = cc[j]
            nux = nu_x[j]
            nuy = nu_y[j]
            val = (
                c0
                - nux * 0.5 * (cxp[j] - cxm[j])
                + a_x[j] * (cxp[j] - 2.0 * c0 + cxm[j])
                - nuy * 0.5 * (cc[jp] - cc[jm])
                + a_y[j] * (cc[jp] - 2.0 * c0 + cc[jm])
                + nux * nuy * 0.25 * (cxp[jp] - cxm[jp] - cxp[jm] + cxm[jm])
            )
            val = min(1.0, max(0.0, val))
            o[j] = val if cl[j] == LW_INTERIOR else o[j]


@njit(**_JIT)
def lw_apply_3d(c, out, coef, cls, rows):
    """The Lax-Wendroff stencil on interior cells only (3-D); see the 2-D version.

    Adds the three cross terms nu_x nu_y D0_x D0_y c, nu_y nu_z D0_y D0_z c and
    nu_z nu_x D0_z D0_x c of eq. (6), (19)-(21).
    """
    nx, ny, nz = c.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            lo = max(rows[i, j, 0], 1)
            hi = min(rows[i, j, 1], nz - 1)
            if hi <= lo:
                continue
            cc, cxp, cxm, cyp, cym = c[i, j], c[i + 1, j], c[i - 1, j], c[i, j + 1], c[i, j - 1]
            cpp, cmp, cpm, cmm = c[i + 1, j + 1], c[i - 1, j + 1], c[i + 1, j - 1], c[i - 1, j - 1]
            nu_x, nu_y, nu_z = coef[0, i, j], coef[1, i, j], coef[2, i, j]
            a_x, a_y, a_z = coef[3, i, j], coef[4, i, j], coef[5, i, j]
            cl = cls[i, j]
            o = out[i, j]
            for k in range(np.uint64(lo), np.uint64(hi)):
                kp = k + _U1
                km = k - _U1
                c0 = cc[k]
                nux = nu_x[k]
                nuy = nu_y[k]
                nuz = nu_z[k]
                xp = cxp[k]
                xm = cxm[k]
                yp = cyp[k]
                ym = cym[k]
                zp = cc[kp]
                zm = cc[km]
                dxy = cpp[k] - cmp[k] - cpm[k] + cmm[k]
                dyz = cyp[kp] - cym[kp] - cyp[km] + cym[km]
                dzx = cxp[kp] - cxm[kp] - cxp[km] + cxm[km]
                val = (
                    c0
                    - 0.5 * (nux * (xp - xm) + nuy * (yp - ym) + nuz * (zp - zm))
                    + a_x[k] * (xp - 2.0 * c0 + xm)
                    + a_y[k] * (yp - 2.0 * c0 + ym)
                    + a_z[k] * (zp - 2.0 * c0 + zm)
                    + 0.25 * (nux * nuy * dxy + nuy * nuz * dyz + nuz * nux * dzx)
                )
                val = min(1.0, max(0.0, val))
                o[k] = val if cl[k] == LW_INTERIOR else o[k]


# The free-surface rule works on the list of surface cells (flat indices, made at each
# classification) and, per cell, where its value comes from: the flat offset of the cell
# one step inward, or the interior cells of its box as a bit mask (bit (a + 1) 9 +
# (b + 1) 3 + (e + 1) for the offset (a, b, e) in 3-D, (a + 1) 3 + (b + 1) in 2-D, i.e.
# in flat-index order). Those depend on the classes and the fill only, so the plan finds
# them once per classification and fill; a step of the rule is then a gather. Scanning
# every material row for the few surface cells and reading the fill around them each step
# took about as long as the stencil. Flat arrays and strides let one kernel serve both
# dimensions.


@njit(**_JIT)
def _surface_cells(cls, rows, n_mid, starts, cells, write):
    """Count (``write`` False) or list (``write`` True) the surface cells, by planes.

    ``cls`` and ``rows`` are viewed as lines along the last axis, ``cls`` of shape
    (n_lines, n_last) and ``rows`` (n_lines, 2); line ``L`` is (i, j) = divmod(L, n_mid) in
    3-D and i = L in 2-D (``n_mid`` = 1). Counting puts plane i's count in ``starts[i + 1]``;
    listing writes plane i's flat indices from ``starts[i]`` on. Cells of the outermost
    layer are never listed.
    """
    n_lines, n_last = cls.shape
    n_outer = n_lines // n_mid
    for i in prange(1, n_outer - 1):
        at = starts[i] if write else 0
        for line in range(i * n_mid, (i + 1) * n_mid):
            if n_mid > 1 and (line - i * n_mid < 1 or line - i * n_mid > n_mid - 2):
                continue
            for k in range(max(rows[line, 0], 1), min(rows[line, 1], n_last - 1)):
                if cls[line, k] != LW_SURFACE:
                    continue
                if write:
                    cells[at] = line * n_last + k
                at += 1
        if not write:
            starts[i + 1] = at


@njit(**_JIT_INLINE)
def _box_mask(flat_cls, f, sx, sy, ndim):
    """Bit mask of the interior cells in the box of flat cell ``f`` (bits in flat order).

    The loops have constant bounds, so they are unrolled: with bounds known only at run
    time the same loops took five times as long.
    """
    mask = 0
    bit = 0
    for a in range(-1, 2):
        for b in range(-1, 2):
            g = f + a * sx + b * sy
            if ndim == 3:
                for e in range(-1, 2):
                    if flat_cls[g + e] == LW_INTERIOR:
                        mask |= 1 << bit
                    bit += 1
            else:
                if flat_cls[g] == LW_INTERIOR:
                    mask |= 1 << bit
                bit += 1
    return mask


def _list_surface_cells(cls, rows):
    """Flat indices of the surface cells and the grid's flat strides."""
    ndim = cls.ndim
    shape = cls.shape
    n_mid = shape[1] if ndim == 3 else 1
    strides = np.array(
        (shape[1] * shape[2], shape[2], 1) if ndim == 3 else (shape[1], 1, 0), np.int64
    )
    lines = cls.reshape(-1, shape[-1])
    row_lines = rows.reshape(-1, 2)
    starts = np.zeros(shape[0] + 1, np.int64)
    _surface_cells(lines, row_lines, n_mid, starts, starts[:0], False)
    np.cumsum(starts, out=starts)
    cells = np.empty(starts[-1], np.int64)
    _surface_cells(lines, row_lines, n_mid, starts, cells, True)
    return cells, strides


@njit(**_JIT_INLINE)
def _normal_step(n, nmax):
    """Integer step (-1, 0, 1) along one axis of the inward normal component ``n``."""
    if abs(n) >= 0.5 * nmax and n != 0.0:
        return 1 if n > 0.0 else -1
    return 0


@njit(**_JIT)
def _surface_steps(fill, flat_cls, cells, strides, ndim, steps, masks):
    """Where each surface cell takes its value from.

    ``steps[s]`` is the flat offset of the cell one step inward along the normal; where
    that cell is not interior it is 0 and ``masks[s]`` marks the interior cells of the box
    (see :func:`_box_mask`), whose mean is used.
    """
    sx, sy, sz = strides[0], strides[1], strides[2]
    for s in prange(cells.size):
        f = cells[s]
        nxv = 0.5 * (fill[f + sx] - fill[f - sx])
        nyv = 0.5 * (fill[f + sy] - fill[f - sy])
        if ndim == 3:
            nzv = 0.5 * (fill[f + sz] - fill[f - sz])
            nmax = max(abs(nxv), max(abs(nyv), abs(nzv)))
            oz = _normal_step(nzv, nmax)
        else:
            nmax = max(abs(nxv), abs(nyv))
            oz = 0
        step = _normal_step(nxv, nmax) * sx + _normal_step(nyv, nmax) * sy + oz * sz
        if flat_cls[f + step] == LW_INTERIOR:
            steps[s] = step
            masks[s] = 0
        else:
            steps[s] = 0
            masks[s] = _box_mask(flat_cls, f, sx, sy, ndim)


@njit(**_JIT)
def _surface_rule(out, cells, masks, steps, strides, ndim):
    """The free-surface rule on flat ``out`` for the listed cells (see :func:`_surface_steps`)."""
    sx, sy, sz = strides[0], strides[1], strides[2]
    e_lo = -1 if ndim == 3 else 0
    e_hi = 2 if ndim == 3 else 1
    for s in prange(cells.size):
        f = cells[s]
        step = steps[s]
        if step != 0:
            out[f] = out[f + step]
            continue
        mask = masks[s]
        if mask == 0:
            continue
        total = 0.0
        count = 0
        bit = 0
        for a in range(-1, 2):
            for b in range(-1, 2):
                for e in range(e_lo, e_hi):
                    if (mask >> bit) & 1:
                        total += out[f + a * sx + b * sy + e * sz]
                        count += 1
                    bit += 1
        out[f] = total / count


def _free_surface(out, cls, rows, fill):
    cells, strides = _list_surface_cells(cls, rows)
    steps = np.empty_like(cells)
    masks = np.empty_like(cells)
    _surface_steps(fill.reshape(-1), cls.reshape(-1), cells, strides, cls.ndim, steps, masks)
    _surface_rule(out.reshape(-1), cells, masks, steps, strides, cls.ndim)


def lw_surface_2d(out, cls, rows, fill):
    """Free-surface rule of the paper in 2-D, applied in place to ``out``.

    Every surface cell takes the value of ``out`` at the cell one step inward along the
    surface normal ``n = grad(fill)`` (central differences in index space; the step along
    axis k is ``sign(n_k)`` where ``|n_k| >= max_k |n_k| / 2``, else 0). If that cell is
    not interior, the mean of the interior cells of the box is used; if there are none,
    the value is kept. Only interior cells are read and only surface cells written, so
    the parallel pass is free of races. Cells of the outermost layer are left alone.
    :class:`LaxWendroffPlan` keeps the surface cells and their steps between calls; this
    function finds them on every call.
    """
    _free_surface(out, cls, rows, fill)


def lw_surface_3d(out, cls, rows, fill):
    """Free-surface rule of the paper in 3-D; see :func:`lw_surface_2d`."""
    _free_surface(out, cls, rows, fill)


class LaxWendroffPlan:
    """Buffers for the split Lax-Wendroff kernels on one grid (allocated once).

    Parameters
    ----------
    shape : tuple of int
        Grid shape, 2-D or 3-D.
    """

    def __init__(self, shape):
        ndim = len(shape)
        self.ndim = ndim
        self.cls = np.zeros(shape, np.uint8)
        self.scratch = np.zeros((2, *shape), np.uint8)
        self.rows = np.zeros((*shape[:-1], 2), np.int64)
        n_coef = LW_COEFFICIENTS_3D if ndim == 3 else LW_COEFFICIENTS_2D
        self.coef = np.zeros((n_coef, *shape))
        # rows of the blended effective velocity, per plane (see lw_coefficients_3d)
        self.row_scratch = np.zeros((shape[0], 4, shape[-1])) if ndim == 3 else None
        self._list_surface()

    def _list_surface(self):
        self.surface_cells, self.strides = _list_surface_cells(self.cls, self.rows)
        self.surface_steps = np.zeros_like(self.surface_cells)
        self.surface_masks = np.zeros_like(self.surface_cells)
        self._steps_from = None  # the fill the steps were computed from

    def classify(self, material):
        """Mark interior, surface and empty cells from a material mask."""
        classify = lw_classify_3d if self.ndim == 3 else lw_classify_2d
        classify(material, self.cls, self.rows, self.scratch)
        self._list_surface()

    def coefficients(self, velocities, diffusivities, dt, spacing):
        """Fold the fields and dt into the per-cell coefficients (after :meth:`classify`)."""
        vel = np.ascontiguousarray(np.stack(velocities), dtype=np.float64)
        dif = np.ascontiguousarray(np.stack(diffusivities), dtype=np.float64)
        self.coefficients_between(vel, vel, dif, dif, 0.0, dt, spacing)

    def coefficients_between(self, vel_a, vel_b, dif_a, dif_b, w, dt, spacing):
        """Coefficients of the flow blended at weight ``w`` between two phases (stacked
        components, shape (ndim, *shape)), without writing the blended fields."""
        if self.ndim == 3:
            lw_coefficients_3d(vel_a, vel_b, dif_a, dif_b, float(w), self.cls, self.rows, dt,
                               *spacing, self.coef, self.row_scratch)  # fmt: skip
        else:
            lw_coefficients_2d(vel_a, vel_b, dif_a, dif_b, float(w), self.cls, dt, *spacing,
                               self.coef)  # fmt: skip

    def apply(self, c, out):
        """One step of the stencil on interior cells, ``c`` -> ``out``."""
        (lw_apply_3d if self.ndim == 3 else lw_apply_2d)(c, out, self.coef, self.cls, self.rows)

    def surface(self, out, fill):
        """The free-surface copy, in place on ``out``.

        ``fill`` is the field the classified material came from: the inward step of each
        surface cell is found from it at the first call after :meth:`classify` (or when
        another array is passed) and reused, since reading ``fill`` around every surface
        cell took as long as the copy itself. Call :meth:`classify` again after changing
        ``fill`` in place.
        """
        if self._steps_from is not fill:
            _surface_steps(
                fill.reshape(-1),
                self.cls.reshape(-1),
                self.surface_cells,
                self.strides,
                self.ndim,
                self.surface_steps,
                self.surface_masks,
            )
            self._steps_from = fill
        _surface_rule(
            out.reshape(-1),
            self.surface_cells,
            self.surface_masks,
            self.surface_steps,
            self.strides,
            self.ndim,
        )

    def interior_cells(self) -> int:
        """Number of cells the stencil updates."""
        return int(np.count_nonzero(self.cls == LW_INTERIOR))


def lw_step_2d(c, out, vx, vy, dxx, dyy, material, dt, dx, dy):
    """One explicit Lax-Wendroff step of eq. (4) in 2-D (eq. 6 as it should read).

    Interior material cells (all 9 cells of their box are material) get
    ``c - sum_k [nu_k D0_k c - (nu_k**2 / 2 + mu_k) d2_k c] + nu_x nu_y D0_x D0_y c``
    clipped to [0, 1], with ``nu_k = (v_k - dD_kk/dx_k) dt / h_k``, ``mu_k = D_kk dt / h_k**2``;
    every other cell is copied from ``c`` (surface cells are then set by
    :func:`lw_free_surface_2d`). A convenience composition of the split kernels; it
    allocates its plan, so time loops use :class:`LaxWendroffPlan` instead.
    """
    plan = LaxWendroffPlan(c.shape)
    plan.classify(material)
    plan.coefficients((vx, vy), (dxx, dyy), dt, (dx, dy))
    out[...] = c
    plan.apply(c, out)


def lw_step_3d(c, out, vx, vy, vz, dxx, dyy, dzz, material, dt, dx, dy, dz):
    """One explicit Lax-Wendroff step of eq. (4) in 3-D (eq. 6 as it should read).

    As :func:`lw_step_2d`, with the 27-cell box and the three cross terms of eq. (19)-(21).
    The update is ``c + dt c_t + dt**2 / 2 c_tt`` with ``c_t = -a . grad c + sum_k D_kk
    c_kk`` and ``c_tt ~ (a . grad)**2 c``, ``a`` the effective velocity of eq. (4).
    """
    plan = LaxWendroffPlan(c.shape)
    plan.classify(material)
    plan.coefficients((vx, vy, vz), (dxx, dyy, dzz), dt, (dx, dy, dz))
    out[...] = c
    plan.apply(c, out)


def lw_free_surface_2d(out, material, fill):
    """The paper's free-surface rule on ``out`` given a material mask (2-D)."""
    plan = LaxWendroffPlan(out.shape)
    plan.classify(material)
    plan.surface(out, fill)


def lw_free_surface_3d(out, material, fill):
    """The paper's free-surface rule on ``out`` given a material mask (3-D)."""
    plan = LaxWendroffPlan(out.shape)
    plan.classify(material)
    plan.surface(out, fill)


# ---------------------------------------------------------------------------------------
# Conservative bounded finite volume
# ---------------------------------------------------------------------------------------


def fv_workspace(shape):
    """Allocate the scratch array of :func:`fv_step_2d` / :func:`fv_step_3d`.

    Parameters
    ----------
    shape : tuple of int
        Grid shape, (nx, ny) or (nx, ny, nz).

    Returns
    -------
    ndarray, shape (FV_WORK_FIELDS, *shape)
        Zero-initialised float64 scratch array; reuse it for every step.
    """
    return np.zeros((FV_WORK_FIELDS, *tuple(int(n) for n in shape)), dtype=np.float64)


# How the finite-volume sweep is computed (the mathematics is in fv_step_3d's docstring).
#
# A sweep along one axis is a set of independent 1-D problems, one per grid line along
# the axis. Work items are blocks of whole lines; each worker thread copies its block into
# a compact scratch area of its own (inside ``work``) and runs the scheme on it in small
# vectorisable loops, one per stage:
#
#   F1 faces: Courant number sigma, antidiffusion A      C2 cells: Zalesak ratios of m
#   F3 faces: limited m flux                             C4 cells: new m, leaving colours
#   F5 faces: species flux                               C6 cells: new q (and c = q / m)
#   then per diffusion sub-step   F7 faces: diffusive flux    C8 cells: new q (and c)
#
# Each face is shared by two cells, so every face quantity is computed once, stored at the
# face's lower cell, and read by both cells. Selects replace branches and indices are
# unsigned (see the Lax-Wendroff stencil) so that LLVM vectorises every stage. Each flux
# and update is evaluated with the same operations in the same order as in the scheme's
# definition (reference.py); the face values both cells see are the same bits, so the
# update stays in exact flux form.
#
# Layout: along x and y (axes 0, 1) a block is ``width`` neighbouring lines and the inner
# loops run across lines (unit stride); the block streams through the sweep axis as a
# wavefront: at time t grid row t is read in, stage s works on row t - 1 - s and row
# t - 1 - n_stages is written out, so only ``ring`` rows of each scratch field are alive
# and they stay in cache. Along z (axis 2, contiguous) a block is ``width`` whole lines
# and each stage runs along them. Along each block only cells from one before the first
# to one after the last cell holding material are updated; the rest, and blocks without
# material, are copied through (no face between two empty cells moves anything). 2-D
# grids run as (nx, 1, ny) for the x sweep and (1, nx, ny) for the y sweep, so one
# compiled kernel serves both dimensions.

#: Scratch fields per worker: m, q, c, new m, new q, then five face/cell fields reused
#: between stages, face openness, face diffusivity and a per-line validity mask.
_FV_FIELDS = 13
#: Scratch bytes per worker: the block and all its stages stay in L2.
_FV_BLOCK_BYTES = 1 << 20


@njit(**_JIT_INLINE)
def _movable(sm, vessel, i):
    """Whether cell i holds material inside the support (``vessel``): the only cells a
    sweep can change or move from. Material the flow left behind outside the support
    (faces to it are closed, it takes no diffusion) comes out of every stage unchanged,
    so windows are made around movable material only and the rest is copied through,
    the same bits (how much stranded material a Tote's run holds: docs/numerics.md)."""
    return (sm[i] > 0.0) & (vessel[i] != 0)


@njit(**_JIT_INLINE)
def _any_support(vessel, g, n):
    """Whether any of the n cells from flat index g is in the support: a row without is
    skipped before its m is read (one byte a cell instead of nine, where most of a grid
    is outside the flow)."""
    count = 0
    for k in range(np.uint64(0), np.uint64(n)):
        count += 1 if vessel[g + k] != 0 else 0
    return count > 0


@njit(**_JIT_INLINE)
def _ratio(g, p):
    """Zalesak ratio: the share of the harmful antidiffusion ``p`` the slack ``g`` allows."""
    r = max(0.0, min(1.0, g / p))
    return 1.0 if p <= 0.0 else r


@njit(**_JIT_SCALAR)
def _fv_block(
    sm, sq, dm, dq, scr, v, dif, vessel, n0, n1, n2, lo0, hi0, lo1, hi1,
    axis, cfl, kdiff, n_diff_sub, width, ring, item, copy_through,
):  # fmt: skip
    """One work item of a sweep along ``axis`` (flat arrays of a (n0, n1, n2) grid).

    A plain function, not inlined into the parallel loop: numba's parallel passes then
    see a small loop body, which keeps compilation short. ``lo0:hi0`` and ``lo1:hi1`` are
    the cells of axes 0 and 1 a sweep may update (axis 2: 1 to n2 - 2). Without
    ``copy_through`` the sweep works in place (``dm`` is ``sm``, ``dq`` is ``sq``): the
    cells it does not update are already where they belong, and are not touched.
    """
    M, Q, CC, DM, DQ = scr[0], scr[1], scr[2], scr[3], scr[4]
    S, A, R1, R2, R3 = scr[5], scr[6], scr[7], scr[8], scr[9]
    OP, DF, VALID = scr[10], scr[11], scr[12]
    s0 = n1 * n2
    along = axis == 2
    n_stages = 6 + 2 * n_diff_sub
    tiny = FV_M_TINY
    keep = 1.0 - FV_MASS_MARGIN
    one = np.uint64(1)
    r0 = 0
    if axis == 0:
        # lines (j, k) b0 .. b0 + nl - 1 (contiguous in memory), rows i at stride s0
        na, g_row, g_step = n0, s0, s0
        b0 = item * width
        nl = min(width, s0 - b0)
        plane_ok = True
        for col in range(nl):
            j = (b0 + col) // n2
            k = b0 + col - j * n2
            VALID[col] = 1.0 if (lo1 <= j < hi1) and (1 <= k <= n2 - 2) else 0.0
    elif axis == 1:
        # lines k0 .. k0 + nl - 1 of plane o, rows j at stride n2
        na, g_row, g_step = n1, n2, n2
        n_blocks = (n2 + width - 1) // width
        o = item // n_blocks
        k0 = (item - o * n_blocks) * width
        b0 = o * s0 + k0
        nl = min(width, n2 - k0)
        plane_ok = lo0 <= o < hi0
        for col in range(nl):
            VALID[col] = 1.0 if 1 <= k0 + col <= n2 - 2 else 0.0
    else:
        # lines j = r0 .. r0 + nl - 1 of plane o, each n2 cells long
        na, g_row, g_step = n2, n2, 1
        n_blocks = (n1 + width - 1) // width
        o = item // n_blocks
        r0 = (item - o * n_blocks) * width
        b0 = o * s0 + r0 * n2
        nl = min(width, n1 - r0)
        plane_ok = lo0 <= o < hi0
    n_rows = nl if along else na
    row_len = n2 if along else nl
    pos_hi = np.uint64(max(na - 3, 0))
    # positions along the sweep holding material that can move: first .. last (-1:
    # none); across the sweep (axes 0, 1), the lines holding such material: line_lo ..
    # line_hi (see _movable)
    first = -1
    last = -1
    line_lo = row_len
    line_hi = -1
    if plane_ok:
        for row in range(n_rows):
            if not _any_support(vessel, np.uint64(b0 + row * g_row), row_len):
                continue
            if along:
                gi = b0 + row * g_row
                lo = 0
                while lo < n2 and not _movable(sm, vessel, gi + lo):
                    lo += 1
                if lo < n2:
                    hi = n2 - 1
                    while not _movable(sm, vessel, gi + hi):
                        hi -= 1
                    first = lo if first < 0 else min(first, lo)
                    last = max(last, hi)
            else:
                g = np.uint64(b0 + row * g_row)
                n_mat = 0
                for k in range(np.uint64(0), np.uint64(row_len)):
                    n_mat += 1 if _movable(sm, vessel, g + k) else 0
                if n_mat > 0:
                    first = row if first < 0 else first
                    last = row
                    lo = 0
                    while not _movable(sm, vessel, g + lo):
                        lo += 1
                    hi = row_len - 1
                    while not _movable(sm, vessel, g + hi):
                        hi -= 1
                    line_lo = min(line_lo, lo)
                    line_hi = max(line_hi, hi)
    if first < 0:
        # no material, or outside the updated range: copied through
        if not copy_through:
            return
        for row in range(n_rows):
            g = np.uint64(b0 + row * g_row)
            for k in range(np.uint64(0), np.uint64(row_len)):
                dm[g + k] = sm[g + k]
                dq[g + k] = sq[g + k]
        return
    # Only a window of positions can change: an empty cell next to material may gain some,
    # and a face between two empty cells carries nothing. Read in w0 .. w1 - 1, compute
    # faces w0 .. f_hi and cells c_lo .. c_hi; everything else is copied through.
    w0 = max(first - 2, 0)
    w1 = min(last + 3, na)
    f_hi = min(w1 - 2, na - 2)
    c_lo = max(w0 + 1, 1)
    c_hi = f_hi
    if along:
        for col in range(n2):
            VALID[col] = 1.0 if c_lo <= col <= c_hi else 0.0
        n_t = n_stages + 2
        pitch = n2
        mask = -1
    else:
        if copy_through:
            for row in range(na):
                if w0 <= row < w1:
                    continue
                g = np.uint64(b0 + row * g_row)
                for k in range(np.uint64(0), np.uint64(row_len)):
                    dm[g + k] = sm[g + k]
                    dq[g + k] = sq[g + k]
        n_t = w1 - w0 + n_stages + 1
        pitch = width
        mask = ring - 1
        # Lines are independent 1-D problems, and a line without material anywhere in the
        # block comes out of every stage unchanged (nothing leaves an empty cell, no
        # diffusion without material): the stages skip such lines at the block's sides
        # and the write-out copies them, the same bits.
        for col in range(nl):
            if col < line_lo or col > line_hi:
                VALID[col] = 0.0
    for step in range(n_t):
        t = step if along else w0 + step
        # read rows in (c = q / m is computed once per cell, for the colour stage)
        if along:
            in_hi = nl if t == 0 else 0
            in_lo = 0
        else:
            in_lo = t
            in_hi = t + 1 if t < w1 else t
        for row in range(in_lo, in_hi):
            g = np.uint64(b0 + row * g_row)
            cb = np.uint64((row & mask) * pitch)
            for k in range(np.uint64(0), np.uint64(row_len)):
                x = sm[g + k]
                y = sq[g + k]
                M[cb + k] = x
                Q[cb + k] = y
                CC[cb + k] = y / x
            # the cells just outside the window keep their m: diffusion reads it there
            if along:
                DM[cb + w0] = M[cb + w0]
                DM[cb + w1 - 1] = M[cb + w1 - 1]
            elif row == w0 or row == w1 - 1:
                for k in range(np.uint64(0), np.uint64(row_len)):
                    DM[cb + k] = M[cb + k]
        if along:
            stage = t - 1
            task_lo = max(lo1 - r0, 0) if 0 <= stage < n_stages else 0
            task_hi = min(hi1 - r0, nl) if 0 <= stage < n_stages else 0
        else:
            task_lo = 0
            task_hi = n_stages
        for task in range(task_lo, task_hi):
            if along:
                face = stage % 2 == 0
                bc = np.uint64(task * n2)
                bl = bc - one
                bu = bc + one
                gb = np.uint64(b0 + task * n2)
                k_lo = np.uint64(w0 if face else c_lo)
                k_hi = np.uint64(f_hi + 1 if face else c_hi + 1)
                rpos = np.uint64(0)
            else:
                stage = task
                p = t - 1 - stage
                face = stage % 2 == 0
                if p < (w0 if face else c_lo) or p > (f_hi if face else c_hi):
                    continue
                bc = np.uint64((p & mask) * pitch)
                bl = np.uint64(((p - 1) & mask) * pitch)
                bu = np.uint64(((p + 1) & mask) * pitch)
                gb = np.uint64(b0 + p * g_row)
                k_lo = np.uint64(line_lo)
                k_hi = np.uint64(line_hi + 1)
                rpos = np.uint64(p)
            gs = np.uint64(g_step)
            if stage == 0:
                # F1: sigma and A of each face; a face touching the outermost layer or a
                # wall is closed, and nothing leaves an empty upwind cell
                for k in range(k_lo, k_hi):
                    c = bc + k
                    u = bu + k
                    g = gb + k
                    pos = k if along else rpos
                    ok = (pos >= one) & (pos <= pos_hi) & (vessel[g] != 0) & (vessel[g + gs] != 0)
                    sg = 0.5 * (v[g] + v[g + gs]) * cfl
                    m_c = M[c]
                    m_u = M[u]
                    fwd = sg > 0.0
                    m_up = m_c if fwd else m_u
                    m_dn = m_u if fwd else m_c
                    moving = ok & (sg != 0.0) & (m_up > tiny)
                    S[c] = sg if moving else 0.0
                    A[c] = 0.5 * sg * (1.0 - abs(sg)) * (m_dn - m_up) if moving else 0.0
                if n_diff_sub > 0:
                    for k in range(k_lo, k_hi):
                        c = bc + k
                        g = gb + k
                        pos = k if along else rpos
                        ok = (
                            (pos >= one)
                            & (pos <= pos_hi)
                            & (vessel[g] != 0)
                            & (vessel[g + gs] != 0)
                        )
                        OP[c] = 1.0 if ok else 0.0
                        DF[c] = 0.5 * (dif[g] + dif[g + gs])
            elif stage == 1:
                # C2: donor-cell m and the Zalesak ratios (gain, loss, loss through a face
                # the cell is upwind of, which also keeps FV_MASS_MARGIN of m)
                for k in range(k_lo, k_hi):
                    c = bc + k
                    lf = bl + k
                    u = bu + k
                    s_l = S[lf]
                    s_r = S[c]
                    a_l = A[lf]
                    a_r = A[c]
                    m_l = M[lf]
                    m_c = M[c]
                    m_r = M[u]
                    m_low = (
                        m_c + s_l * (m_l if s_l > 0.0 else m_c) - s_r * (m_c if s_r > 0.0 else m_r)
                    )
                    m_top = max(max(m_l, m_c), max(m_r, m_low))
                    m_bot = min(min(m_l, m_c), min(m_r, m_low))
                    out_low = (s_r * m_c if s_r > 0.0 else 0.0) - (s_l * m_c if s_l < 0.0 else 0.0)
                    gain = (a_l if a_l > 0.0 else 0.0) - (a_r if a_r < 0.0 else 0.0)
                    loss = (0.0 - a_l if a_l < 0.0 else 0.0) + (a_r if a_r > 0.0 else 0.0)
                    loss_up = (0.0 - a_l if (a_l < 0.0) & (s_l < 0.0) else 0.0) + (
                        a_r if (a_r > 0.0) & (s_r > 0.0) else 0.0
                    )
                    r_loss = _ratio(m_low - m_bot, loss)
                    R1[c] = _ratio(m_top - m_low, gain)
                    R2[c] = r_loss
                    R3[c] = min(r_loss, _ratio(max(0.0, keep * m_c - out_low), loss_up))
            elif stage == 2:
                # F3: limited m flux = donor cell + coefficient x A; the losing side uses
                # its upwind ratio if the face is one it is upwind of
                for k in range(k_lo, k_hi):
                    c = bc + k
                    u = bu + k
                    sg = S[c]
                    a = A[c]
                    m_c = M[c]
                    m_u = M[u]
                    gain_c, loss_c, lup_c = R1[c], R2[c], R3[c]
                    gain_u, loss_u, lup_u = R1[u], R2[u], R3[u]
                    donor = sg * (m_c if sg > 0.0 else m_u)
                    c_pos = min(gain_u, lup_c if sg > 0.0 else loss_c)
                    c_neg = min(gain_c, lup_u if sg < 0.0 else loss_u)
                    coef = c_pos if a > 0.0 else (c_neg if a < 0.0 else 0.0)
                    A[c] = donor + coef * a if sg != 0.0 else 0.0
            elif stage == 3:
                # C4: new m; colours leaving through the lower (R1) and upper (R2) face
                # from the MC-limited slope, scaled so the staying material stays in range
                for k in range(k_lo, k_hi):
                    c = bc + k
                    lf = bl + k
                    u = bu + k
                    f_l = A[lf]
                    f_r = A[c]
                    s_l = S[lf]
                    s_r = S[c]
                    m_l = M[lf]
                    m_c = M[c]
                    m_r = M[u]
                    DM[c] = m_c + f_l - f_r
                    c_c = CC[c]
                    c_l = CC[lf]
                    c_r = CC[u]
                    has_l = m_l > tiny
                    has_r = m_r > tiny
                    d_lo = c_c - c_l if has_l else 0.0
                    d_hi = c_r - c_c if has_r else 0.0
                    cmax = max(c_c, c_l) if has_l else c_c
                    cmin = min(c_c, c_l) if has_l else c_c
                    cmax = max(cmax, c_r) if has_r else cmax
                    cmin = min(cmin, c_r) if has_r else cmin
                    mag = min(2.0 * min(abs(d_lo), abs(d_hi)), 0.5 * abs(d_lo + d_hi))
                    slope = 0.0 if d_lo * d_hi <= 0.0 else (mag if d_lo > 0.0 else -mag)
                    o_r = f_r if s_r > 0.0 else 0.0
                    o_l = -f_l if s_l < 0.0 else 0.0
                    h_r = 0.5 * (1.0 - o_r / m_c)
                    h_l = 0.5 * (1.0 - o_l / m_c)
                    x = slope * (o_r * h_r - o_l * h_l)
                    stay = m_c - o_r - o_l
                    # one division for both signs of x
                    num = stay * (c_c - cmin) if x > 0.0 else stay * (cmax - c_c)
                    den = x if x > 0.0 else -x
                    alpha = max(0.0, min(1.0, num / den) if x != 0.0 else 1.0)
                    level = slope == 0.0
                    R1[c] = c_c if level else c_c - h_l * alpha * slope
                    R2[c] = c_c if level else c_c + h_r * alpha * slope
            elif stage == 4:
                # F5: species flux, the m flux times the colour its upwind cell sends
                for k in range(k_lo, k_hi):
                    c = bc + k
                    u = bu + k
                    sg = S[c]
                    f = A[c]
                    up = f * R2[c]
                    dn = f * R1[u]
                    R3[c] = up if sg > 0.0 else (dn if sg < 0.0 else 0.0)
            elif stage == 5:
                # C6: new q; c for diffusion (only cells with m > FV_M_TINY carry colour)
                for k in range(k_lo, k_hi):
                    c = bc + k
                    lf = bl + k
                    qn = Q[c] + R3[lf] - R3[c]
                    DQ[c] = qn
                    mn = DM[c]
                    S[c] = qn / mn if mn > tiny else 0.0
            elif face:
                # F7: diffusive flux D_f m_f (c_R - c_L), m_f = min of the two new m
                for k in range(k_lo, k_hi):
                    c = bc + k
                    u = bu + k
                    mf = min(DM[c], DM[u])
                    gf = DF[c] * mf * (S[u] - S[c])
                    A[c] = gf if (OP[c] != 0.0) & (mf > tiny) else 0.0
            else:
                # C8: one diffusion sub-step of q (cells without material keep theirs)
                for k in range(k_lo, k_hi):
                    c = bc + k
                    lf = bl + k
                    mn = DM[c]
                    qo = DQ[c]
                    qn = qo + kdiff * (A[c] - A[lf])
                    qn = qn if mn > 0.0 else qo
                    DQ[c] = qn
                    S[c] = qn / mn if mn > tiny else 0.0
        # write rows out: updated cells from the new fields, the others unchanged
        if along:
            out_lo = 0
            out_hi = nl if t == n_t - 1 else 0
        else:
            out_lo = t - 1 - n_stages
            out_hi = out_lo + 1 if out_lo >= w0 else out_lo
        for row in range(out_lo, out_hi):
            g = np.uint64(b0 + row * g_row)
            cb = np.uint64((row & mask) * pitch)
            row_ok = (lo1 <= r0 + row < hi1) if along else (c_lo <= row <= c_hi)
            for k in range(np.uint64(0), np.uint64(row_len)):
                new = row_ok & (VALID[k] != 0.0)
                dm[g + k] = DM[cb + k] if new else M[cb + k]
                dq[g + k] = DQ[cb + k] if new else Q[cb + k]


@njit(**_JIT)
def _fv_sweep(
    sm, sq, dm, dq, pool, v, dif, vessel, n0, n1, n2, lo0, hi0, lo1, hi1,
    axis, cfl, kdiff, n_diff_sub, width, ring, n_workers, fstride, copy_through,
):  # fmt: skip
    """One 1-D sweep: ``n_workers`` threads, each with its scratch, take blocks in turn.

    Consecutive blocks go to different workers, so both get a share of every region of
    the grid (material is rarely spread evenly) and neighbouring blocks, which share
    cache lines and pages, are worked on at about the same time.
    """
    if axis == 0:
        n_items = (n1 * n2 + width - 1) // width
    elif axis == 1:
        n_items = n0 * ((n2 + width - 1) // width)
    else:
        n_items = n0 * ((n1 + width - 1) // width)
    size = _FV_FIELDS * fstride
    for wk in prange(n_workers):
        scr = pool[wk * size : (wk + 1) * size].reshape(_FV_FIELDS, fstride)
        for item in range(wk, n_items, n_workers):
            _fv_block(
                sm, sq, dm, dq, scr, v, dif, vessel, n0, n1, n2, lo0, hi0, lo1, hi1,
                axis, cfl, kdiff, n_diff_sub, width, ring, item, copy_through,
            )  # fmt: skip


def _fv_plan(n0, n1, n2, axis, n_diff_sub):
    """Block width, ring depth, workers and scratch field size of one sweep."""
    threads = get_num_threads()
    cells_max = _FV_BLOCK_BYTES // (8 * _FV_FIELDS)
    if axis == 2:
        ring = 1
        # a few lines per block: blocks of empty lines are skipped, and the window of
        # positions holding material (see _fv_block) stays tight
        width = max(1, min(n1, cells_max // n2, 8))
        if n0 * -(-n1 // width) < 4 * threads:
            # few planes (2-D): smaller blocks, so that every thread gets some
            width = max(1, min(width, -(-n0 * n1 // (4 * threads))))
        n_items = n0 * -(-n1 // width)
        cells = width * n2
    else:
        # rows alive in the wavefront: read-in to write-out spans n_stages + 2 rows
        ring = 1 << (6 + 2 * n_diff_sub + 1).bit_length()
        n_lines, planes = (n1 * n2, 1) if axis == 0 else (n2, n0)
        width = max(8, cells_max // ring // 8 * 8)
        if planes * -(-n_lines // width) < 4 * threads:
            width = max(8, -(-planes * n_lines // (4 * threads * 8)) * 8)
        width = min(width, n_lines)
        n_items = planes * -(-n_lines // width)
        cells = ring * width
    # padding between fields: field starts that differ by a multiple of 4 KiB would
    # compete for the same cache sets
    fstride = -(-cells // 8) * 8 + 8
    return width, ring, max(1, min(threads, n_items)), fstride


def _flat(a):
    if not a.flags.c_contiguous:
        raise ValueError("the finite-volume kernels need C-contiguous arrays")
    return a.reshape(-1)


def _fv_step(src, out, work, sweeps, dt, n_diff_sub, in_place):
    """Run the sweeps ``(axis, shape3, valid ranges, velocity, diffusivity, h)``."""
    w = _flat(work).reshape(FV_WORK_FIELDS, -1)
    # (m, q) in -> ... -> out, through fields 0 and 1 of work; fields 2.. are the pool.
    # In place every sweep reads and writes (m, q): each block of lines is read into its
    # thread's scratch before any of it is written back, and blocks share no cells
    n = len(sweeps)
    if in_place:
        stops = [src] * (n + 1)
    else:
        middle = [(w[0], w[1]) if (n - 1 - s) % 2 == 0 else out for s in range(1, n)]
        stops = [src] + middle + [out]
    pool = w[2:].reshape(-1)
    for s, (axis, (n0, n1, n2), ranges, v, dif, vessel, h) in enumerate(sweeps):
        width, ring, n_workers, fstride = _fv_plan(n0, n1, n2, axis, n_diff_sub)
        need = n_workers * _FV_FIELDS * fstride
        scratch = pool if need <= pool.size else np.empty(need)
        kdiff = dt / max(n_diff_sub, 1) / (h * h)
        _fv_sweep(
            *stops[s], *stops[s + 1], scratch, v, dif, vessel, n0, n1, n2, *ranges,
            axis, dt / h, kdiff, n_diff_sub, width, ring, n_workers, fstride, not in_place,
        )  # fmt: skip


def _in_place(m, q, m_out, q_out):
    """Whether a step writes its input (``m_out`` is ``m`` and ``q_out`` is ``q``)."""
    same = m_out is m, q_out is q
    if same[0] != same[1]:
        raise ValueError("m and q are updated in place together or not at all")
    if not same[0] and any(np.may_share_memory(a, b) for a in (m, q) for b in (m_out, q_out)):
        raise ValueError(
            "the output arrays overlap the input: pass the same arrays to update in place"
        )
    return same[0]


def fv_step_3d(
    m, q, m_out, q_out, work, vx, vy, vz, dxx, dyy, dzz, vessel, dt, dx, dy, dz, reverse, n_diff_sub
):
    """One step of the conservative bounded finite-volume scheme in 3-D.

    Transports the material volume fraction ``m`` and the species content ``q = m c`` in
    flux form, so ``sum(m)`` and ``sum(q)`` are conserved to round-off, and keeps
    ``c = q / m`` within the range of each cell and its neighbours without clipping, also
    where ``m`` is tiny and where the velocity field is not divergence-free.

    Splitting: one 1-D sweep per axis, x, y, z when ``reverse`` is False and z, y, x when
    True (plain dimension splitting within a step); alternating ``reverse`` between steps
    makes each pair of steps second-order. Each sweep advects (m, q) along its axis and
    then diffuses the species along the same axis with ``n_diff_sub`` explicit sub-steps
    of ``dt / n_diff_sub`` (none when ``n_diff_sub == 0``).

    Mass: the face velocity is the mean of the two adjacent cell velocities, zero where
    either cell is outside the vessel or in the outermost layer, and nothing leaves an
    empty upwind cell. The m flux is donor cell plus the Lax-Wendroff antidiffusion
    limited by Zalesak flux-corrected transport: the new m stays within the range of the
    cell, its neighbours and its donor-cell value, and antidiffusion may not raise a
    cell's outflow above ``(1 - FV_MASS_MARGIN) m`` (nor above the donor-cell outflow if
    that is larger). Every flux keeps the sign of the face velocity.

    Species: the species flux is the m flux times the colour of the leaving slab, from an
    MC-limited linear reconstruction of c in the upwind cell (``c +- (1 - nu) s / 2``,
    ``nu`` the share of the cell's m leaving through the face), with the slope scaled down
    where needed so that the material staying behind keeps a colour in range. Why
    bounded: a cell's outflow never exceeds its content (donor-cell outflow
    ``<= (|sigma_lo| + |sigma_hi|) m <= m`` for per-face Courant ``<= 1/2``, and the limiter
    adds at most up to ``(1 - FV_MASS_MARGIN) m``), so the new ``m c`` is the staying
    material (colour in range by the slope scaling) plus inflows whose colours lie
    between the two cells' colours (MC): a convex combination, with positive weights only,
    so it is also free of cancellation where ``m`` is small. The m limiter never looks
    at q, and the colour reconstruction is odd in c, so swapping the colours
    (``q -> m - q``) gives ``m - q`` to round-off; a constant c stays constant.

    Diffusion of the species uses the flux ``-D_f m_f (c_R - c_L) / h`` with ``D_f`` the
    arithmetic mean and ``m_f = min(m_L, m_R)`` (zero through walls and into empty
    cells); since ``m_f <= m_i`` each sub-step is a convex combination of neighbouring c
    as long as ``D dt_sub / h**2 <= 1/2``.

    ``work`` (``FV_WORK_FIELDS`` fields) holds (m, q) between sweeps in fields 0-1 and each
    thread's scratch in the rest (see the notes above :func:`_fv_block`). All arrays must be
    C-contiguous.

    Parameters
    ----------
    m, q : ndarray, shape (nx, ny, nz)
        Material volume fraction and species content ``m c`` at step n (not modified,
        unless the step is in place).
    m_out, q_out : ndarray, shape (nx, ny, nz)
        Receive m and q at step n + 1: other arrays, or ``m`` and ``q`` themselves (in
        place: the cells no sweep updates are then never touched, which saves copying
        them three times a step).
    work : ndarray, shape (FV_WORK_FIELDS, nx, ny, nz)
        Scratch array from :func:`fv_workspace`.
    vx, vy, vz : ndarray, shape (nx, ny, nz)
        Cell-centred velocity components (m/s); need not be divergence-free.
    dxx, dyy, dzz : ndarray, shape (nx, ny, nz)
        Diagonal species diffusivities (m^2/s).
    vessel : ndarray of uint8, shape (nx, ny, nz)
        1 inside the vessel; faces touching a 0 cell carry no flux.
    dt, dx, dy, dz : float
        Time step (s) and grid spacing (m). Requires per-face ``|u_f| dt / h <= 1/2``
        (see ``blendxr.ade.stability.finite_volume_max_dt``).
    reverse : bool
        Sweep order z, y, x instead of x, y, z.
    n_diff_sub : int
        Number of explicit diffusion sub-steps per sweep (0 skips diffusion); each needs
        ``D dt / (n_diff_sub h**2) <= 1/2`` (see ``blendxr.ade.stability.diffusion_substeps``).
    """
    nx, ny, nz = m.shape
    shape = (nx, ny, nz)
    ranges = (1, nx - 1, 1, ny - 1)
    ves = _flat(vessel)
    sweeps = [
        (0, shape, ranges, _flat(vx), _flat(dxx), ves, dx),
        (1, shape, ranges, _flat(vy), _flat(dyy), ves, dy),
        (2, shape, ranges, _flat(vz), _flat(dzz), ves, dz),
    ]
    if reverse:
        sweeps.reverse()
    _fv_step(
        (_flat(m), _flat(q)), (_flat(m_out), _flat(q_out)), work, sweeps, dt, n_diff_sub,
        _in_place(m, q, m_out, q_out),
    )  # fmt: skip


def fv_step_2d(m, q, m_out, q_out, work, vx, vy, dxx, dyy, vessel, dt, dx, dy, reverse, n_diff_sub):
    """One step of the conservative bounded finite-volume scheme in 2-D.

    Same scheme as :func:`fv_step_3d` with sweeps x, y (``reverse``: y, x); z is never
    touched.

    Parameters
    ----------
    m, q : ndarray, shape (nx, ny)
        Material volume fraction and species content ``m c`` at step n (not modified,
        unless the step is in place).
    m_out, q_out : ndarray, shape (nx, ny)
        Receive m and q at step n + 1, or are ``m`` and ``q`` themselves (in place).
    work : ndarray, shape (FV_WORK_FIELDS, nx, ny)
        Scratch array from :func:`fv_workspace`.
    vx, vy : ndarray, shape (nx, ny)
        Cell-centred velocity components (m/s); need not be divergence-free.
    dxx, dyy : ndarray, shape (nx, ny)
        Diagonal species diffusivities (m^2/s).
    vessel : ndarray of uint8, shape (nx, ny)
        1 inside the vessel; faces touching a 0 cell carry no flux.
    dt, dx, dy : float
        Time step (s) and grid spacing (m). Requires per-face ``|u_f| dt / h <= 1/2``.
    reverse : bool
        Sweep order y, x instead of x, y.
    n_diff_sub : int
        Number of explicit diffusion sub-steps per sweep (0 skips diffusion).
    """
    nx, ny = m.shape
    ves = _flat(vessel)
    # x sweeps across lines of a (nx, 1, ny) grid, y sweeps along the lines of (1, nx, ny)
    sweeps = [
        (0, (nx, 1, ny), (1, nx - 1, 0, 1), _flat(vx), _flat(dxx), ves, dx),
        (2, (1, nx, ny), (0, 1, 1, nx - 1), _flat(vy), _flat(dyy), ves, dy),
    ]
    if reverse:
        sweeps.reverse()
    _fv_step(
        (_flat(m), _flat(q)), (_flat(m_out), _flat(q_out)), work, sweeps, dt, n_diff_sub,
        _in_place(m, q, m_out, q_out),
    )  # fmt: skip


@njit(**_JIT_INLINE)
def _transport_value(va, vb, w, a, j, b, jm, jp, dt, span, cap):
    u = _mix(va[a, j, b], vb[a, j, b], w)
    up = _mix(va[a, jp, b], vb[a, jp, b], w)
    um = _mix(va[a, jm, b], vb[a, jm, b], w)
    factor = 1.0 - 0.5 * dt * (up - um) / span
    return u * min(max(factor, 0.0), cap)


@njit(**_JIT)
def _transport_velocity(va, vb, w, out, dt, h, cap):
    # Every axis streams through the arrays in memory order: along the last axis each
    # thread takes whole lines; otherwise (a, j) pairs, each with its contiguous b run
    # (a loop over j outside a would stride through all of memory once per j).
    n0, n, n2 = va.shape
    if n2 == 1:
        for a in prange(n0):
            for j in range(n):
                jm = max(j - 1, 0)
                jp = min(j + 1, n - 1)
                span = (jp - jm) * h
                out[a, j, 0] = _transport_value(va, vb, w, a, j, 0, jm, jp, dt, span, cap)
    else:
        for t in prange(n0 * n):
            a = t // n
            j = t - a * n
            jm = max(j - 1, 0)
            jp = min(j + 1, n - 1)
            span = (jp - jm) * h
            for b in range(n2):
                out[a, j, b] = _transport_value(va, vb, w, a, j, b, jm, jp, dt, span, cap)


def fv_transport_velocity(v, out, axis, dt, h, cap, v_b=None, w=0.0):
    """Velocity component ``v`` advanced half a step along its own axis, for the sweeps.

    ``out = v (1 - dt/2 dv/dx_axis)``, central differences (one-sided at the array ends),
    the factor clipped to ``[0, cap]``. In the 1-D sweep m_t + (v m)_x = 0 the
    Lax-Wendroff flux is ``v m - dt/2 v (v m)_x``; the antidiffusive flux of the sweep
    supplies ``-dt/2 v^2 m_x`` and the face velocity ``out`` supplies the
    ``-dt/2 v v_x m`` term that a constant-velocity flux lacks: without it the scheme is
    only first-order in time where the velocity varies along the sweep.

    Parameters
    ----------
    v, out : ndarray
        One velocity component (m/s) and the array receiving the transport velocity, same
        shape, C-contiguous.
    axis : int
        The component's axis.
    dt, h : float
        Time step (s) and spacing along ``axis`` (m).
    cap : float
        Largest factor allowed (>= 1 keeps the face Courant numbers within the limit the
        step was chosen for: pass limit / dt).
    v_b, w : ndarray and float, optional
        The same component of a second phase and the blend weight: the velocity is
        ``v + w (v_b - v)``, formed where it is read (no blended field is written).
    """
    shape = v.shape
    view = (int(np.prod(shape[:axis])), shape[axis], int(np.prod(shape[axis + 1 :])))
    v_b = v if v_b is None else v_b
    _transport_velocity(v.reshape(view), v_b.reshape(view), float(w), out.reshape(view), dt, h, cap)
    return out


@njit(**_JIT)
def fv_support(fill_a, fill_b, w, vessel, least, out):
    """out = 1 where the fill blended at weight ``w`` exceeds ``least`` inside the vessel
    (flat arrays): the cells the finite volumes may move material into."""
    for i in prange(out.size):
        out[i] = 1 if (_mix(fill_a[i], fill_b[i], w) > least) & (vessel[i] != 0) else 0


@njit(**_JIT)
def _concentration_flat(m, q, out, m_min):
    n = m.shape[0]
    for i in prange(n):
        if m[i] > m_min:
            out[i] = q[i] / m[i]
        else:
            out[i] = np.nan


def concentration(m, q, out, m_min):
    """Colour concentration ``c = q / m`` where ``m > m_min``, NaN elsewhere.

    Works on any shape; the arrays are viewed as flat, so they must be C-contiguous.

    Parameters
    ----------
    m, q : ndarray
        Material volume fraction and species content, same shape.
    out : ndarray
        Receives the concentration (same shape, C-contiguous float64).
    m_min : float
        Cells with ``m <= m_min`` hold too little material for a meaningful colour; use at
        least ``FV_M_TINY`` (below it the finite-volume scheme freezes cells and ``q`` may
        have underflowed).

    Returns
    -------
    ndarray
        ``out``.
    """
    if not (m.flags.c_contiguous and q.flags.c_contiguous and out.flags.c_contiguous):
        raise ValueError("concentration needs C-contiguous arrays")
    if m.shape != q.shape or m.shape != out.shape:
        raise ValueError("m, q and out must have the same shape")
    _concentration_flat(m.reshape(-1), q.reshape(-1), out.reshape(-1), float(m_min))
    return out


# ---------------------------------------------------------------------------------------
# Flow-field blending in time and the stable time step (run once per refresh / interval)
# ---------------------------------------------------------------------------------------


@njit(**_JIT)
def lerp_into(out, a, b, w):
    """out = a + w (b - a) on flat (1-D) arrays: linear interpolation between two phases."""
    for i in prange(out.size):
        out[i] = a[i] + w * (b[i] - a[i])


@njit(**_JIT_SCALAR)
def _limit_from_bounds(a1, a23, b2):
    """Lax-Wendroff dt limit from sum |nu|/dt, sum |nu|^(2/3)/dt^(2/3) and 2 sum mu/dt."""
    low = np.inf
    if a23 > 0.0:
        low = a23**-1.5
    denom = b2 + np.sqrt(b2 * b2 + 4.0 * a1 * a1)
    if denom > 0.0:
        low = min(low, 2.0 / denom)
    return low


# The powers of the |nu|**(2/3) law are most of the cost of the pair limits. A cell's
# (sum_k s_k**(2/3))**-1.5 is at least n**-1.5 / max_k s_k (n axes, all s_k at their
# largest), so a cell whose quadratic limit and that bound both reach the running minimum
# cannot lower it and its powers are skipped; the minimum is the same number. The bounds
# are lowered by 0.1 % so that rounding in the powers can never matter.
_POW_BOUND_3D = 0.999 * 3.0**-1.5
_POW_BOUND_2D = 0.999 * 2.0**-1.5


@njit(**_JIT_SCALAR)
def _may_bind(a1, smax, b2, pow_bound, low):
    """False when the cell's limit (see :func:`_limit_from_bounds`) cannot be below ``low``."""
    denom = b2 + np.sqrt(b2 * b2 + 4.0 * a1 * a1)
    if denom > 0.0 and 2.0 / denom < low:
        return True
    return pow_bound / smax < low


@njit(**_JIT_SCALAR)
def _lw_pair_cell_3d(vel_a, dif_a, vel_b, dif_b, i, j, k, dx, dy, dz, low):
    """min(low, the pair limit of one cell) for any cell, edges included (3-D)."""
    nx, ny, nz = vel_a.shape[1:]
    gxa = gxb = gya = gyb = gza = gzb = 0.0
    if 0 < i < nx - 1:
        gxa = (dif_a[0, i + 1, j, k] - dif_a[0, i - 1, j, k]) / (2.0 * dx)
        gxb = (dif_b[0, i + 1, j, k] - dif_b[0, i - 1, j, k]) / (2.0 * dx)
    if 0 < j < ny - 1:
        gya = (dif_a[1, i, j + 1, k] - dif_a[1, i, j - 1, k]) / (2.0 * dy)
        gyb = (dif_b[1, i, j + 1, k] - dif_b[1, i, j - 1, k]) / (2.0 * dy)
    if 0 < k < nz - 1:
        gza = (dif_a[2, i, j, k + 1] - dif_a[2, i, j, k - 1]) / (2.0 * dz)
        gzb = (dif_b[2, i, j, k + 1] - dif_b[2, i, j, k - 1]) / (2.0 * dz)
    sx = max(abs(vel_a[0, i, j, k] - gxa), abs(vel_b[0, i, j, k] - gxb)) / dx
    sy = max(abs(vel_a[1, i, j, k] - gya), abs(vel_b[1, i, j, k] - gyb)) / dy
    sz = max(abs(vel_a[2, i, j, k] - gza), abs(vel_b[2, i, j, k] - gzb)) / dz
    b2 = 2.0 * (
        max(dif_a[0, i, j, k], dif_b[0, i, j, k]) / (dx * dx)
        + max(dif_a[1, i, j, k], dif_b[1, i, j, k]) / (dy * dy)
        + max(dif_a[2, i, j, k], dif_b[2, i, j, k]) / (dz * dz)
    )
    if _may_bind(sx + sy + sz, max(sx, max(sy, sz)), b2, _POW_BOUND_3D, low):
        a23 = sx ** (2.0 / 3.0) + sy ** (2.0 / 3.0) + sz ** (2.0 / 3.0)
        low = min(low, _limit_from_bounds(sx + sy + sz, a23, b2))
    return low


@njit(**_JIT_INLINE)
def _row_range(row):
    """(lo, hi): the half-open range of a uint8 row holding its nonzero cells ((n, n): none)."""
    n = row.size
    lo = 0
    while lo < n and row[lo] == 0:
        lo += 1
    if lo == n:
        return n, n
    hi = n
    while row[hi - 1] == 0:
        hi -= 1
    return lo, hi


@njit(**_JIT_INLINE)
def _pair_rows_3d(vel_a, dif_a, vel_b, dif_b, i, j, klo, khi, dx, dy, dz, sx, sy, sz, b2, quad):
    """Along row (i, j), cells klo .. khi - 1 (none on the grid's edge): the bounded
    speeds, 2 sum mu / dt and the quadratic limit of the pair (see
    :func:`lw_max_dt_pair_3d`), in loops of one store each that LLVM vectorises."""
    hx, hy, hz = 2.0 * dx, 2.0 * dy, 2.0 * dz
    ex, ey, ez = dx * dx, dy * dy, dz * dz
    xa, xb = vel_a[0, i, j], vel_b[0, i, j]
    ya, yb = vel_a[1, i, j], vel_b[1, i, j]
    za, zb = vel_a[2, i, j], vel_b[2, i, j]
    pa_p, pa_m = dif_a[0, i + 1, j], dif_a[0, i - 1, j]
    pb_p, pb_m = dif_b[0, i + 1, j], dif_b[0, i - 1, j]
    qa_p, qa_m = dif_a[1, i, j + 1], dif_a[1, i, j - 1]
    qb_p, qb_m = dif_b[1, i, j + 1], dif_b[1, i, j - 1]
    ra, rb = dif_a[2, i, j], dif_b[2, i, j]
    pa, pb, qa, qb = dif_a[0, i, j], dif_b[0, i, j], dif_a[1, i, j], dif_b[1, i, j]
    for k in range(klo, khi):
        ga = (pa_p[k] - pa_m[k]) / hx
        gb = (pb_p[k] - pb_m[k]) / hx
        sx[k] = max(abs(xa[k] - ga), abs(xb[k] - gb)) / dx
    for k in range(klo, khi):
        ga = (qa_p[k] - qa_m[k]) / hy
        gb = (qb_p[k] - qb_m[k]) / hy
        sy[k] = max(abs(ya[k] - ga), abs(yb[k] - gb)) / dy
    for k in range(klo, khi):
        kp = k + _U1
        km = k - _U1
        ga = (ra[kp] - ra[km]) / hz
        gb = (rb[kp] - rb[km]) / hz
        sz[k] = max(abs(za[k] - ga), abs(zb[k] - gb)) / dz
    for k in range(klo, khi):
        xy = max(pa[k], pb[k]) / ex + max(qa[k], qb[k]) / ey
        b2[k] = 2.0 * (xy + max(ra[k], rb[k]) / ez)
    for k in range(klo, khi):
        a1 = sx[k] + sy[k] + sz[k]
        denom = b2[k] + np.sqrt(b2[k] * b2[k] + 4.0 * a1 * a1)
        quad[k] = 2.0 / denom if denom > 0.0 else np.inf


# A cell's power-law limit (sum_k s_k**(2/3))**-1.5 = 1 / ||s||_(2/3) lies between
# 1 / (sqrt(n) ||s||_1) and 1 / ||s||_1 (norm inequalities, n axes), a factor sqrt(3) in
# 3-D: bounds of each cell's limit that need no powers. Both are widened by 0.1 % so that
# rounding in the powers can never matter.
_POW_UPPER_3D = 1.001
_POW_LOWER_3D = 0.999 / np.sqrt(3.0)


@njit(**_JIT)
def _lw_pair_pass_3d(vel_a, dif_a, vel_b, dif_b, material, dx, dy, dz, scratch, threshold,
                     exact, best):  # fmt: skip
    """One pass of :func:`lw_max_dt_pair_3d` over the grid, per plane into ``best``.

    ``exact`` False: an upper bound of the pair limit, the least over material cells of
    min(quadratic limit, :data:`_POW_UPPER_3D` / sum_k s_k) (cells on the grid's edge give
    their exact limit). ``exact`` True: the least exact limit of the cells whose lower
    bound, min(quadratic limit, :data:`_POW_LOWER_3D` / sum_k s_k), does not exceed
    ``threshold`` or the plane's least limit so far; every other cell's limit is above
    the minimum, so this is the pair limit when ``threshold`` is the first pass's bound.
    """
    nx, ny, nz = material.shape
    for i in prange(nx):
        sx, sy, sz = scratch[i, 0], scratch[i, 1], scratch[i, 2]
        b2, quad = scratch[i, 3], scratch[i, 4]
        low = np.inf
        inner_plane = 0 < i < nx - 1
        for j in range(ny):
            row = material[i, j]
            lo, hi = _row_range(row)
            if lo == nz:
                continue
            if not (inner_plane and 0 < j < ny - 1):
                for k in range(lo, hi):
                    if row[k] != 0:
                        low = _lw_pair_cell_3d(vel_a, dif_a, vel_b, dif_b, i, j, k, dx, dy, dz, low)
                continue
            # the grid's first and last cell along z take the per-cell path
            if lo == 0:
                low = _lw_pair_cell_3d(vel_a, dif_a, vel_b, dif_b, i, j, 0, dx, dy, dz, low)
                lo = 1
            if hi == nz:
                if row[nz - 1] != 0:
                    k = nz - 1
                    low = _lw_pair_cell_3d(vel_a, dif_a, vel_b, dif_b, i, j, k, dx, dy, dz, low)
                hi = nz - 1
            if hi <= lo:
                continue
            _pair_rows_3d(vel_a, dif_a, vel_b, dif_b, i, j, np.uint64(lo), np.uint64(hi),
                          dx, dy, dz, sx, sy, sz, b2, quad)  # fmt: skip
            for k in range(lo, hi):
                if row[k] == 0:
                    continue
                a1 = sx[k] + sy[k] + sz[k]
                if not exact:
                    low = min(low, min(quad[k], _POW_UPPER_3D / a1))
                elif min(quad[k], _POW_LOWER_3D / a1) <= min(threshold, low):
                    a23 = sx[k] ** (2.0 / 3.0) + sy[k] ** (2.0 / 3.0) + sz[k] ** (2.0 / 3.0)
                    low = min(low, _limit_from_bounds(a1, a23, b2[k]))
        best[i] = low


@njit(**_JIT_SCALAR)
def lw_max_dt_pair_3d(vel_a, dif_a, vel_b, dif_b, material, dx, dy, dz):
    """Largest Lax-Wendroff dt valid for every blend of two phases (3-D).

    Per material cell and axis the effective speed |v_k - dD_kk/dx_k| / h_k and D_kk / h_k**2
    are bounded by their larger value over the two phases (a blend is a convex combination),
    and the limits of :func:`blendxr.ade.stability.lax_wendroff_max_dt` are applied to those
    bounds: sum_k |nu_k|**(2/3) <= 1 and (sum_k |nu_k|)**2 + 2 sum_k mu_k <= 1.

    The powers of the 2/3 law are most of a cell's cost, so two passes
    (:func:`_lw_pair_pass_3d`): the first bounds the minimum from above without them,
    the second takes them only in the cells whose lower bound reaches that bound (the
    bounds are a factor sqrt(3) apart, so in a smooth flow these are the fastest cells).
    Each cell's limit is made with the same operations as the per-cell formula, so the
    minimum is the same number.

    Parameters
    ----------
    vel_a, dif_a, vel_b, dif_b : ndarray, shape (3, nx, ny, nz)
        Velocity and diffusivity components of the two phases.
    material : ndarray of uint8, shape (nx, ny, nz)
        Cells that constrain dt (material in either phase).
    """
    nx, ny, nz = material.shape
    best = np.full(nx, np.inf)
    # per plane: bounded speeds along x, y, z, 2 sum mu / dt, the quadratic limit
    scratch = np.empty((nx, 5, nz))
    _lw_pair_pass_3d(vel_a, dif_a, vel_b, dif_b, material, dx, dy, dz, scratch, np.inf,
                     False, best)  # fmt: skip
    bound = best.min()
    if not bound < np.inf:
        return bound  # no material, or speeds that are not finite: no step is stable
    _lw_pair_pass_3d(vel_a, dif_a, vel_b, dif_b, material, dx, dy, dz, scratch, bound,
                     True, best)  # fmt: skip
    return best.min()


@njit(**_JIT)
def lw_max_dt_pair_2d(vel_a, dif_a, vel_b, dif_b, material, dx, dy):
    """Largest Lax-Wendroff dt valid for every blend of two phases (2-D); see the 3-D one."""
    nx, ny = material.shape
    best = np.full(nx, np.inf)
    for i in prange(nx):
        low = np.inf
        for j in range(ny):
            if material[i, j] == 0:
                continue
            gxa = gxb = gya = gyb = 0.0
            if 0 < i < nx - 1:
                gxa = (dif_a[0, i + 1, j] - dif_a[0, i - 1, j]) / (2.0 * dx)
                gxb = (dif_b[0, i + 1, j] - dif_b[0, i - 1, j]) / (2.0 * dx)
            if 0 < j < ny - 1:
                gya = (dif_a[1, i, j + 1] - dif_a[1, i, j - 1]) / (2.0 * dy)
                gyb = (dif_b[1, i, j + 1] - dif_b[1, i, j - 1]) / (2.0 * dy)
            sx = max(abs(vel_a[0, i, j] - gxa), abs(vel_b[0, i, j] - gxb)) / dx
            sy = max(abs(vel_a[1, i, j] - gya), abs(vel_b[1, i, j] - gyb)) / dy
            b2 = 2.0 * (
                max(dif_a[0, i, j], dif_b[0, i, j]) / (dx * dx)
                + max(dif_a[1, i, j], dif_b[1, i, j]) / (dy * dy)
            )
            if _may_bind(sx + sy, max(sx, sy), b2, _POW_BOUND_2D, low):
                a23 = sx ** (2.0 / 3.0) + sy ** (2.0 / 3.0)
                low = min(low, _limit_from_bounds(sx + sy, a23, b2))
        best[i] = low
    return best.min()


@njit(**_JIT_INLINE)
def _face_dt(va, vb, comp, flat, nb, h, low):
    """min(low, the Courant-1/2 dt of the face between flat cells ``flat`` and ``nb``)."""
    fa = abs(0.5 * (va[comp, flat] + va[comp, nb]))
    fb = abs(0.5 * (vb[comp, flat] + vb[comp, nb]))
    f = max(fa, fb)
    return min(low, 0.5 * h / f) if f > 0.0 else low


@njit(**_JIT)
def fv_max_dt_pair(vel_a, vel_b, vessel, spacing):
    """Largest finite-volume dt for every blend of two phases: per-face Courant <= 1/2.

    The face velocity (mean of the two cells, zero at a wall) of a blend is bounded by the
    larger of the two phases' face velocities. Works on 2-D or 3-D data: ``vel_*`` have
    shape (ndim, *grid shape), ``vessel`` the grid's shape and ``spacing`` holds h_k per
    axis. A 2-D grid is walked as (nx, 1, ny).
    """
    ndim = vel_a.shape[0]
    shape = vessel.shape
    n0 = shape[0]
    n1 = shape[1] if len(shape) == 3 else 1
    n2 = shape[-1]
    va = vel_a.reshape(ndim, -1)
    vb = vel_b.reshape(ndim, -1)
    ves = vessel.reshape(-1)
    best = np.full(n0, np.inf)
    for i in prange(n0):
        low = np.inf
        for j in range(n1):
            for k in range(n2):
                flat = (i * n1 + j) * n2 + k
                if ves[flat] == 0:
                    continue
                nb = flat + n1 * n2
                if i + 1 < n0 and ves[nb] != 0:
                    low = _face_dt(va, vb, 0, flat, nb, spacing[0], low)
                nb = flat + n2
                if len(shape) == 3 and j + 1 < n1 and ves[nb] != 0:
                    low = _face_dt(va, vb, 1, flat, nb, spacing[1], low)
                nb = flat + 1
                if k + 1 < n2 and ves[nb] != 0:
                    low = _face_dt(va, vb, ndim - 1, flat, nb, spacing[ndim - 1], low)
        best[i] = low
    return best.min()
