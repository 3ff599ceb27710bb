"""A bounded semi-Lagrangian scheme: steps several times the advective limit.

Each step traces every material cell's trajectory back over dt through the flow
(second-order midpoint rule, two fixed-point iterations, the velocity interpolated
trilinearly) and takes c at the departure point by tensor cubic Lagrange interpolation,
clipped to the range of the eight cells that bracket the point (the quasi-monotone
semi-Lagrangian scheme of Bermejo and Staniforth, 1992): bounded without a limiter, third
order in space where the flow is smooth. Where the 4^d interpolation stencil reaches a
cell without material (the free surface, the wall) the value is the material-weighted
trilinear mean of the bracketing cells, so no colour is drawn from empty cells. Diffusion
follows as explicit flux-form sub-steps between material cells (no flux into empty
cells), as many as ``dt_sub * sum_k 2 max(D_kk) / h_k**2 <= 1`` needs, each a convex
combination and so bounded.

Advection by interpolation is stable at any dt; what limits dt is accuracy:
:data:`COURANT` cells of travel per step, and trajectories that cannot cross
(``dt * max |dv_i/dx_j| <= LIPSCHITZ``, the deformational Courant number). The scheme
carries c only (like the paper's), so species content is not conserved to round-off: it
is reported as drift, as for ``lax-wendroff``.

Kernels take plain arrays of shape (nx, ny, nz); a 2-D grid is stepped as (nx, ny, 1)
with no z work (an axis of one cell has one interpolation point and no neighbours).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .. import kernels, stability
from .base import ColourScheme

#: at most this many cells of travel per step (an accuracy limit, not a stability one)
COURANT = 4.0
#: at most this deformational Courant number dt * max |dv_i/dx_j| (trajectories cross
#: above 1; the midpoint rule is accurate well below it)
LIPSCHITZ = 0.5

_JIT = {"parallel": True, "cache": True, "fastmath": False, "error_model": "numpy"}
_JIT_INLINE = {"cache": True, "fastmath": False, "error_model": "numpy", "inline": "always"}


# ---------------------------------------------------------------------------- kernels


@njit(**_JIT_INLINE)
def _bracket(p, n):
    """Lower index, upper index and weight of the upper one for position ``p`` (cells);
    a position outside the grid takes the nearest end cell."""
    if n == 1:
        return 0, 0, 0.0
    if p <= 0.0:
        return 0, 1, 0.0
    if p >= n - 1:
        return n - 2, n - 1, 1.0
    i0 = int(math.floor(p))
    return i0, i0 + 1, p - i0


@njit(**_JIT_INLINE)
def _corner(o, i0, i1, f):
    """Index and linear weight of the lower (``o`` = 0) or upper (1) bracketing cell."""
    return (i0, 1.0 - f) if o == 0 else (i1, f)


@njit(**_JIT_INLINE)
def _velocity_at(vx, vy, vz, px, py, pz):
    """The velocity (m/s) trilinearly at position (px, py, pz) in cells."""
    nx, ny, nz = vx.shape
    i0, i1, fx = _bracket(px, nx)
    j0, j1, fy = _bracket(py, ny)
    k0, k1, fz = _bracket(pz, nz)
    ux = uy = uz = 0.0
    for a in range(2):
        i, wa = _corner(a, i0, i1, fx)
        for b in range(2):
            j, wb = _corner(b, j0, j1, fy)
            for g in range(2):
                k, wg = _corner(g, k0, k1, fz)
                w = wa * wb * wg
                ux += w * vx[i, j, k]
                uy += w * vy[i, j, k]
                uz += w * vz[i, j, k]
    return ux, uy, uz


@njit(**_JIT_INLINE)
def _cubic_weights(f, n):
    """The number of points and the Lagrange weights of the points -1, 0, 1, 2 for the
    fraction ``f``; one point (weight 1) on an axis of one cell."""
    if n == 1:
        return 1, (1.0, 0.0, 0.0, 0.0)
    return 4, (
        -f * (f - 1.0) * (f - 2.0) / 6.0,
        (f + 1.0) * (f - 1.0) * (f - 2.0) / 2.0,
        -(f + 1.0) * f * (f - 2.0) / 2.0,
        (f + 1.0) * f * (f - 1.0) / 6.0,
    )


@njit(**_JIT_INLINE)
def _sample(c, material, core, px, py, pz, fallback):
    """c at (px, py, pz) (cells): clipped cubic where the stencil is all material, else
    the material-weighted trilinear mean; ``fallback`` when no bracketing cell is
    material."""
    nx, ny, nz = c.shape
    i0, i1, fx = _bracket(px, nx)
    j0, j1, fy = _bracket(py, ny)
    k0, k1, fz = _bracket(pz, nz)
    if core[i0, j0, k0]:
        lo, hi = 1.0e300, -1.0e300
        for i in (i0, i1):
            for j in (j0, j1):
                for k in (k0, k1):
                    v = c[i, j, k]
                    lo = min(lo, v)
                    hi = max(hi, v)
        mx, wx = _cubic_weights(fx, nx)
        my, wy = _cubic_weights(fy, ny)
        mz, wz = _cubic_weights(fz, nz)
        bx = i0 - 1 if mx == 4 else i0
        by = j0 - 1 if my == 4 else j0
        bz = k0 - 1 if mz == 4 else k0
        acc = 0.0
        for a in range(mx):
            i = min(max(bx + a, 0), nx - 1)
            for b in range(my):
                j = min(max(by + b, 0), ny - 1)
                wab = wx[a] * wy[b]
                for g in range(mz):
                    k = min(max(bz + g, 0), nz - 1)
                    acc += wab * wz[g] * c[i, j, k]
        return min(max(acc, lo), hi)
    num = 0.0
    den = 0.0
    for a in range(2):
        i, wa = _corner(a, i0, i1, fx)
        for b in range(2):
            j, wb = _corner(b, j0, j1, fy)
            for g in range(2):
                k, wg = _corner(g, k0, k1, fz)
                if material[i, j, k]:
                    w = wa * wb * wg
                    num += w * c[i, j, k]
                    den += w
    if den > 1e-12:
        return num / den
    return fallback


@njit(**_JIT)
def sl_advect(c, out, vx, vy, vz, material, core, dt, hx, hy, hz):
    """One semi-Lagrangian advection step of ``dt`` from ``c`` into ``out``.

    Parameters
    ----------
    c, out : ndarray (nx, ny, nz) of float64
        The concentration now and after the step (cells without material copy ``c``).
    vx, vy, vz : ndarray (nx, ny, nz)
        The velocity (m/s) of the step (its midpoint in time).
    material : ndarray (nx, ny, nz) of uint8
        1 where the cell holds material.
    core : ndarray (nx, ny, nz) of uint8
        1 where every cell of the cubic stencil based at the cell is material
        (:func:`sl_core`).
    dt : float
        The step (s).
    hx, hy, hz : float
        Cell sizes (m).
    """
    nx, ny, nz = c.shape
    sx, sy, sz = dt / hx, dt / hy, dt / hz
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                if not material[i, j, k]:
                    out[i, j, k] = c[i, j, k]
                    continue
                # midpoint rule: the departure point from the velocity half-way back
                ux, uy, uz = vx[i, j, k], vy[i, j, k], vz[i, j, k]
                for _ in range(2):
                    ux, uy, uz = _velocity_at(
                        vx, vy, vz, i - 0.5 * sx * ux, j - 0.5 * sy * uy, k - 0.5 * sz * uz
                    )  # fmt: skip
                out[i, j, k] = _sample(
                    c, material, core, i - sx * ux, j - sy * uy, k - sz * uz, c[i, j, k]
                )  # fmt: skip


@njit(**_JIT)
def _window_min(src, dst, axis):
    """dst = the least of src over offsets -1..2 along ``axis`` (clamped at the ends)."""
    nx, ny, nz = src.shape
    n = src.shape[axis]
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                p = np.int64(i) if axis == 0 else (np.int64(j) if axis == 1 else np.int64(k))
                v = src[i, j, k]
                for o in (-1, 1, 2):
                    q = min(max(p + o, 0), n - 1)
                    if axis == 0:
                        v = min(v, src[q, j, k])
                    elif axis == 1:
                        v = min(v, src[i, q, k])
                    else:
                        v = min(v, src[i, j, q])
                dst[i, j, k] = v


def sl_core(material, core, scratch):
    """``core`` = 1 where the cubic stencil based at the cell (offsets -1..2 per axis,
    clamped) is all material; ``scratch``: an array like ``material``."""
    axes = [axis for axis in range(3) if material.shape[axis] > 1]
    if not axes:
        core[...] = material
        return
    # targets alternate so that the last pass writes core and none works in place
    targets = [core if (len(axes) - 1 - n) % 2 == 0 else scratch for n in range(len(axes))]
    src = material
    for axis, out in zip(axes, targets, strict=True):
        _window_min(src, out, axis)
        src = out


@njit(**_JIT)
def sl_diffuse(c, out, dxx, dyy, dzz, material, rx, ry, rz):
    """One explicit diffusion sub-step from ``c`` into ``out``: flux form between
    material cells (face diffusivity the mean of its two cells), no flux into empty
    cells. ``rx = dt_sub / hx**2`` etc.; stable and bounded when
    ``2 (rx max(dxx) + ry max(dyy) + rz max(dzz)) <= 1``
    (:func:`blendxr.ade.stability.unsplit_diffusion_substeps`)."""
    nx, ny, nz = c.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                ci = c[i, j, k]
                if not material[i, j, k]:
                    out[i, j, k] = ci
                    continue
                acc = 0.0
                if i > 0 and material[i - 1, j, k]:
                    acc += rx * 0.5 * (dxx[i, j, k] + dxx[i - 1, j, k]) * (c[i - 1, j, k] - ci)
                if i < nx - 1 and material[i + 1, j, k]:
                    acc += rx * 0.5 * (dxx[i, j, k] + dxx[i + 1, j, k]) * (c[i + 1, j, k] - ci)
                if j > 0 and material[i, j - 1, k]:
                    acc += ry * 0.5 * (dyy[i, j, k] + dyy[i, j - 1, k]) * (c[i, j - 1, k] - ci)
                if j < ny - 1 and material[i, j + 1, k]:
                    acc += ry * 0.5 * (dyy[i, j, k] + dyy[i, j + 1, k]) * (c[i, j + 1, k] - ci)
                if k > 0 and material[i, j, k - 1]:
                    acc += rz * 0.5 * (dzz[i, j, k] + dzz[i, j, k - 1]) * (c[i, j, k - 1] - ci)
                if k < nz - 1 and material[i, j, k + 1]:
                    acc += rz * 0.5 * (dzz[i, j, k] + dzz[i, j, k + 1]) * (c[i, j, k + 1] - ci)
                out[i, j, k] = ci + acc


@njit(**_JIT)
def sl_max_rates(vel_a, vel_b, material, inv_h):
    """(largest speed in cells per second along any axis, largest difference of a
    velocity component in cells per second between neighbouring material cells) over the
    material cells of either phase; velocities (m/s) of shape (ndim, nx, ny, nz),
    ``inv_h`` the inverse cell sizes (1/m) of the ndim axes."""
    ndim, nx, ny, nz = vel_a.shape
    speed = np.zeros(nx)
    grad = np.zeros(nx)
    for i in prange(nx):
        s_max = 0.0
        g_max = 0.0
        for j in range(ny):
            for k in range(nz):
                if not material[i, j, k]:
                    continue
                for vel in (vel_a, vel_b):
                    for d in range(ndim):
                        scale = inv_h[d]  # m/s to cells per second
                        v = vel[d, i, j, k]
                        s_max = max(s_max, abs(v) * scale)
                        # one-sided differences towards material neighbours
                        if i + 1 < nx and material[i + 1, j, k]:
                            g_max = max(g_max, abs(vel[d, i + 1, j, k] - v) * scale)
                        if j + 1 < ny and material[i, j + 1, k]:
                            g_max = max(g_max, abs(vel[d, i, j + 1, k] - v) * scale)
                        if k + 1 < nz and material[i, j, k + 1]:
                            g_max = max(g_max, abs(vel[d, i, j, k + 1] - v) * scale)
        speed[i] = s_max
        grad[i] = g_max
    return speed.max() if nx else 0.0, grad.max() if nx else 0.0


# ---------------------------------------------------------------------------- the scheme


class SemiLagrangian(ColourScheme):
    """Quasi-monotone cubic semi-Lagrangian advection of c, explicit diffusion."""

    name = "semi-lagrangian"

    def __init__(self, grid, vessel, with_diffusion):
        super().__init__(grid, vessel, with_diffusion)
        self.shape3 = tuple(grid.shape) + (1,) * (3 - self.ndim)
        self.core = np.zeros(self.shape3, np.uint8)
        self._scratch = np.zeros(self.shape3, np.uint8)
        self.vel = np.zeros((3, *self.shape3))  # z stays zero on a 2-D grid
        self.dif = np.zeros((3, *self.shape3)) if with_diffusion else None
        self.n_sub = 0

    def _3d(self, a):
        return a.reshape(self.shape3)

    # --- per phase pair, per refresh, per step -------------------------------
    def max_dt(self, a, b):
        speed, grad = sl_max_rates(
            a.vel.reshape(self.ndim, *self.shape3),
            b.vel.reshape(self.ndim, *self.shape3),
            self._3d(self.material_of_pair(a, b)),
            1.0 / np.asarray(self.grid.spacing, float),
        )  # fmt: skip
        limit = math.inf
        if speed > 0:
            limit = COURANT / speed
        if grad > 0:
            limit = min(limit, LIPSCHITZ / grad)
        return float(limit)

    def begin_interval(self, a, b, dt):
        """Diffusion sub-steps of one step, refused above
        :data:`~blendxr.ade.schemes.base.MAX_DIFFUSION_SUBSTEPS`."""
        if not self.with_diffusion:
            self.n_sub = 0
            return 0
        dmax = np.maximum(a.dif_max, b.dif_max)
        n_sub = stability.unsplit_diffusion_substeps(dmax, self.grid.spacing, dt)
        self.n_sub = self.checked_substeps(n_sub, dt, "dt * sum_k 2 D_kk / h_k^2 <= 1")
        return self.n_sub

    def blend_fields(self, a, b, w):
        self.blend_material(a, b, w)
        sl_core(self._3d(self.material), self.core, self._scratch)
        for d in range(self.ndim):
            kernels.lerp_into(self.vel[d].reshape(-1), a.vel[d].reshape(-1),
                              b.vel[d].reshape(-1), w)  # fmt: skip
            if self.dif is not None:
                kernels.lerp_into(self.dif[d].reshape(-1), a.dif[d].reshape(-1),
                                  b.dif[d].reshape(-1), w)  # fmt: skip
        self._active = int(np.count_nonzero(self.material))

    def prepare_step(self, a, b, w, dt, limit):
        return None  # the step reads the blended fields directly

    def step(self):
        h = tuple(self.grid.spacing) + (1.0,) * (3 - self.ndim)
        material = self._3d(self.material)
        sl_advect(self._3d(self.c), self._3d(self.c_next), *self.vel, material, self.core,
                  self._dt, *h)  # fmt: skip
        self.c, self.c_next = self.c_next, self.c
        if self.n_sub:
            dt_sub = self._dt / self.n_sub
            r = tuple(dt_sub / s**2 for s in h[: self.ndim]) + (0.0,) * (3 - self.ndim)
            for _ in range(self.n_sub):
                sl_diffuse(self._3d(self.c), self._3d(self.c_next), *self.dif, material, *r)
                self.c, self.c_next = self.c_next, self.c
