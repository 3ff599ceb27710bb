"""Density projection: move particles out of cells they crowd past their packing.

MPM particles move with the interpolated grid velocity and their volumes with the affine
matrix; in a shearing bed the two drift apart, and particles crowd past their seeded
packing where no stress sees it (docs/flow.md). The projection takes the grid's excess
packing ``e = max(m_i / (rho h^d c_i) - 1, 0)`` (``c_i``: the share of node i's support
inside the vessel, so that a node at a wall is full at its own capacity) and finds the
displacement ``u = -grad phi`` whose divergence is that excess,

    -laplace phi = relax * e      on the nodes that hold material,
    phi = 0                       on nodes with less than ``air`` of a full node (the
                                  free surface: the bed grows there),
    d phi / dn = 0                on nodes mostly outside the vessel (walls) and across
                                  a mirror plane,

then moves each particle by ``u`` interpolated with the quadratic B-splines (the
implicit density projection of particle-in-cell liquids, applied to positions only:
velocity, affine matrix, stress and mass stay with the particle). A crowded cell so
pushes its neighbours aside all the way to the free surface, and the bed's volume grows
by the excess it had lost; a bed at or below its packing is left alone.

The Poisson problem is solved by conjugate gradients on the node grid (5- or 7-point
Laplacian in grid units, symmetric positive definite once every connected region of
material touches a free-surface node; ``REGULARISATION`` keeps a sealed pocket finite).
Kernels take plain arrays; the driver (``solver.py``) calls :func:`project_density`.
"""

from __future__ import annotations

import math
import time

import numpy as np
from numba import njit, prange

from .kernels import _limited, _stencil, _stencil_slopes

__all__ = [
    "AIR",
    "MATERIAL",
    "SOLID",
    "CAPACITY_MIN",
    "node_capacity",
    "classify_2d",
    "classify_3d",
    "poisson_rows",
    "assemble_poisson_2d",
    "assemble_poisson_3d",
    "apply_poisson",
    "solve_poisson",
    "displace_2d",
    "displace_3d",
    "extend_to_walls",
    "mirror_images",
]

_JIT = {"parallel": True, "cache": True, "fastmath": False, "error_model": "numpy"}
_JIT_SERIAL = {"cache": True, "fastmath": False, "error_model": "numpy"}

AIR = 0  # phi = 0 (free surface)
MATERIAL = 1  # unknown
SOLID = 2  # no flux (wall, outside the grid)
#: Nodes with less of their support inside the vessel than this are walls (no flux).
CAPACITY_MIN = 0.25
#: Diagonal shift of the Laplacian: a pocket of material sealed from every free-surface
#: node would make the operator singular; this keeps its solution bounded.
REGULARISATION = 1e-6


# ------------------------------------------------------------------------- capacity


def node_capacity(node_sdf: np.ndarray, h: float) -> np.ndarray:
    """Share of each node's B-spline support inside the vessel, from its wall distance.

    The quadratic B-spline integrates to ``h^d``; for a wall plane along a grid axis the
    share inside is the spline's cumulative integral at ``-sdf / h`` (exact there, and a
    close estimate where the wall is oblique or curved on the scale of a cell). A node
    in a bed at its seeded packing holds ``rho h^d`` times this.

    Parameters
    ----------
    node_sdf : ndarray
        Signed distance of every node to the wall [m] (negative inside).
    h : float
        Node spacing [m].

    Returns
    -------
    ndarray of float64, the shape of ``node_sdf``, in [0, 1].
    """
    t = np.clip(-np.asarray(node_sdf, float) / h, -1.5, 1.5)
    low = (t + 1.5) ** 3 / 6.0
    mid = 0.5 + 0.75 * t - t**3 / 3.0
    high = 1.0 - (1.5 - t) ** 3 / 6.0
    return np.where(t <= -0.5, low, np.where(t <= 0.5, mid, high))


# ------------------------------------------------------------------------- classify


@njit(**_JIT)
def classify_2d(fill, capacity, air, code):
    """Mark every node air, material or solid (2-D).

    Parameters
    ----------
    fill : ndarray of float64, shape (nx, ny)
        Node fill: the particles' volume on the node over the node's volume ``h^2``.
    capacity : ndarray of float64, shape (nx, ny)
        :func:`node_capacity`; a node's fill is measured against it.
    air : float
        Nodes filled below this share of their capacity are free surface (phi = 0).
    code : ndarray of int8, shape (nx, ny)
        Out: :data:`AIR`, :data:`MATERIAL` or :data:`SOLID`.
    """
    nx, ny = fill.shape
    for i in prange(nx):
        for j in range(ny):
            c = capacity[i, j]
            if c < CAPACITY_MIN:
                code[i, j] = SOLID
            elif fill[i, j] < air * c:
                code[i, j] = AIR
            else:
                code[i, j] = MATERIAL


@njit(**_JIT)
def classify_3d(fill, capacity, air, code):
    """As :func:`classify_2d`, shape (nx, ny, nz), node volume ``h^3``."""
    nx, ny, nz = fill.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                c = capacity[i, j, k]
                if c < CAPACITY_MIN:
                    code[i, j, k] = SOLID
                elif fill[i, j, k] < air * c:
                    code[i, j, k] = AIR
                else:
                    code[i, j, k] = MATERIAL


@njit(**_JIT)
def excess_2d(fill, capacity, code, relax, rhs):
    """Right-hand side: ``relax (fill / capacity - 1)`` on material nodes inside the bed
    (both signs: a node short of material draws its neighbours in), only its positive
    part on nodes next to the free surface (a surface is short of material by nature),
    0 elsewhere. Returns the largest ``fill / capacity`` of a material node."""
    nx, ny = fill.shape
    worst = 0.0
    for i in prange(nx):
        for j in range(ny):
            rhs[i, j] = 0.0
            if code[i, j] != MATERIAL:
                continue
            e = fill[i, j] / capacity[i, j] - 1.0
            worst = max(worst, e + 1.0)
            surface = (
                (i > 0 and code[i - 1, j] == AIR)
                or (i < nx - 1 and code[i + 1, j] == AIR)
                or (j > 0 and code[i, j - 1] == AIR)
                or (j < ny - 1 and code[i, j + 1] == AIR)
            )
            if surface and e < 0.0:
                continue
            rhs[i, j] = relax * e
    return worst


@njit(**_JIT)
def excess_3d(fill, capacity, code, relax, rhs):
    """As :func:`excess_2d` in 3-D."""
    nx, ny, nz = fill.shape
    worst = 0.0
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                rhs[i, j, k] = 0.0
                if code[i, j, k] != MATERIAL:
                    continue
                e = fill[i, j, k] / capacity[i, j, k] - 1.0
                worst = max(worst, e + 1.0)
                surface = (
                    (i > 0 and code[i - 1, j, k] == AIR)
                    or (i < nx - 1 and code[i + 1, j, k] == AIR)
                    or (j > 0 and code[i, j - 1, k] == AIR)
                    or (j < ny - 1 and code[i, j + 1, k] == AIR)
                    or (k > 0 and code[i, j, k - 1] == AIR)
                    or (k < nz - 1 and code[i, j, k + 1] == AIR)
                )
                if surface and e < 0.0:
                    continue
                rhs[i, j, k] = relax * e
    return worst


@njit(**_JIT)
def scatter_volume_2d(x, vol, origin, inv_h, work, starts, fill):
    """``fill_i = sum_p vol_p w_ip / h^2`` (quadratic B-splines); ``work`` of shape
    (tasks, nx, ny) holds each task's sums (no two tasks write one array)."""
    tasks = starts.shape[0] - 1
    nx, ny = fill.shape
    scale = inv_h * inv_h
    for t in prange(tasks):
        acc = work[t]
        acc[...] = 0.0
        for q in range(starts[t], starts[t + 1]):
            bx, _, wx0, wx1, wx2 = _stencil((x[q, 0] - origin[0]) * inv_h, nx)
            by, _, wy0, wy1, wy2 = _stencil((x[q, 1] - origin[1]) * inv_h, ny)
            wx = (wx0, wx1, wx2)
            wy = (wy0, wy1, wy2)
            v = vol[q] * scale
            for a in range(3):
                for b in range(3):
                    acc[bx + a, by + b] += v * wx[a] * wy[b]
    for i in prange(nx):
        for j in range(ny):
            s = 0.0
            for t in range(tasks):
                s += work[t, i, j]
            fill[i, j] = s


@njit(**_JIT)
def scatter_volume_3d(x, vol, origin, inv_h, work, starts, fill):
    """As :func:`scatter_volume_2d` in 3-D (``/ h^3``)."""
    tasks = starts.shape[0] - 1
    nx, ny, nz = fill.shape
    scale = inv_h * inv_h * inv_h
    for t in prange(tasks):
        acc = work[t]
        acc[...] = 0.0
        for q in range(starts[t], starts[t + 1]):
            bx, _, wx0, wx1, wx2 = _stencil((x[q, 0] - origin[0]) * inv_h, nx)
            by, _, wy0, wy1, wy2 = _stencil((x[q, 1] - origin[1]) * inv_h, ny)
            bz, _, wz0, wz1, wz2 = _stencil((x[q, 2] - origin[2]) * inv_h, nz)
            wx = (wx0, wx1, wx2)
            wy = (wy0, wy1, wy2)
            wz = (wz0, wz1, wz2)
            v = vol[q] * scale
            for a in range(3):
                for b in range(3):
                    for c in range(3):
                        acc[bx + a, by + b, bz + c] += v * wx[a] * wy[b] * wz[c]
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                s = 0.0
                for t in range(tasks):
                    s += work[t, i, j, k]
                fill[i, j, k] = s


# ------------------------------------------------------------------------ Laplacian
# A = -laplace (grid units) on the material nodes, stored compactly: each material
# node is a row with its diagonal and the rows of its material neighbours. Links to air
# see phi = 0 (they add to the diagonal only), links to walls and off the grid carry no
# flux. The conjugate gradients then run over the material nodes alone in one serial
# call: on these small grids, launching parallel loops four times an iteration cost more
# than the arithmetic (docs/flow.md).

#: the most material neighbours a node has (6 in 3-D; the 2-D rows pad with -1)
NEIGHBOURS = 6


@njit(**_JIT_SERIAL)
def _open_link(code_j, row_j, rows, d, m, r):
    """Add the link to a neighbour of code ``code_j`` (row ``row_j``) to row ``r``:
    returns the new diagonal and count of material neighbours."""
    if code_j == MATERIAL:
        rows[r, m] = row_j
        return d + 1.0, m + 1
    if code_j == AIR:
        return d + 1.0, m
    return d, m


@njit(**_JIT_SERIAL)
def poisson_rows(code, k0, index):
    """Number the unknowns: ``index`` (the grid's shape, int64) receives each material
    node's row (-1 elsewhere and, with a mirror plane ``k0 >= 0``, on the image planes
    below it); returns the number of rows."""
    flat_code = code.reshape(-1)
    flat = index.reshape(-1)
    nz = code.shape[-1] if code.ndim == 3 else 1
    n = 0
    for q in range(flat.shape[0]):
        if flat_code[q] == MATERIAL and not (k0 >= 0 and q % nz < k0):
            flat[q] = n
            n += 1
        else:
            flat[q] = -1
    return n


@njit(**_JIT_SERIAL)
def assemble_poisson_2d(code, index, diagonal, rows):
    """The rows of A on a 2-D grid: ``diagonal`` (n) and ``rows`` (n, NEIGHBOURS), the
    material neighbours' rows padded with -1 (:func:`poisson_rows` numbered them)."""
    nx, ny = code.shape
    rows[...] = -1
    for i in range(nx):
        for j in range(ny):
            r = index[i, j]
            if r < 0:
                continue
            d, m = REGULARISATION, 0
            if i > 0:
                d, m = _open_link(code[i - 1, j], index[i - 1, j], rows, d, m, r)
            if i < nx - 1:
                d, m = _open_link(code[i + 1, j], index[i + 1, j], rows, d, m, r)
            if j > 0:
                d, m = _open_link(code[i, j - 1], index[i, j - 1], rows, d, m, r)
            if j < ny - 1:
                d, m = _open_link(code[i, j + 1], index[i, j + 1], rows, d, m, r)
            diagonal[r] = d


@njit(**_JIT_SERIAL)
def assemble_poisson_3d(code, index, diagonal, rows, k0):
    """As :func:`assemble_poisson_2d` in 3-D; with ``k0 >= 0`` the node plane ``k = k0``
    is a mirror: a link from the plane downward reaches the image of the node above
    it, which is that node (its row appears twice)."""
    nx, ny, nz = code.shape
    rows[...] = -1
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                r = index[i, j, k]
                if r < 0:
                    continue
                d, m = REGULARISATION, 0
                if i > 0:
                    d, m = _open_link(code[i - 1, j, k], index[i - 1, j, k], rows, d, m, r)
                if i < nx - 1:
                    d, m = _open_link(code[i + 1, j, k], index[i + 1, j, k], rows, d, m, r)
                if j > 0:
                    d, m = _open_link(code[i, j - 1, k], index[i, j - 1, k], rows, d, m, r)
                if j < ny - 1:
                    d, m = _open_link(code[i, j + 1, k], index[i, j + 1, k], rows, d, m, r)
                down = k + 1 if (k0 >= 0 and k == k0) else k - 1
                if down >= 0:
                    d, m = _open_link(code[i, j, down], index[i, j, down], rows, d, m, r)
                if k < nz - 1:
                    d, m = _open_link(code[i, j, k + 1], index[i, j, k + 1], rows, d, m, r)
                diagonal[r] = d


@njit(**_JIT_SERIAL)
def apply_poisson(diagonal, rows, p, out):
    """``out = A p`` on the compact rows; returns ``p . A p``."""
    pap = 0.0
    for r in range(p.shape[0]):
        s = diagonal[r] * p[r]
        for m in range(NEIGHBOURS):
            c = rows[r, m]
            if c < 0:
                break
            s -= p[c]
        out[r] = s
        pap += p[r] * s
    return pap


# ------------------------------------------------------------- conjugate gradients


@njit(**_JIT_SERIAL)
def _conjugate_gradients(diagonal, rows, b, x, r, p, ap, tol, max_iter):
    """Solve ``A x = b`` on the compact rows from the guess ``x`` (in place); returns
    (iterations, relative residual)."""
    n = b.shape[0]
    bb = 0.0
    for q in range(n):
        bb += b[q] * b[q]
    if bb == 0.0:
        x[:] = 0.0
        return 0, 0.0
    apply_poisson(diagonal, rows, x, ap)
    rr = 0.0
    for q in range(n):
        r[q] = b[q] - ap[q]
        p[q] = r[q]
        rr += r[q] * r[q]
    target = tol * tol * bb
    iterations = 0
    while rr > target and iterations < max_iter:
        pap = apply_poisson(diagonal, rows, p, ap)
        if pap <= 0.0:
            break
        alpha = rr / pap
        rr_new = 0.0
        for q in range(n):
            x[q] += alpha * p[q]
            r[q] -= alpha * ap[q]
            rr_new += r[q] * r[q]
        beta = rr_new / rr
        for q in range(n):
            p[q] = r[q] + beta * p[q]
        rr = rr_new
        iterations += 1
    return iterations, math.sqrt(rr / bb)


def solve_poisson(code, rhs, phi, tol, max_iter, k0=-1):
    """Solve ``A phi = rhs`` by conjugate gradients, from ``phi`` as the first guess.

    A is -laplace in grid units on the material nodes (links to air see phi = 0, links
    to walls and off the grid carry no flux), assembled compactly
    (:func:`assemble_poisson_3d`) and solved over the material nodes alone.

    Parameters
    ----------
    code, rhs : ndarray
        From :func:`classify_2d` / :func:`classify_3d`.
    phi : ndarray of float64
        First guess on the material nodes, overwritten there by the solution (the other
        nodes are left as they are).
    tol : float
        Stop when ``|r| <= tol |rhs|``.
    max_iter : int
    k0 : int
        Mirror plane of a 3-D grid (-1: none): the nodes below it are images, not
        unknowns.

    Returns
    -------
    iterations : int
    relative_residual : float
    """
    index = np.empty(code.shape, np.int64)
    n = poisson_rows(code, k0, index)
    diagonal = np.empty(n)
    rows = np.empty((n, NEIGHBOURS), np.int64)
    if phi.ndim == 3:
        assemble_poisson_3d(code, index, diagonal, rows, k0)
    else:
        assemble_poisson_2d(code, index, diagonal, rows)
    unknown = index >= 0
    b = np.ascontiguousarray(rhs[unknown])
    x = np.ascontiguousarray(phi[unknown])
    r, p, ap = np.empty(n), np.empty(n), np.empty(n)
    iterations, residual = _conjugate_gradients(diagonal, rows, b, x, r, p, ap, tol, max_iter)
    phi[unknown] = x
    return iterations, residual


# -------------------------------------------------------------------------- extend


@njit(**_JIT)
def _extend_pass_2d(phi, code, filled, sweep):
    nx, ny = phi.shape
    for i in prange(nx):
        for j in range(ny):
            if code[i, j] != SOLID or filled[i, j] != 0:
                continue
            s = 0.0
            n = 0
            for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                a = i + di
                b = j + dj
                if 0 <= a < nx and 0 <= b < ny and 0 < filled[a, b] < sweep:
                    s += phi[a, b]
                    n += 1
            if n > 0:
                phi[i, j] = s / n
                filled[i, j] = sweep


@njit(**_JIT)
def _extend_pass_3d(phi, code, filled, sweep):
    nx, ny, nz = phi.shape
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                if code[i, j, k] != SOLID or filled[i, j, k] != 0:
                    continue
                s = 0.0
                n = 0
                for di, dj, dk in (
                    (-1, 0, 0),
                    (1, 0, 0),
                    (0, -1, 0),
                    (0, 1, 0),
                    (0, 0, -1),
                    (0, 0, 1),
                ):
                    a = i + di
                    b = j + dj
                    c = k + dk
                    if 0 <= a < nx and 0 <= b < ny and 0 <= c < nz and 0 < filled[a, b, c] < sweep:
                        s += phi[a, b, c]
                        n += 1
                if n > 0:
                    phi[i, j, k] = s / n
                    filled[i, j, k] = sweep


def extend_to_walls(phi: np.ndarray, code: np.ndarray, filled: np.ndarray, sweeps: int = 2):
    """Give air nodes phi = 0 and wall nodes the mean of their known neighbours, sweep by
    sweep outward (``sweeps`` layers), so that the gather near a wall sees no flux
    through it; ``filled`` is int8 scratch of phi's shape."""
    phi[code == AIR] = 0.0
    filled[...] = 0
    filled[code != SOLID] = 1
    phi[code == SOLID] = 0.0
    passes = _extend_pass_3d if phi.ndim == 3 else _extend_pass_2d
    for sweep in range(2, sweeps + 2):
        passes(phi, code, filled, sweep)


# ------------------------------------------------------------------------- displace


@njit(**_JIT)
def displace_2d(x, phi, origin, inv_h, max_shift, starts):
    """Move every particle by ``-h grad phi`` (grid units to metres), at most
    ``max_shift`` [m]; in place. ``starts``: contiguous particle chunks per task."""
    nx, ny = phi.shape
    h = 1.0 / inv_h
    for t in prange(starts.shape[0] - 1):
        for q in range(starts[t], starts[t + 1]):
            bx, rx, wx0, wx1, wx2 = _stencil((x[q, 0] - origin[0]) * inv_h, nx)
            by, ry, wy0, wy1, wy2 = _stencil((x[q, 1] - origin[1]) * inv_h, ny)
            wx = (wx0, wx1, wx2)
            wy = (wy0, wy1, wy2)
            sx = _stencil_slopes(rx)
            sy = _stencil_slopes(ry)
            gx = 0.0
            gy = 0.0
            for a in range(3):
                for b in range(3):
                    v = phi[bx + a, by + b]
                    gx += sx[a] * wy[b] * v
                    gy += wx[a] * sy[b] * v
            dx, dy, _ = _limited(-h * gx, -h * gy, 0.0, max_shift)
            x[q, 0] += dx
            x[q, 1] += dy


@njit(**_JIT)
def displace_3d(x, phi, origin, inv_h, max_shift, starts):
    """As :func:`displace_2d` in 3-D (``phi`` with its mirror images filled in)."""
    nx, ny, nz = phi.shape
    h = 1.0 / inv_h
    for t in prange(starts.shape[0] - 1):
        for q in range(starts[t], starts[t + 1]):
            bx, rx, wx0, wx1, wx2 = _stencil((x[q, 0] - origin[0]) * inv_h, nx)
            by, ry, wy0, wy1, wy2 = _stencil((x[q, 1] - origin[1]) * inv_h, ny)
            bz, rz, wz0, wz1, wz2 = _stencil((x[q, 2] - origin[2]) * inv_h, nz)
            wx = (wx0, wx1, wx2)
            wy = (wy0, wy1, wy2)
            wz = (wz0, wz1, wz2)
            sx = _stencil_slopes(rx)
            sy = _stencil_slopes(ry)
            sz = _stencil_slopes(rz)
            gx = 0.0
            gy = 0.0
            gz = 0.0
            for a in range(3):
                for b in range(3):
                    for c in range(3):
                        v = phi[bx + a, by + b, bz + c]
                        gx += sx[a] * wy[b] * wz[c] * v
                        gy += wx[a] * sy[b] * wz[c] * v
                        gz += wx[a] * wy[b] * sz[c] * v
            dx, dy, dz = _limited(-h * gx, -h * gy, -h * gz, max_shift)
            x[q, 0] += dx
            x[q, 1] += dy
            x[q, 2] += dz


def mirror_images(phi: np.ndarray, k0: int) -> None:
    """Fill the node planes below the mirror ``k0`` with the images of those above."""
    for g in range(1, k0 + 1):
        phi[:, :, k0 - g] = phi[:, :, k0 + g]


# --------------------------------------------------------------------------- driver


class DensityProjection:
    """The work arrays and settings of the density projection on one background grid.

    Parameters
    ----------
    node_sdf : ndarray
        Wall distance of every node [m].
    h : float
        Node spacing [m].
    tasks : int
        Parallel particle chunks (one scatter array each).
    mirror_index : int
        Mirror plane of a 3-D grid (-1: none).
    air : float
        Nodes below this share of their capacity are free surface.
    relax : float
        Share of the excess one projection removes, in (0, 1].
    tol : float
        Relative residual of the conjugate gradients.
    max_iter : int
    max_shift : float
        Largest move of a particle in one projection [m] (default half a cell).
    """

    def __init__(self, node_sdf, h, tasks, mirror_index=-1, *, air=0.5, relax=1.0,
                 tol=1e-2, max_iter=500, max_shift=None):  # fmt: skip
        shape = node_sdf.shape
        self.h = float(h)
        self.k0 = int(mirror_index)
        self.air, self.relax, self.tol, self.max_iter = air, relax, tol, int(max_iter)
        self.max_shift = 0.5 * self.h if max_shift is None else float(max_shift)
        self.capacity = node_capacity(node_sdf, h)
        self.code = np.zeros(shape, np.int8)
        self.filled = np.zeros(shape, np.int8)
        self.fill = np.zeros(shape)
        self.rhs = np.zeros(shape)
        self.phi = np.zeros(shape)
        self.scatter_work = np.zeros((tasks, *shape))
        self.iterations = 0  # summed over calls
        self.calls = 0
        self.wall_seconds = 0.0  # summed over calls
        self.worst_fill = 0.0  # the largest node fill seen by the last call

    def node_fill(self, x, vol, origin, starts) -> np.ndarray:
        """The particles' volume per node over the node's volume (mirror images in)."""
        three = x.shape[1] == 3
        scatter = scatter_volume_3d if three else scatter_volume_2d
        scatter(x, vol, origin, 1.0 / self.h, self.scatter_work, starts, self.fill)
        if self.k0 >= 0:
            fold_mirror_scalar(self.fill, self.k0)
        return self.fill

    def __call__(self, x, vol, origin, starts) -> float:
        """Move the particles ``x`` (volumes ``vol``) toward a fill of 1 (in place);
        returns the largest node fill before the move."""
        started = time.perf_counter()
        three = x.shape[1] == 3
        fill = self.node_fill(x, vol, origin, starts)
        (classify_3d if three else classify_2d)(fill, self.capacity, self.air, self.code)
        worst = (excess_3d if three else excess_2d)(
            fill, self.capacity, self.code, self.relax, self.rhs
        )
        self.worst_fill = float(worst)
        self.calls += 1
        # from zero every call: the state of a run is its particles alone, so that a
        # resumed run repeats the projection bit for bit
        self.phi[...] = 0.0
        n, _ = solve_poisson(self.code, self.rhs, self.phi, self.tol, self.max_iter, self.k0)
        self.iterations += n
        extend_to_walls(self.phi, self.code, self.filled)
        if self.k0 >= 0:
            mirror_images(self.phi, self.k0)
        (displace_3d if three else displace_2d)(
            x, self.phi, origin, 1.0 / self.h, self.max_shift, starts
        )
        self.wall_seconds += time.perf_counter() - started
        return worst


def fold_mirror_scalar(field: np.ndarray, k0: int) -> None:
    """A node field scattered from the particles above the mirror plane ``k0`` made that
    of the bed and its image: what went into the ghost plane ``k0 - g`` belongs to
    ``k0 + g`` as well, the plane's own nodes count twice, and the ghosts become images.
    """
    field[:, :, k0] *= 2.0
    for g in range(1, k0 + 1):
        field[:, :, k0 + g] += field[:, :, k0 - g]
    mirror_images(field, k0)
