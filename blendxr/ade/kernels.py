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
their loops and run ``prange`` over the outermost axis only. The outermost layer of cells
(index 0 and n - 1 on every axis) is never updated: it is copied unchanged.
"""

import numpy as np
from numba import njit, prange

__all__ = [
    "LW_EMPTY",
    "LW_INTERIOR",
    "LW_SURFACE",
    "LaxWendroffPlan",
    "fv_max_dt_pair",
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


@njit(**_JIT_INLINE)
def _interior_2d(material, i, j):
    """True when every cell of the 3x3 box around (i, j) is material."""
    nx, ny = material.shape
    if i < 1 or j < 1 or i > nx - 2 or j > ny - 2:
        return False
    for a in range(i - 1, i + 2):
        for b in range(j - 1, j + 2):
            if material[a, b] == 0:
                return False
    return True


@njit(**_JIT_INLINE)
def _interior_3d(material, i, j, k):
    """True when every cell of the 3x3x3 box around (i, j, k) is material."""
    nx, ny, nz = material.shape
    if i < 1 or j < 1 or k < 1 or i > nx - 2 or j > ny - 2 or k > nz - 2:
        return False
    for a in range(i - 1, i + 2):
        for b in range(j - 1, j + 2):
            for e in range(k - 1, k + 2):
                if material[a, b, e] == 0:
                    return False
    return True


@njit(**_JIT_SCALAR)
def _normal_offset(n, nmax):
    """Integer step (-1, 0, 1) along one axis of the inward normal component ``n``."""
    if abs(n) >= 0.5 * nmax and n != 0.0:
        return 1 if n > 0.0 else -1
    return 0


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


@njit(**_JIT)
def lw_coefficients_2d(vx, vy, dxx, dyy, cls, dt, dx, dy, coef):
    """Per-cell coefficients of eq. (6) for interior cells (2-D).

    ``coef[0:2]`` = nu_k = (v_k - dD_kk/dx_k) dt / h_k (eq. 7-8 as they should read: the
    effective velocity of eq. 4, gradient by central differences, eq. 22-23) and
    ``coef[2:4]`` = nu_k**2 / 2 + mu_k with mu_k = D_kk dt / h_k**2 (eq. 10-11).
    Other cells are left as they are (never read).
    """
    nx, ny = cls.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            if cls[i, j] != LW_INTERIOR:
                continue
            nux = (vx[i, j] - (dxx[i + 1, j] - dxx[i - 1, j]) / (2.0 * dx)) * dt / dx
            nuy = (vy[i, j] - (dyy[i, j + 1] - dyy[i, j - 1]) / (2.0 * dy)) * dt / dy
            coef[0, i, j] = nux
            coef[1, i, j] = nuy
            coef[2, i, j] = 0.5 * nux * nux + dxx[i, j] * dt / (dx * dx)
            coef[3, i, j] = 0.5 * nuy * nuy + dyy[i, j] * dt / (dy * dy)


@njit(**_JIT)
def lw_coefficients_3d(vx, vy, vz, dxx, dyy, dzz, cls, dt, dx, dy, dz, coef):
    """Per-cell coefficients of eq. (6) for interior cells (3-D); see the 2-D version."""
    nx, ny, nz = cls.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            for k in range(1, nz - 1):
                if cls[i, j, k] != LW_INTERIOR:
                    continue
                nux = (vx[i, j, k] - (dxx[i + 1, j, k] - dxx[i - 1, j, k]) / (2.0 * dx)) * dt / dx
                nuy = (vy[i, j, k] - (dyy[i, j + 1, k] - dyy[i, j - 1, k]) / (2.0 * dy)) * dt / dy
                nuz = (vz[i, j, k] - (dzz[i, j, k + 1] - dzz[i, j, k - 1]) / (2.0 * dz)) * dt / dz
                coef[0, i, j, k] = nux
                coef[1, i, j, k] = nuy
                coef[2, i, j, k] = nuz
                coef[3, i, j, k] = 0.5 * nux * nux + dxx[i, j, k] * dt / (dx * dx)
                coef[4, i, j, k] = 0.5 * nuy * nuy + dyy[i, j, k] * dt / (dy * dy)
                coef[5, i, j, k] = 0.5 * nuz * nuz + dzz[i, j, k] * dt / (dz * dz)


@njit(**_JIT)
def lw_apply_2d(c, out, coef, cls, rows):
    """The Lax-Wendroff stencil on interior cells only (2-D).

    ``out = c - sum_k [nu_k D0_k c - A_k d2_k c] + nu_x nu_y D0_x D0_y c``, clipped to
    [0, 1]. Cells that are not interior are not written: the caller keeps them equal in
    both buffers (surface cells are set by :func:`lw_surface_2d` every step).
    """
    nx, ny = c.shape
    for i in prange(1, nx - 1):
        for j in range(max(rows[i, 0], 1), min(rows[i, 1], ny - 1)):
            if cls[i, j] != LW_INTERIOR:
                continue
            c0 = c[i, j]
            nux = coef[0, i, j]
            nuy = coef[1, i, j]
            val = (
                c0
                - nux * 0.5 * (c[i + 1, j] - c[i - 1, j])
                + coef[2, i, j] * (c[i + 1, j] - 2.0 * c0 + c[i - 1, j])
                - nuy * 0.5 * (c[i, j + 1] - c[i, j - 1])
                + coef[3, i, j] * (c[i, j + 1] - 2.0 * c0 + c[i, j - 1])
                + nux
                * nuy
                * 0.25
                * (c[i + 1, j + 1] - c[i - 1, j + 1] - c[i + 1, j - 1] + c[i - 1, j - 1])
            )
            out[i, j] = min(1.0, max(0.0, val))


@njit(**_JIT)
def lw_apply_3d(c, out, coef, cls, rows):
    """The Lax-Wendroff stencil on interior cells only (3-D); see the 2-D version.

    Adds the three cross terms nu_x nu_y D0_x D0_y c, nu_y nu_z D0_y D0_z c and
    nu_z nu_x D0_z D0_x c of eq. (6), (19)-(21).
    """
    nx, ny, nz = c.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            for k in range(max(rows[i, j, 0], 1), min(rows[i, j, 1], nz - 1)):
                if cls[i, j, k] != LW_INTERIOR:
                    continue
                c0 = c[i, j, k]
                nux = coef[0, i, j, k]
                nuy = coef[1, i, j, k]
                nuz = coef[2, i, j, k]
                xp = c[i + 1, j, k]
                xm = c[i - 1, j, k]
                yp = c[i, j + 1, k]
                ym = c[i, j - 1, k]
                zp = c[i, j, k + 1]
                zm = c[i, j, k - 1]
                dxy = (
                    c[i + 1, j + 1, k]
                    - c[i - 1, j + 1, k]
                    - c[i + 1, j - 1, k]
                    + c[i - 1, j - 1, k]
                )
                dyz = (
                    c[i, j + 1, k + 1]
                    - c[i, j - 1, k + 1]
                    - c[i, j + 1, k - 1]
                    + c[i, j - 1, k - 1]
                )
                dzx = (
                    c[i + 1, j, k + 1]
                    - c[i - 1, j, k + 1]
                    - c[i + 1, j, k - 1]
                    + c[i - 1, j, k - 1]
                )
                val = (
                    c0
                    - 0.5 * (nux * (xp - xm) + nuy * (yp - ym) + nuz * (zp - zm))
                    + coef[3, i, j, k] * (xp - 2.0 * c0 + xm)
                    + coef[4, i, j, k] * (yp - 2.0 * c0 + ym)
                    + coef[5, i, j, k] * (zp - 2.0 * c0 + zm)
                    + 0.25 * (nux * nuy * dxy + nuy * nuz * dyz + nuz * nux * dzx)
                )
                out[i, j, k] = min(1.0, max(0.0, val))


@njit(**_JIT)
def lw_surface_2d(out, cls, rows, fill):
    """Free-surface rule of the paper in 2-D, applied in place to ``out``.

    Every surface cell takes the value of ``out`` at the cell one step inward along the
    surface normal ``n = grad(fill)`` (central differences in index space; the step along
    axis k is ``sign(n_k)`` where ``|n_k| >= max_k |n_k| / 2``, else 0). If that cell is
    not interior, the mean of the interior cells of the box is used; if there are none,
    the value is kept. Only interior cells are read and only surface cells written, so
    the parallel pass is free of races.
    """
    nx, ny = out.shape
    for i in prange(1, nx - 1):
        for j in range(max(rows[i, 0], 1), min(rows[i, 1], ny - 1)):
            if cls[i, j] != LW_SURFACE:
                continue
            nxv = 0.5 * (fill[i + 1, j] - fill[i - 1, j])
            nyv = 0.5 * (fill[i, j + 1] - fill[i, j - 1])
            nmax = max(abs(nxv), abs(nyv))
            ti = i + _normal_offset(nxv, nmax)
            tj = j + _normal_offset(nyv, nmax)
            if cls[ti, tj] == LW_INTERIOR:
                out[i, j] = out[ti, tj]
                continue
            total = 0.0
            count = 0
            for a in range(i - 1, i + 2):
                for b in range(j - 1, j + 2):
                    if cls[a, b] == LW_INTERIOR:
                        total += out[a, b]
                        count += 1
            if count > 0:
                out[i, j] = total / count


@njit(**_JIT)
def lw_surface_3d(out, cls, rows, fill):
    """Free-surface rule of the paper in 3-D; see :func:`lw_surface_2d`."""
    nx, ny, nz = out.shape
    for i in prange(1, nx - 1):
        for j in range(1, ny - 1):
            for k in range(max(rows[i, j, 0], 1), min(rows[i, j, 1], nz - 1)):
                if cls[i, j, k] != LW_SURFACE:
                    continue
                nxv = 0.5 * (fill[i + 1, j, k] - fill[i - 1, j, k])
                nyv = 0.5 * (fill[i, j + 1, k] - fill[i, j - 1, k])
                nzv = 0.5 * (fill[i, j, k + 1] - fill[i, j, k - 1])
                nmax = max(abs(nxv), max(abs(nyv), abs(nzv)))
                ti = i + _normal_offset(nxv, nmax)
                tj = j + _normal_offset(nyv, nmax)
                tk = k + _normal_offset(nzv, nmax)
                if cls[ti, tj, tk] == LW_INTERIOR:
                    out[i, j, k] = out[ti, tj, tk]
                    continue
                total = 0.0
                count = 0
                for a in range(i - 1, i + 2):
                    for b in range(j - 1, j + 2):
                        for e in range(k - 1, k + 2):
                            if cls[a, b, e] == LW_INTERIOR:
                                total += out[a, b, e]
                                count += 1
                if count > 0:
                    out[i, j, k] = total / count


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

    def classify(self, material):
        """Mark interior, surface and empty cells from a material mask."""
        classify = lw_classify_3d if self.ndim == 3 else lw_classify_2d
        classify(material, self.cls, self.rows, self.scratch)

    def coefficients(self, velocities, diffusivities, dt, spacing):
        """Fold the fields and dt into the per-cell coefficients (after :meth:`classify`)."""
        if self.ndim == 3:
            lw_coefficients_3d(*velocities, *diffusivities, self.cls, dt, *spacing, self.coef)
        else:
            lw_coefficients_2d(*velocities, *diffusivities, self.cls, dt, *spacing, self.coef)

    def apply(self, c, out):
        """One step of the stencil on interior cells, ``c`` -> ``out``."""
        (lw_apply_3d if self.ndim == 3 else lw_apply_2d)(c, out, self.coef, self.cls, self.rows)

    def surface(self, out, fill):
        """The free-surface copy, in place on ``out``."""
        (lw_surface_3d if self.ndim == 3 else lw_surface_2d)(out, self.cls, self.rows, fill)

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


@njit(**_JIT_SCALAR)
def _ratio(g, p):
    """Zalesak ratio: the share of the harmful antidiffusion ``p`` the slack ``g`` allows."""
    if p <= 0.0:
        return 1.0
    return max(0.0, min(1.0, g / p))


@njit(**_JIT_SCALAR)
def _face_values(m_l, m_r, sgm):
    """(sigma, A) of an open face with Courant number ``sgm`` (positive towards +axis).

    ``A`` is the Lax-Wendroff flux of m minus the donor-cell flux,
    ``sigma (1 - |sigma|) / 2 (m_dn - m_up)``. Nothing leaves an empty upwind cell, so the
    face is closed (sigma = 0) then (see ``FV_M_TINY``).
    """
    if sgm > 0.0:
        mu, md = m_l, m_r
    else:
        mu, md = m_r, m_l
    if sgm == 0.0 or mu <= FV_M_TINY:
        return 0.0, 0.0
    return sgm, 0.5 * sgm * (1.0 - abs(sgm)) * (md - mu)


@njit(**_JIT_INLINE)
def _face_2d(m, v, vessel, i, j, i2, j2, p, na, cfl):
    """(sigma, A) of the face between (i, j) and (i2, j2), ``p`` its lower index on the axis."""
    if p < 1 or p > na - 3:
        # the face touches the outermost layer, which never exchanges
        return 0.0, 0.0
    if vessel[i, j] == 0 or vessel[i2, j2] == 0:
        return 0.0, 0.0
    return _face_values(m[i, j], m[i2, j2], 0.5 * (v[i, j] + v[i2, j2]) * cfl)


@njit(**_JIT_INLINE)
def _face_3d(m, v, vessel, i, j, k, i2, j2, k2, p, na, cfl):
    """(sigma, A) of the face between (i, j, k) and (i2, j2, k2)."""
    if p < 1 or p > na - 3:
        return 0.0, 0.0
    if vessel[i, j, k] == 0 or vessel[i2, j2, k2] == 0:
        return 0.0, 0.0
    return _face_values(m[i, j, k], m[i2, j2, k2], 0.5 * (v[i, j, k] + v[i2, j2, k2]) * cfl)


@njit(**_JIT_SCALAR)
def _donor_flux(m_l, m_r, sgm):
    """Donor-cell flux of m through a face (positive towards +axis)."""
    return sgm * (m_l if sgm > 0.0 else m_r)


@njit(**_JIT_SCALAR)
def _mass_ratios(m_l, m_c, m_r, face_l, face_r):
    """Donor-cell m and the three Zalesak ratios of one cell of a 1-D sweep.

    The cell gains the lower face's flux and loses the upper face's (positive towards
    +axis). Constraints: ``m <= max(m_{i-1}, m_i, m_{i+1}, m_low)`` (ratio for gains),
    ``m >= min(...)`` (ratio for losses) and outflow through the faces the cell is upwind
    of at most ``max(outflow_low, (1 - FV_MASS_MARGIN) m_i)`` (combined with the former
    into the ratio for losses through such faces). Returns
    ``(m_low, r_gain, r_loss, r_loss_upwind)``.
    """
    s_l, a_l = face_l
    s_r, a_r = face_r
    m_low = m_c + _donor_flux(m_l, m_c, s_l) - _donor_flux(m_c, m_r, s_r)
    m_top = max(max(m_l, m_c), max(m_r, m_low))
    m_bot = min(min(m_l, m_c), min(m_r, m_low))
    out_low = 0.0
    if s_r > 0.0:
        out_low += s_r * m_c
    if s_l < 0.0:
        out_low -= s_l * m_c
    gain = 0.0
    loss = 0.0
    loss_up = 0.0
    if a_l > 0.0:
        gain += a_l
    elif a_l < 0.0:
        loss -= a_l
        if s_l < 0.0:
            loss_up -= a_l
    if a_r < 0.0:
        gain -= a_r
    elif a_r > 0.0:
        loss += a_r
        if s_r > 0.0:
            loss_up += a_r
    r_gain = _ratio(m_top - m_low, gain)
    r_loss = _ratio(m_low - m_bot, loss)
    r_out = _ratio(max(0.0, (1.0 - FV_MASS_MARGIN) * m_c - out_low), loss_up)
    return m_low, r_gain, r_loss, min(r_loss, r_out)


@njit(**_JIT_SCALAR)
def _mass_flux(m_l, m_r, face, r_lo, r_hi):
    """Limited m flux of a face between a low-side and a high-side cell.

    ``r_lo``/``r_hi`` are the cells' (r_gain, r_loss, r_loss_upwind). Every harmful
    contribution of the face is its own ``|A|``, so the coefficient moves the flux by no
    more than the round-off of the slack it protects.
    """
    sgm, a = face
    if sgm == 0.0:
        return 0.0
    if a > 0.0:
        # the low side loses, the high side gains
        coef = min(r_hi[0], r_lo[2] if sgm > 0.0 else r_lo[1])
    elif a < 0.0:
        coef = min(r_lo[0], r_hi[2] if sgm < 0.0 else r_hi[1])
    else:
        coef = 0.0
    return _donor_flux(m_l, m_r, sgm) + coef * a


@njit(**_JIT_SCALAR)
def _outflow_colours(m_l, q_l, m_c, q_c, m_r, q_r, s_l, f_l, s_r, f_r):
    """Colours carried out of a cell through its lower and upper faces.

    MC-limited linear reconstruction of c in the cell, averaged over the slab that leaves
    in this sweep (``c_i +- (1 - nu) s / 2`` with ``nu`` the share of the cell's m that
    leaves through the face). The slope is scaled by ``alpha <= 1`` so that the material
    that stays keeps a colour within the range of the cell and its neighbours; together
    with MC (the face colour lies between the two cells' colours) the new c is a convex
    combination of colours in that range. ``f_l``/``f_r`` are the limited m fluxes
    (positive towards +axis); the result is only meaningful for outflow faces.
    """
    c_c = q_c / m_c
    cmax = c_c
    cmin = c_c
    d_lo = 0.0
    d_hi = 0.0
    if m_l > FV_M_TINY:
        c_l = q_l / m_l
        d_lo = c_c - c_l
        cmax = max(cmax, c_l)
        cmin = min(cmin, c_l)
    if m_r > FV_M_TINY:
        c_r = q_r / m_r
        d_hi = c_r - c_c
        cmax = max(cmax, c_r)
        cmin = min(cmin, c_r)
    # MC slope: minmod(2 d_lo, 2 d_hi, (d_lo + d_hi) / 2), odd in (d_lo, d_hi)
    if d_lo * d_hi <= 0.0:
        slope = 0.0
    else:
        mag = min(2.0 * min(abs(d_lo), abs(d_hi)), 0.5 * abs(d_lo + d_hi))
        slope = mag if d_lo > 0.0 else -mag
    if slope == 0.0:
        return c_c, c_c
    o_r = f_r if s_r > 0.0 else 0.0
    o_l = -f_l if s_l < 0.0 else 0.0
    h_r = 0.5 * (1.0 - o_r / m_c)
    h_l = 0.5 * (1.0 - o_l / m_c)
    # colour the leaving slabs take away, relative to c_c, per unit slope
    x = slope * (o_r * h_r - o_l * h_l)
    stay = m_c - o_r - o_l
    alpha = 1.0
    if x > 0.0:
        alpha = min(1.0, stay * (c_c - cmin) / x)
    elif x < 0.0:
        alpha = min(1.0, stay * (cmax - c_c) / -x)
    alpha = max(0.0, alpha)
    return c_c - h_l * alpha * slope, c_c + h_r * alpha * slope


@njit(**_JIT_SCALAR)
def _diffusion_flux(m_l, q_l, m_r, q_r, d_l, d_r):
    """``D_f m_f (c_R - c_L)`` across one open face (zero into empty cells)."""
    mf = min(m_l, m_r)
    if mf <= FV_M_TINY:
        return 0.0
    return 0.5 * (d_l + d_r) * mf * (q_r / m_r - q_l / m_l)


@njit(**_JIT_INLINE)
def _ratios_cell_3d(sm, fq, r_gain, r_loss, r_lup, v, vessel, i, j, k, oi, oj, ok, na, cfl):
    """Phase 0 at one cell: Zalesak ratios of m; clears the species flux of its upper face."""
    nx, ny, nz = sm.shape
    fq[i, j, k] = 0.0
    if i < 1 or j < 1 or k < 1 or i > nx - 2 or j > ny - 2 or k > nz - 2:
        return
    il, jl, kl = i - oi, j - oj, k - ok
    ir, jr, kr = i + oi, j + oj, k + ok
    m_c = sm[i, j, k]
    m_l = sm[il, jl, kl]
    m_r = sm[ir, jr, kr]
    if m_c <= 0.0 and m_l <= 0.0 and m_r <= 0.0:
        return
    p = i * oi + j * oj + k * ok
    face_l = _face_3d(sm, v, vessel, il, jl, kl, i, j, k, p - 1, na, cfl)
    face_r = _face_3d(sm, v, vessel, i, j, k, ir, jr, kr, p, na, cfl)
    res = _mass_ratios(m_l, m_c, m_r, face_l, face_r)
    r_gain[i, j, k] = res[1]
    r_loss[i, j, k] = res[2]
    r_lup[i, j, k] = res[3]


@njit(**_JIT_INLINE)
def _mass_cell_3d(sm, sq, dm, fq, r_gain, r_loss, r_lup, v, vessel, i, j, k, oi, oj, ok, na, cfl):
    """Phase 1 at one cell: limited m fluxes, new m, species flux of its outflow faces.

    Both cells of a face evaluate its m flux from the same data (same bits, so the update
    is in flux form); the species flux is written only by the face's upwind cell.
    """
    nx, ny, nz = sm.shape
    if i < 1 or j < 1 or k < 1 or i > nx - 2 or j > ny - 2 or k > nz - 2:
        dm[i, j, k] = sm[i, j, k]
        return
    il, jl, kl = i - oi, j - oj, k - ok
    ir, jr, kr = i + oi, j + oj, k + ok
    m_c = sm[i, j, k]
    m_l = sm[il, jl, kl]
    m_r = sm[ir, jr, kr]
    if m_c <= 0.0 and m_l <= 0.0 and m_r <= 0.0:
        dm[i, j, k] = m_c
        return
    p = i * oi + j * oj + k * ok
    r_c = (r_gain[i, j, k], r_loss[i, j, k], r_lup[i, j, k])
    face_l = _face_3d(sm, v, vessel, il, jl, kl, i, j, k, p - 1, na, cfl)
    face_r = _face_3d(sm, v, vessel, i, j, k, ir, jr, kr, p, na, cfl)
    f_l = 0.0
    f_r = 0.0
    if face_l[0] != 0.0:
        r_l = (r_gain[il, jl, kl], r_loss[il, jl, kl], r_lup[il, jl, kl])
        f_l = _mass_flux(m_l, m_c, face_l, r_l, r_c)
    if face_r[0] != 0.0:
        r_r = (r_gain[ir, jr, kr], r_loss[ir, jr, kr], r_lup[ir, jr, kr])
        f_r = _mass_flux(m_c, m_r, face_r, r_c, r_r)
    dm[i, j, k] = m_c + f_l - f_r
    if face_r[0] > 0.0 or face_l[0] < 0.0:
        col = _outflow_colours(
            m_l, sq[il, jl, kl], m_c, sq[i, j, k], m_r, sq[ir, jr, kr],
            face_l[0], f_l, face_r[0], f_r,
        )  # fmt: skip
        if face_l[0] < 0.0:
            fq[il, jl, kl] = f_l * col[0]
        if face_r[0] > 0.0:
            fq[i, j, k] = f_r * col[1]


@njit(**_JIT_INLINE)
def _species_cell_3d(sm, sq, fq, q_dst, i, j, k, oi, oj, ok):
    """Phase 2 at one cell: species update from the face fluxes."""
    nx, ny, nz = sm.shape
    if i < 1 or j < 1 or k < 1 or i > nx - 2 or j > ny - 2 or k > nz - 2:
        q_dst[i, j, k] = sq[i, j, k]
        return
    q_dst[i, j, k] = sq[i, j, k] + fq[i - oi, j - oj, k - ok] - fq[i, j, k]


@njit(**_JIT_INLINE)
def _diffuse_cell_3d(m, src, dst, dif, vessel, i, j, k, oi, oj, ok, na, kdiff):
    """One explicit diffusion sub-step of the species at one cell, along one axis."""
    nx, ny, nz = m.shape
    q_c = src[i, j, k]
    m_c = m[i, j, k]
    if m_c <= 0.0 or i < 1 or j < 1 or k < 1 or i > nx - 2 or j > ny - 2 or k > nz - 2:
        dst[i, j, k] = q_c
        return
    p = i * oi + j * oj + k * ok
    flux = 0.0
    if p < na - 2:
        ir, jr, kr = i + oi, j + oj, k + ok
        if vessel[i, j, k] != 0 and vessel[ir, jr, kr] != 0:
            flux += _diffusion_flux(
                m_c, q_c, m[ir, jr, kr], src[ir, jr, kr], dif[i, j, k], dif[ir, jr, kr]
            )
    if p > 1:
        il, jl, kl = i - oi, j - oj, k - ok
        if vessel[i, j, k] != 0 and vessel[il, jl, kl] != 0:
            flux -= _diffusion_flux(
                m[il, jl, kl], src[il, jl, kl], m_c, q_c, dif[il, jl, kl], dif[i, j, k]
            )
    dst[i, j, k] = q_c + kdiff * flux


@njit(**_JIT)
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

    Scratch layout of ``work`` (``FV_WORK_FIELDS`` fields): 0 diffusion buffer, 1-3 Zalesak
    ratios of m (gain, loss, loss through an upwind face), 4 species flux per face
    (stored at the face's lower cell), 5-6 intermediate (m, q) between sweeps.

    Parameters
    ----------
    m, q : ndarray, shape (nx, ny, nz)
        Material volume fraction and species content ``m c`` at step n (not modified).
    m_out, q_out : ndarray, shape (nx, ny, nz)
        Receive m and q at step n + 1.
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
    tq = work[0]
    r_gain = work[1]
    r_loss = work[2]
    r_lup = work[3]
    fq = work[4]
    wm = work[5]
    wq = work[6]
    for sweep in range(3):
        axis = 2 - sweep if reverse else sweep
        if axis == 0:
            v = vx
            dif = dxx
            h = dx
            oi, oj, ok = 1, 0, 0
            na = nx
        elif axis == 1:
            v = vy
            dif = dyy
            h = dy
            oi, oj, ok = 0, 1, 0
            na = ny
        else:
            v = vz
            dif = dzz
            h = dz
            oi, oj, ok = 0, 0, 1
            na = nz
        # buffers: in -> out -> work -> out, so the last sweep lands in the output
        if sweep == 0:
            sm = m
            sq = q
        elif sweep == 1:
            sm = m_out
            sq = q_out
        else:
            sm = wm
            sq = wq
        if sweep == 1:
            dm = wm
            dq = wq
        else:
            dm = m_out
            dq = q_out
        cfl = dt / h
        kdiff = dt / max(n_diff_sub, 1) / (h * h)
        # with an odd number of diffusion sub-steps the advected q goes to the diffusion
        # buffer, so that the ping-pong ends in dq
        q_adv = tq if n_diff_sub % 2 == 1 else dq
        # phase 0: m ratios; 1: m fluxes, new m, species fluxes; 2: new q; 3..: diffusion.
        # All phases share ONE parallel loop: every prange loop is compiled as a separate
        # parallel function, so one loop with a phase switch keeps numba compile time down.
        for phase in range(3 + n_diff_sub):
            if (phase + n_diff_sub) % 2 == 0:
                src = tq
                dst = dq
            else:
                src = dq
                dst = tq
            for i in prange(nx):
                for j in range(ny):
                    for k in range(nz):
                        if phase == 0:
                            _ratios_cell_3d(
                                sm, fq, r_gain, r_loss, r_lup,
                                v, vessel, i, j, k, oi, oj, ok, na, cfl,
                            )  # fmt: skip
                        elif phase == 1:
                            _mass_cell_3d(
                                sm, sq, dm, fq, r_gain, r_loss, r_lup,
                                v, vessel, i, j, k, oi, oj, ok, na, cfl,
                            )  # fmt: skip
                        elif phase == 2:
                            _species_cell_3d(sm, sq, fq, q_adv, i, j, k, oi, oj, ok)
                        else:
                            _diffuse_cell_3d(
                                dm, src, dst, dif, vessel, i, j, k, oi, oj, ok, na, kdiff
                            )


@njit(**_JIT_INLINE)
def _ratios_cell_2d(sm, fq, r_gain, r_loss, r_lup, v, vessel, i, j, oi, oj, na, cfl):
    """2-D twin of :func:`_ratios_cell_3d`."""
    nx, ny = sm.shape
    fq[i, j] = 0.0
    if i < 1 or j < 1 or i > nx - 2 or j > ny - 2:
        return
    il, jl = i - oi, j - oj
    ir, jr = i + oi, j + oj
    m_c = sm[i, j]
    m_l = sm[il, jl]
    m_r = sm[ir, jr]
    if m_c <= 0.0 and m_l <= 0.0 and m_r <= 0.0:
        return
    p = i * oi + j * oj
    face_l = _face_2d(sm, v, vessel, il, jl, i, j, p - 1, na, cfl)
    face_r = _face_2d(sm, v, vessel, i, j, ir, jr, p, na, cfl)
    res = _mass_ratios(m_l, m_c, m_r, face_l, face_r)
    r_gain[i, j] = res[1]
    r_loss[i, j] = res[2]
    r_lup[i, j] = res[3]


@njit(**_JIT_INLINE)
def _mass_cell_2d(sm, sq, dm, fq, r_gain, r_loss, r_lup, v, vessel, i, j, oi, oj, na, cfl):
    """2-D twin of :func:`_mass_cell_3d`."""
    nx, ny = sm.shape
    if i < 1 or j < 1 or i > nx - 2 or j > ny - 2:
        dm[i, j] = sm[i, j]
        return
    il, jl = i - oi, j - oj
    ir, jr = i + oi, j + oj
    m_c = sm[i, j]
    m_l = sm[il, jl]
    m_r = sm[ir, jr]
    if m_c <= 0.0 and m_l <= 0.0 and m_r <= 0.0:
        dm[i, j] = m_c
        return
    p = i * oi + j * oj
    r_c = (r_gain[i, j], r_loss[i, j], r_lup[i, j])
    face_l = _face_2d(sm, v, vessel, il, jl, i, j, p - 1, na, cfl)
    face_r = _face_2d(sm, v, vessel, i, j, ir, jr, p, na, cfl)
    f_l = 0.0
    f_r = 0.0
    if face_l[0] != 0.0:
        r_l = (r_gain[il, jl], r_loss[il, jl], r_lup[il, jl])
        f_l = _mass_flux(m_l, m_c, face_l, r_l, r_c)
    if face_r[0] != 0.0:
        r_r = (r_gain[ir, jr], r_loss[ir, jr], r_lup[ir, jr])
        f_r = _mass_flux(m_c, m_r, face_r, r_c, r_r)
    dm[i, j] = m_c + f_l - f_r
    if face_r[0] > 0.0 or face_l[0] < 0.0:
        col = _outflow_colours(
            m_l, sq[il, jl], m_c, sq[i, j], m_r, sq[ir, jr], face_l[0], f_l, face_r[0], f_r
        )
        if face_l[0] < 0.0:
            fq[il, jl] = f_l * col[0]
        if face_r[0] > 0.0:
            fq[i, j] = f_r * col[1]


@njit(**_JIT_INLINE)
def _species_cell_2d(sm, sq, fq, q_dst, i, j, oi, oj):
    """2-D twin of :func:`_species_cell_3d`."""
    nx, ny = sm.shape
    if i < 1 or j < 1 or i > nx - 2 or j > ny - 2:
        q_dst[i, j] = sq[i, j]
        return
    q_dst[i, j] = sq[i, j] + fq[i - oi, j - oj] - fq[i, j]


@njit(**_JIT_INLINE)
def _diffuse_cell_2d(m, src, dst, dif, vessel, i, j, oi, oj, na, kdiff):
    """2-D twin of :func:`_diffuse_cell_3d`."""
    nx, ny = m.shape
    q_c = src[i, j]
    m_c = m[i, j]
    if m_c <= 0.0 or i < 1 or j < 1 or i > nx - 2 or j > ny - 2:
        dst[i, j] = q_c
        return
    p = i * oi + j * oj
    flux = 0.0
    if p < na - 2:
        ir, jr = i + oi, j + oj
        if vessel[i, j] != 0 and vessel[ir, jr] != 0:
            flux += _diffusion_flux(m_c, q_c, m[ir, jr], src[ir, jr], dif[i, j], dif[ir, jr])
    if p > 1:
        il, jl = i - oi, j - oj
        if vessel[i, j] != 0 and vessel[il, jl] != 0:
            flux -= _diffusion_flux(m[il, jl], src[il, jl], m_c, q_c, dif[il, jl], dif[i, j])
    dst[i, j] = q_c + kdiff * flux


@njit(**_JIT)
def fv_step_2d(m, q, m_out, q_out, work, vx, vy, dxx, dyy, vessel, dt, dx, dy, reverse, n_diff_sub):
    """One step of the conservative bounded finite-volume scheme in 2-D.

    Same scheme as :func:`fv_step_3d` with sweeps x, y (``reverse``: y, x); z is never
    touched.

    Parameters
    ----------
    m, q : ndarray, shape (nx, ny)
        Material volume fraction and species content ``m c`` at step n (not modified).
    m_out, q_out : ndarray, shape (nx, ny)
        Receive m and q at step n + 1.
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
    tq = work[0]
    r_gain = work[1]
    r_loss = work[2]
    r_lup = work[3]
    fq = work[4]
    wm = work[5]
    wq = work[6]
    for sweep in range(2):
        axis = 1 - sweep if reverse else sweep
        if axis == 0:
            v = vx
            dif = dxx
            h = dx
            oi, oj = 1, 0
            na = nx
        else:
            v = vy
            dif = dyy
            h = dy
            oi, oj = 0, 1
            na = ny
        # buffers: in -> work -> out, so the last sweep lands in the output
        if sweep == 0:
            sm = m
            sq = q
            dm = wm
            dq = wq
        else:
            sm = wm
            sq = wq
            dm = m_out
            dq = q_out
        cfl = dt / h
        kdiff = dt / max(n_diff_sub, 1) / (h * h)
        q_adv = tq if n_diff_sub % 2 == 1 else dq
        # one parallel loop with a phase switch, as in fv_step_3d
        for phase in range(3 + n_diff_sub):
            if (phase + n_diff_sub) % 2 == 0:
                src = tq
                dst = dq
            else:
                src = dq
                dst = tq
            for i in prange(nx):
                for j in range(ny):
                    if phase == 0:
                        _ratios_cell_2d(
                            sm, fq, r_gain, r_loss, r_lup, v, vessel, i, j, oi, oj, na, cfl
                        )
                    elif phase == 1:
                        _mass_cell_2d(
                            sm, sq, dm, fq, r_gain, r_loss, r_lup,
                            v, vessel, i, j, oi, oj, na, cfl,
                        )  # fmt: skip
                    elif phase == 2:
                        _species_cell_2d(sm, sq, fq, q_adv, i, j, oi, oj)
                    else:
                        _diffuse_cell_2d(dm, src, dst, dif, vessel, i, j, oi, oj, na, kdiff)


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


@njit(**_JIT)
def lw_max_dt_pair_3d(vel_a, dif_a, vel_b, dif_b, material, dx, dy, dz):
    """Largest Lax-Wendroff dt valid for every blend of two phases (3-D).

    Per material cell and axis the effective speed |v_k - dD_kk/dx_k| / h_k and D_kk / h_k**2
    are bounded by their larger value over the two phases (a blend is a convex combination),
    and the limits of :func:`blendxr.ade.stability.lax_wendroff_max_dt` are applied to those
    bounds: sum_k |nu_k|**(2/3) <= 1 and (sum_k |nu_k|)**2 + 2 sum_k mu_k <= 1.

    Parameters
    ----------
    vel_a, dif_a, vel_b, dif_b : ndarray, shape (3, nx, ny, nz)
        Velocity and diffusivity components of the two phases.
    material : ndarray of uint8, shape (nx, ny, nz)
        Cells that constrain dt (material in either phase).
    """
    nx, ny, nz = material.shape
    best = np.full(nx, np.inf)
    for i in prange(nx):
        low = np.inf
        for j in range(ny):
            for k in range(nz):
                if material[i, j, k] == 0:
                    continue
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
                a23 = sx ** (2.0 / 3.0) + sy ** (2.0 / 3.0) + sz ** (2.0 / 3.0)
                low = min(low, _limit_from_bounds(sx + sy + sz, a23, b2))
        best[i] = low
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
            a23 = sx ** (2.0 / 3.0) + sy ** (2.0 / 3.0)
            low = min(low, _limit_from_bounds(sx + sy, a23, b2))
        best[i] = low
    return best.min()


@njit(**_JIT)
def fv_max_dt_pair(vel_a, vel_b, vessel, spacing):
    """Largest finite-volume dt for every blend of two phases: per-face Courant <= 1/2.

    The face velocity (mean of the two cells, zero at a wall) of a blend is bounded by the
    larger of the two phases' face velocities. Works on 2-D or 3-D data flattened to
    (ndim, n) with the grid ``shape`` given through ``spacing`` (h_k per axis) and
    ``vessel`` of the grid's shape; ``vel_*`` have shape (ndim, *grid shape).
    """
    ndim = vel_a.shape[0]
    shape = vessel.shape
    n0 = shape[0]
    best = np.full(n0, np.inf)
    va = vel_a.reshape(ndim, -1)
    vb = vel_b.reshape(ndim, -1)
    ves = vessel.reshape(-1)
    stride = np.ones(ndim, np.int64)
    for axis in range(ndim - 2, -1, -1):
        stride[axis] = stride[axis + 1] * shape[axis + 1]
    per_slab = stride[0]
    for i in prange(n0):
        low = np.inf
        for flat in range(i * per_slab, (i + 1) * per_slab):
            if ves[flat] == 0:
                continue
            rem = flat
            for axis in range(ndim):
                idx = rem // stride[axis]
                rem -= idx * stride[axis]
                if idx + 1 >= shape[axis]:
                    continue
                nb = flat + stride[axis]
                if ves[nb] == 0:
                    continue
                fa = abs(0.5 * (va[axis, flat] + va[axis, nb]))
                fb = abs(0.5 * (vb[axis, flat] + vb[axis, nb]))
                f = max(fa, fb)
                if f > 0.0:
                    low = min(low, 0.5 * spacing[axis] / f)
        best[i] = low
    return best.min()
