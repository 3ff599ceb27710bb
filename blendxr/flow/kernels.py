"""Numba kernels of the material point method (MPM) granular flow solver.

Method
------
MLS-MPM (the moving least squares material point method of Hu et al. 2018) with APIC
affine transfers and quadratic B-spline weights, in the vessel frame. Plain float64 arrays
in and out; the driver owns the time loop and all bookkeeping; the constitutive update
(:mod:`blendxr.flow.mohr_coulomb`, scalar code) is called from inside G2P.

Grid: nodes at ``origin + i*h`` (i = 0 .. n-1 per axis, the same ``h`` on every axis);
node arrays have shape (nx, ny) in 2-D and (nx, ny, nz) in 3-D, vector node arrays one more
trailing axis of length d. Particles: positions ``x`` (N, d) [m], velocities ``v`` (N, d)
[m/s], affine matrices ``C`` (N, d, d) [1/s], masses ``m`` (N) [kg], current volumes
``vol`` (N) [m^3], Jacobians ``J`` (N) [1], Cauchy stress ``stress`` (N, 3, 3) [Pa] (always
3 x 3, tension positive; in 2-D plane strain only the in-plane 2 x 2 block makes forces).
In MLS-MPM the affine matrix is the velocity gradient, ``L = C``, so no ``L`` is stored.
Pass C-contiguous float64 arrays (int64 for ``starts``) and Python floats for scalars:
other types work but compile again.

One step is

1. :func:`p2g_3d` scatters mass and MLS-MPM momentum
   ``p_i += w_ip [m_p v_p + (m_p C_p - dt vol_p D^-1 (sigma_p + q_p I))(x_i - x_p)]``,
   ``D^-1 = 4 / h**2``, ``q_p`` the bulk-viscous pressure from ``tr C_p``, into one
   private grid per thread (mass and momentum side by side in each node's d + 1 values:
   one cache line a node for the scatter), and :func:`reduce_grids_3d` sums those into
   node masses and momenta (the internal-force impulse is already in the momentum);
2. :func:`grid_update_3d` turns momentum into velocity and adds gravity, centrifugal,
   Coriolis (an exact rotation), damping and the frictional walls;
3. :func:`g2p_3d` gathers the particle velocity and affine matrix ``C = D^-1 B``,
   advects, updates ``J`` and ``vol`` and updates the stress with ``L = C`` (Jaumann
   rate, Mohr-Coulomb return), all in one pass over the particles;

the driver then puts particles that crossed a wall back with the exact distance
(:mod:`blendxr.flow.walls`). The ``_2d`` kernels are the same in plane strain.
Two passes over the whole particle state per step: at 10^5 particles and more the
particle data (about 250 bytes each) is far larger than the caches, and every pass
streams it from memory.

Stability (the driver's job)
----------------------------
The scheme is explicit: ``dt <= C_cfl * h / (c_p + |v|max)`` with the P-wave speed
``c_p = sqrt((K + 4G/3) / rho)`` and a Courant number ``C_cfl`` below 1 (0.3 - 0.5 is
usual for MLS-MPM; DESIGN section 4); with ``C_cfl < 1`` no particle crosses more than a
cell per step. Gravity, centrifugal and friction impose no limit of their own, and the
Coriolis term is applied as an exact rotation, which is unconditionally stable.

Particle-range precondition (the driver's job)
----------------------------------------------
Every particle's 3 x 3 (x 3) stencil must lie on the grid:
``0.5 <= (x - origin) / h < n - 1.5`` on every axis. The kernels raise nothing and do not
check: :func:`particles_in_range` returns the first offending particle (NaN positions
offend too) and the driver calls it before every P2G. Out-of-range particles are clamped to
the edge stencil, which keeps memory safe but makes their transfer wrong. A grid that holds
the vessel with two nodes to spare on every side keeps wall-projected particles in range.

Parallel loops
--------------
P2G scatters: two particles write the same node, so each of T chunks of the particle range
(``starts``, see :func:`chunk_starts`) scatters into its own private grid, a leading axis of
length T of ``grid``, and :func:`reduce_grids_3d` sums them; no atomics, and
the result does not depend on the thread schedule. Sorting particles by cell now and then
(:func:`sort_by_cell`) keeps each chunk in a slab of the grid, which keeps the scatter in
cache. Every other kernel writes disjoint outputs per iteration of its one ``prange`` loop
(grid planes or particles); :func:`deposit_parts_3d` runs its parts (the phase
averager's halves of the particles) in parallel, each into its own accumulator, and
:func:`deposit_3d` (one part) and the helpers are serial.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .mohr_coulomb import (
    BATCH_BLOCK,
    batch_work,
    eigh3_batch,
    rate_friction,
    read_stress,
    return_batch,
    stress_step,
    trial_batch,
    write_stress,
)

__all__ = [
    "G2P_BLOCK",
    "GRID_MASS_TINY",
    "chunk_starts",
    "deposit_2d",
    "deposit_3d",
    "fastest_particle",
    "fold_mirror_3d",
    "g2p_2d",
    "g2p_3d",
    "g2p_work",
    "gather_rows",
    "grid_update_2d",
    "grid_update_3d",
    "p2g_2d",
    "p2g_3d",
    "particles_in_range",
    "reduce_grids_2d",
    "reduce_grids_3d",
    "sort_by_cell",
]

#: Nodes with no more mass than this [kg] are empty: no velocity, zero written. Far below
#: any real particle mass times a stencil weight, far above the subnormal range, where
#: ``p / m`` would lose its digits.
GRID_MASS_TINY = 1e-250

# Divisions are guarded, so the NumPy error model (no exception path) changes no result.
_JIT = {"parallel": True, "cache": True, "fastmath": False, "error_model": "numpy"}
_JIT_SERIAL = {"cache": True, "fastmath": False, "error_model": "numpy"}
# helpers inlined at numba-IR level into their caller's loop
_JIT_INLINE = {"cache": True, "fastmath": False, "error_model": "numpy", "inline": "always"}

# P2G and G2P run their prange over chunks of particles and call serial helpers per
# chunk: a small parallel loop body compiles much faster than a large one.

#: Particles per block of the 3-D G2P's batched stress update
#: (:data:`blendxr.flow.mohr_coulomb.BATCH_BLOCK`).
G2P_BLOCK = BATCH_BLOCK
#: Particles per sub-block of the 3-D G2P's gather: their 27 node velocities (81 rows
#: of float64) take 20 KiB, within a 32 KiB L1 data cache; a constant, so that LLVM
#: vectorises the sums over the rows (see :func:`_contract_nodes`).
GATHER_WIDTH = 32
_GATHER_ROWS = (81, 12, 12)  # node velocities; weights and offsets; sums


def g2p_work(threads, block=G2P_BLOCK):
    """Work arrays of :func:`g2p_3d` for ``threads`` chunks: the batched stress update's
    (``blendxr.flow.mohr_coulomb.batch_work(threads, block)``), then the gather's flat
    node velocities, weights and sums, (threads, rows * GATHER_WIDTH) each."""
    gather = tuple(np.zeros((threads, rows * GATHER_WIDTH)) for rows in _GATHER_ROWS)
    return batch_work(threads, block) + gather


# ---------------------------------------------------------------------------------------
# Scalar helpers (small; LLVM inlines them into the kernels)
# ---------------------------------------------------------------------------------------


@njit(**_JIT_SERIAL)
def _stencil(f, n):
    """Base node and quadratic B-spline weights along one axis.

    ``f`` is the position in grid units, ``(x - origin) / h``; ``n`` the number of nodes.
    Returns ``(base, r, w0, w1, w2)``: the stencil's nodes are base, base + 1, base + 2,
    ``r = f - base`` lies in [0.5, 1.5) and node base + a sits at ``a - r`` grid units from
    the particle. The base is clamped to [0, n - 3] (in floating point, so NaN is caught):
    an out-of-range particle then stays in memory, though its weights are meaningless.
    """
    b = np.floor(f - 0.5)
    if not b >= 0.0:
        b = 0.0
    elif b > n - 3:
        b = float(n - 3)
    r = f - b
    return int(b), r, 0.5 * (1.5 - r) ** 2, 0.75 - (r - 1.0) ** 2, 0.5 * (r - 0.5) ** 2


@njit(**_JIT_SERIAL)
def _wall_2d(vx, vy, nx, ny, mu):
    """Frictional wall contact: drop an inward normal velocity, Coulomb-slow the rest."""
    vn = vx * nx + vy * ny
    if not vn > 0.0:
        return vx, vy
    tx = vx - vn * nx
    ty = vy - vn * ny
    vt = math.sqrt(tx * tx + ty * ty)
    if vt <= mu * vn:
        return 0.0, 0.0
    s = 1.0 - mu * vn / vt
    return tx * s, ty * s


@njit(**_JIT_SERIAL)
def _wall_3d(vx, vy, vz, nx, ny, nz, mu):
    """Frictional wall contact: drop an inward normal velocity, Coulomb-slow the rest."""
    vn = vx * nx + vy * ny + vz * nz
    if not vn > 0.0:
        return vx, vy, vz
    tx = vx - vn * nx
    ty = vy - vn * ny
    tz = vz - vn * nz
    vt = math.sqrt(tx * tx + ty * ty + tz * tz)
    if vt <= mu * vn:
        return 0.0, 0.0, 0.0
    s = 1.0 - mu * vn / vt
    return tx * s, ty * s, tz * s


@njit(**_JIT_SERIAL)
def _bulk_pressure(rate, bulk):
    """Bulk-viscous pressure ``q = linear tr(L) + quadratic min(tr(L), 0) |tr(L)|`` [Pa].

    ``bulk = (linear, quadratic)`` with linear = rho h b1 c_p [Pa s] and quadratic =
    rho (b2 h)**2 [kg/m]: the linear and quadratic bulk viscosity of explicit dynamics
    codes, added to the stress P2G uses (not to the stress history). Elastic waves in the
    rigidly moving parts of a bed are otherwise undamped (neither the material nor APIC
    dissipates them) and ring on for whole revolutions; q acts only on volume change, so
    shear flow and rigid motion are untouched. ``rate = tr(C)`` is tr(L): in MLS-MPM the
    affine matrix is the velocity gradient.
    """
    q = bulk[0] * rate
    if rate < 0.0:
        q += bulk[1] * (-rate) * rate
    return q


@njit(**_JIT_SERIAL)
def _zero(a):
    """Zero a C-contiguous array in place (a plain loop: no parfor inside a prange)."""
    flat = a.reshape(a.size)
    for k in range(flat.size):
        flat[k] = 0.0


# ---------------------------------------------------------------------------------------
# Driver helpers
# ---------------------------------------------------------------------------------------


def chunk_starts(n_particles, n_chunks):
    """Split ``range(n_particles)`` into ``n_chunks`` contiguous, nearly equal chunks.

    Parameters
    ----------
    n_particles, n_chunks : int
        Number of particles and of chunks (private grids, usually the thread count).

    Returns
    -------
    ndarray of int64, shape (n_chunks + 1,)
        Chunk ``t`` is ``starts[t]:starts[t + 1]``; ``starts[0] = 0``,
        ``starts[-1] = n_particles``.
    """
    return (np.arange(n_chunks + 1, dtype=np.int64) * n_particles) // n_chunks


@njit(**_JIT_SERIAL)
def particles_in_range(x, origin, inv_h, shape):
    """First particle whose P2G/G2P stencil leaves the grid, or -1.

    Parameters
    ----------
    x : ndarray of float64, shape (N, d)
        Particle positions [m].
    origin : ndarray of float64, shape (d,)
        Position of node 0 [m].
    inv_h : float
        Inverse node spacing [1/m].
    shape : tuple of int or ndarray of int64, length d
        Nodes per axis.

    Returns
    -------
    int
        Index of the first particle with ``(x - origin) / h`` outside [0.5, n - 1.5) on
        some axis (or NaN), -1 when every particle is in range.
    """
    n, d = x.shape
    for p in range(n):
        for a in range(d):
            f = (x[p, a] - origin[a]) * inv_h
            if not (0.5 <= f < shape[a] - 1.5):
                return p
    return -1


@njit(**_JIT_SERIAL)
def sort_by_cell(x, origin, inv_h, shape):
    """Permutation that orders particles by grid cell, x-major (stable counting sort).

    The cell of a particle is ``floor((x - origin) / h)`` per axis, clamped to the grid;
    the order is by (ix, iy[, iz]) with iz fastest, and particles of one cell keep their
    order. Apply it to every particle array (``x = x[perm]`` ...) every few tens of steps,
    so that the P2G chunks cover compact slabs of the grid.

    Parameters
    ----------
    x : ndarray of float64, shape (N, d)
        Particle positions [m].
    origin : ndarray of float64, shape (d,)
        Position of node 0 [m].
    inv_h : float
        Inverse node spacing [1/m].
    shape : tuple of int or ndarray of int64, length d
        Nodes per axis.

    Returns
    -------
    ndarray of int64, shape (N,)
    """
    n, d = x.shape
    n_cells = 1
    for a in range(d):
        n_cells *= shape[a]
    keys = np.empty(n, np.int64)
    for p in range(n):
        key = 0
        for a in range(d):
            c = np.floor((x[p, a] - origin[a]) * inv_h)
            if not c >= 0.0:
                c = 0.0
            elif c > shape[a] - 1:
                c = float(shape[a] - 1)
            key = key * shape[a] + int(c)
        keys[p] = key
    first = np.zeros(n_cells + 1, np.int64)
    for p in range(n):
        first[keys[p] + 1] += 1
    for k in range(n_cells):
        first[k + 1] += first[k]
    perm = np.empty(n, np.int64)
    for p in range(n):
        perm[first[keys[p]]] = p
        first[keys[p]] += 1
    return perm


@njit(**_JIT)
def fastest_particle(v, starts, scratch):
    """The first particle of greatest speed, one whose speed is not finite before all.

    Parameters
    ----------
    v : ndarray of float64, shape (N, d)
        Particle velocities [m/s].
    starts : ndarray of int64, shape (T + 1,)
        Contiguous particle chunks, one per parallel task (:func:`chunk_starts`).
    scratch : ndarray of float64, shape (T, >= 2)
        Per-task workspace: receives each task's key and particle.

    Returns
    -------
    int
        The particle's index (-1 with no particles).
    """
    d = v.shape[1]
    tasks = starts.shape[0] - 1
    for t in prange(tasks):
        best = -1.0
        at = -1
        for p in range(starts[t], starts[t + 1]):
            square = 0.0
            for a in range(d):
                square += v[p, a] * v[p, a]
            if not math.isfinite(square):
                best = math.inf
                at = p
                break
            if square > best:
                best = square
                at = p
        scratch[t, 0] = best
        scratch[t, 1] = at
    best = -1.0
    at = -1
    for t in range(tasks):
        if scratch[t, 0] > best:
            best = scratch[t, 0]
            at = int(scratch[t, 1])
    return at


@njit(**_JIT)
def gather_rows(source, order, out):
    """``out[i] = source[order[i]]`` row by row, in parallel over the rows.

    Applies a re-sort's permutation (:func:`sort_by_cell`) to one particle array viewed
    as (N, k) into a preallocated array of the same shape, so that the re-sort allocates
    nothing (the driver swaps the two, double-buffered).

    Parameters
    ----------
    source : ndarray of float64, shape (N, k)
        The array in its old order (read only).
    order : ndarray of int64, shape (N,)
        A permutation of ``range(N)``.
    out : ndarray of float64, shape (N, k)
        Receives the rows in the new order; must not share memory with ``source``.
    """
    n, k = out.shape
    for i in prange(n):
        row = order[i]
        for j in range(k):
            out[i, j] = source[row, j]


# ---------------------------------------------------------------------------------------
# P2G: particles to private grids, then the sum over the private grids
# ---------------------------------------------------------------------------------------


@njit(**_JIT_SERIAL)
def _p2g_chunk_2d(lo, hi, x, v, C, m, vol, stress, origin, inv_h, dt, bulk, gq):
    """Zero one private grid and scatter particles lo:hi into it (see :func:`p2g_2d`)."""
    _zero(gq)
    nx, ny = gq.shape[0], gq.shape[1]
    h = 1.0 / inv_h
    stress_scale = 4.0 * inv_h * inv_h * dt  # dt * D^-1
    for p in range(lo, hi):
        bx, rx, wx0, wx1, wx2 = _stencil((x[p, 0] - origin[0]) * inv_h, nx)
        by, ry, wy0, wy1, wy2 = _stencil((x[p, 1] - origin[1]) * inv_h, ny)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        mp = m[p]
        s = stress_scale * vol[p]
        mv0 = mp * v[p, 0]
        mv1 = mp * v[p, 1]
        pressure = _bulk_pressure(C[p, 0, 0] + C[p, 1, 1], bulk)
        # affine momentum Q = m C - dt vol D^-1 (sigma + q I), times h: it acts on offsets
        # measured in grid units
        q00 = (mp * C[p, 0, 0] - s * (stress[p, 0, 0] + pressure)) * h
        q01 = (mp * C[p, 0, 1] - s * stress[p, 0, 1]) * h
        q10 = (mp * C[p, 1, 0] - s * stress[p, 1, 0]) * h
        q11 = (mp * C[p, 1, 1] - s * (stress[p, 1, 1] + pressure)) * h
        for a in range(3):
            dx = a - rx
            pa0 = mv0 + q00 * dx
            pa1 = mv1 + q10 * dx
            i = bx + a
            for b in range(3):
                dy = b - ry
                w = wx[a] * wy[b]
                j = by + b
                gq[i, j, 0] += w * mp
                gq[i, j, 1] += w * (pa0 + q01 * dy)
                gq[i, j, 2] += w * (pa1 + q11 * dy)


@njit(**_JIT_SERIAL)
def _p2g_chunk_3d(lo, hi, x, v, C, m, vol, stress, origin, inv_h, dt, bulk, gq):
    """Zero one private grid and scatter particles lo:hi into it (see :func:`p2g_3d`)."""
    _zero(gq)
    nx, ny, nz = gq.shape[0], gq.shape[1], gq.shape[2]
    h = 1.0 / inv_h
    stress_scale = 4.0 * inv_h * inv_h * dt  # dt * D^-1
    # unsigned offsets into the flat grid: no index needs a negative-index check
    flat = gq.reshape(-1)
    line_x = np.uint64(ny * nz * 4)
    line_y = np.uint64(nz * 4)
    for p in range(lo, hi):
        bx, rx, wx0, wx1, wx2 = _stencil((x[p, 0] - origin[0]) * inv_h, nx)
        by, ry, wy0, wy1, wy2 = _stencil((x[p, 1] - origin[1]) * inv_h, ny)
        bz, rz, wz0, wz1, wz2 = _stencil((x[p, 2] - origin[2]) * inv_h, nz)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        mp = m[p]
        s = stress_scale * vol[p]
        mv0 = mp * v[p, 0]
        mv1 = mp * v[p, 1]
        mv2 = mp * v[p, 2]
        pressure = _bulk_pressure(C[p, 0, 0] + C[p, 1, 1] + C[p, 2, 2], bulk)
        # affine momentum Q = m C - dt vol D^-1 (sigma + q I), times h (offsets in grid units)
        q00 = (mp * C[p, 0, 0] - s * (stress[p, 0, 0] + pressure)) * h
        q01 = (mp * C[p, 0, 1] - s * stress[p, 0, 1]) * h
        q02 = (mp * C[p, 0, 2] - s * stress[p, 0, 2]) * h
        q10 = (mp * C[p, 1, 0] - s * stress[p, 1, 0]) * h
        q11 = (mp * C[p, 1, 1] - s * (stress[p, 1, 1] + pressure)) * h
        q12 = (mp * C[p, 1, 2] - s * stress[p, 1, 2]) * h
        q20 = (mp * C[p, 2, 0] - s * stress[p, 2, 0]) * h
        q21 = (mp * C[p, 2, 1] - s * stress[p, 2, 1]) * h
        q22 = (mp * C[p, 2, 2] - s * (stress[p, 2, 2] + pressure)) * h
        for a in range(3):
            dx = a - rx
            pa0 = mv0 + q00 * dx
            pa1 = mv1 + q10 * dx
            pa2 = mv2 + q20 * dx
            i = bx + a
            for b in range(3):
                dy = b - ry
                pb0 = pa0 + q01 * dy
                pb1 = pa1 + q11 * dy
                pb2 = pa2 + q21 * dy
                wab = wx[a] * wy[b]
                j = by + b
                # the line of three nodes along z: twelve adjacent numbers of the flat grid
                q = np.uint64(i) * line_x + np.uint64(j) * line_y + np.uint64(4 * bz)
                for c in range(3):
                    dz = c - rz
                    w = wab * wz[c]
                    k = q + np.uint64(4 * c)
                    flat[k] += w * mp
                    flat[k + np.uint64(1)] += w * (pb0 + q02 * dz)
                    flat[k + np.uint64(2)] += w * (pb1 + q12 * dz)
                    flat[k + np.uint64(3)] += w * (pb2 + q22 * dz)


@njit(**_JIT)
def p2g_2d(x, v, C, m, vol, stress, origin, inv_h, dt, bulk, grid, starts):
    """Scatter mass and MLS-MPM momentum to per-chunk private grids (2-D plane strain).

    Parameters
    ----------
    x, v : ndarray of float64, shape (N, 2)
        Particle positions [m] and velocities [m/s].
    C : ndarray of float64, shape (N, 2, 2)
        APIC affine matrices [1/s].
    m, vol : ndarray of float64, shape (N,)
        Masses [kg] and current volumes [m^3] (per metre of depth in 2-D).
    stress : ndarray of float64, shape (N, 3, 3)
        Cauchy stress [Pa], tension positive; the in-plane 2 x 2 block is used.
    origin : ndarray of float64, shape (2,)
        Position of node 0 [m].
    inv_h, dt : float
        Inverse node spacing [1/m], time step [s].
    bulk : tuple of float
        ``(linear, quadratic)`` bulk viscosity, see :func:`_bulk_pressure`; (0.0, 0.0)
        for none.
    grid : ndarray of float64, shape (T, nx, ny, 3)
        Receives each chunk's node masses [kg] (``[..., 0]``) and momenta [kg m/s]
        (``[..., 1:]``, including the internal-force impulse); zeroed here first.
    starts : ndarray of int64, shape (T + 1,)
        Chunk t holds particles ``starts[t]:starts[t + 1]`` (see :func:`chunk_starts`).

    Notes
    -----
    Precondition: every particle in range (:func:`particles_in_range`). Sum the private
    grids with :func:`reduce_grids_2d`. T may exceed the thread count (still correct).
    """
    for t in prange(grid.shape[0]):
        _p2g_chunk_2d(
            starts[t], starts[t + 1], x, v, C, m, vol, stress, origin, inv_h, dt, bulk,
            grid[t],
        )  # fmt: skip


@njit(**_JIT)
def p2g_3d(x, v, C, m, vol, stress, origin, inv_h, dt, bulk, grid, starts):
    """Scatter mass and MLS-MPM momentum to per-chunk private grids (3-D).

    Parameters
    ----------
    x, v : ndarray of float64, shape (N, 3)
        Particle positions [m] and velocities [m/s].
    C : ndarray of float64, shape (N, 3, 3)
        APIC affine matrices [1/s].
    m, vol : ndarray of float64, shape (N,)
        Masses [kg] and current volumes [m^3].
    stress : ndarray of float64, shape (N, 3, 3)
        Cauchy stress [Pa], tension positive.
    origin : ndarray of float64, shape (3,)
        Position of node 0 [m].
    inv_h, dt : float
        Inverse node spacing [1/m], time step [s].
    bulk : tuple of float
        ``(linear, quadratic)`` bulk viscosity, see :func:`_bulk_pressure`; (0.0, 0.0)
        for none.
    grid : ndarray of float64, shape (T, nx, ny, nz, 4)
        Receives each chunk's node masses [kg] (``[..., 0]``) and momenta [kg m/s]
        (``[..., 1:]``, including the internal-force impulse); zeroed here first. Side by
        side, a node's four values share a cache line: the scatter runs about a fifth
        faster than into separate mass and momentum arrays (measured, one thread).
    starts : ndarray of int64, shape (T + 1,)
        Chunk t holds particles ``starts[t]:starts[t + 1]`` (see :func:`chunk_starts`).

    Notes
    -----
    Precondition: every particle in range (:func:`particles_in_range`). Sum the private
    grids with :func:`reduce_grids_3d`. T may exceed the thread count (still correct).
    """
    for t in prange(grid.shape[0]):
        _p2g_chunk_3d(
            starts[t], starts[t + 1], x, v, C, m, vol, stress, origin, inv_h, dt, bulk,
            grid[t],
        )  # fmt: skip


@njit(**_JIT)
def reduce_grids_2d(grid, out_m, out_p):
    """Sum the private grids of :func:`p2g_2d` over their leading (chunk) axis.

    Parameters
    ----------
    grid : ndarray of float64, shape (T, nx, ny, 3)
        Each chunk's node masses and momenta, as :func:`p2g_2d` leaves them.
    out_m : ndarray of float64, shape (nx, ny)
        Receives the node masses [kg].
    out_p : ndarray of float64, shape (nx, ny, 2)
        Receives the node momenta [kg m/s].
    """
    n_chunks, nx, ny = grid.shape[0], grid.shape[1], grid.shape[2]
    for i in prange(nx):
        for j in range(ny):
            mass = grid[0, i, j, 0]
            p0 = grid[0, i, j, 1]
            p1 = grid[0, i, j, 2]
            for t in range(1, n_chunks):
                mass += grid[t, i, j, 0]
                p0 += grid[t, i, j, 1]
                p1 += grid[t, i, j, 2]
            out_m[i, j] = mass
            out_p[i, j, 0] = p0
            out_p[i, j, 1] = p1


@njit(**_JIT)
def reduce_grids_3d(grid, out_m, out_p):
    """Sum the private grids of :func:`p2g_3d` over their leading (chunk) axis.

    Parameters
    ----------
    grid : ndarray of float64, shape (T, nx, ny, nz, 4)
        Each chunk's node masses and momenta, as :func:`p2g_3d` leaves them.
    out_m : ndarray of float64, shape (nx, ny, nz)
        Receives the node masses [kg].
    out_p : ndarray of float64, shape (nx, ny, nz, 3)
        Receives the node momenta [kg m/s].
    """
    n_chunks, nx, ny, nz = grid.shape[0], grid.shape[1], grid.shape[2], grid.shape[3]
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                mass = grid[0, i, j, k, 0]
                p0 = grid[0, i, j, k, 1]
                p1 = grid[0, i, j, k, 2]
                p2 = grid[0, i, j, k, 3]
                for t in range(1, n_chunks):
                    mass += grid[t, i, j, k, 0]
                    p0 += grid[t, i, j, k, 1]
                    p1 += grid[t, i, j, k, 2]
                    p2 += grid[t, i, j, k, 3]
                out_m[i, j, k] = mass
                out_p[i, j, k, 0] = p0
                out_p[i, j, k, 1] = p1
                out_p[i, j, k, 2] = p2


@njit(**_JIT)
def fold_mirror_3d(out_m, out_p, k0):
    """Make the node fields those of the bed and its mirror image across a plane z = z0.

    For a flow that is mirror-symmetric about the node plane ``k = k0`` the driver keeps
    only the particles on its upper side (``z >= z0``). Their mirror images would put
    into node ``k0 + g`` what the kept particles put into node ``k0 - g``, with the z
    momentum reversed; this adds that in (the plane's own nodes get their mass doubled
    and no z momentum), then writes the mirror image of the upper nodes onto the ghost
    nodes below the plane, so that the grid update and the gather see the whole
    symmetric field. Exact: the result equals a P2G of the bed and its mirror image.

    Parameters
    ----------
    out_m : ndarray of float64, shape (nx, ny, nz)
        Node masses [kg] from :func:`reduce_grids_3d`, folded in place.
    out_p : ndarray of float64, shape (nx, ny, nz, 3)
        Node momenta [kg m/s], folded in place.
    k0 : int
        Index of the mirror plane's nodes, ``1 <= k0``, ``2 k0 < nz`` (the ghost nodes
        ``0 .. k0 - 1`` must have their images on the grid).
    """
    nx, ny, nz = out_m.shape
    for i in prange(nx):
        for j in range(ny):
            out_m[i, j, k0] *= 2.0
            out_p[i, j, k0, 0] *= 2.0
            out_p[i, j, k0, 1] *= 2.0
            out_p[i, j, k0, 2] = 0.0
            for g in range(1, k0 + 1):
                up = k0 + g
                down = k0 - g
                mass = out_m[i, j, up] + out_m[i, j, down]
                p0 = out_p[i, j, up, 0] + out_p[i, j, down, 0]
                p1 = out_p[i, j, up, 1] + out_p[i, j, down, 1]
                p2 = out_p[i, j, up, 2] - out_p[i, j, down, 2]
                out_m[i, j, up] = mass
                out_p[i, j, up, 0] = p0
                out_p[i, j, up, 1] = p1
                out_p[i, j, up, 2] = p2
                out_m[i, j, down] = mass
                out_p[i, j, down, 0] = p0
                out_p[i, j, down, 1] = p1
                out_p[i, j, down, 2] = -p2


# ---------------------------------------------------------------------------------------
# Grid update
# ---------------------------------------------------------------------------------------


@njit(**_JIT)
def grid_update_2d(
    out_m,
    out_p,
    vel,
    origin,
    h,
    dt,
    gravity,
    omega,
    damping,
    node_sdf,
    node_normal,
    mu_wall,
    band,
):
    """Node velocities after body forces, Coriolis, damping and walls (2-D plane strain).

    At each node with mass above :data:`GRID_MASS_TINY`, in this order:

    1. ``v = p / m`` (the internal-force impulse is already in ``p``);
    2. ``v += dt * (gravity + omega**2 * (x, y))`` (gravity in the vessel frame,
       centrifugal for rotation about z through the origin);
    3. Coriolis ``dv/dt = -2 omega z x v`` integrated exactly over dt: (vx, vy) rotated by
       the angle ``-2 omega dt``. A rotation keeps ``|v|``: unconditionally stable and
       energy-preserving, as the fictitious force does no work;
    4. ``v *= 1 - damping``;
    5. walls, where ``node_sdf > -band``: if ``vn = v . n > 0`` (into the wall) the normal
       part is removed and the tangential part slowed by Coulomb friction,
       ``vt <- vt max(0, 1 - mu_wall vn / |vt|)``: the friction impulse is bounded by the
       normal impulse removed. Nodes outside the vessel follow the same rule.

    Parameters
    ----------
    out_m : ndarray of float64, shape (nx, ny)
        Node masses [kg].
    out_p : ndarray of float64, shape (nx, ny, 2)
        Node momenta [kg m/s].
    vel : ndarray of float64, shape (nx, ny, 2)
        Receives node velocities [m/s] (zero at nodes without mass).
    origin : ndarray of float64, shape (2,)
        Position of node 0 [m], relative to the rotation axis.
    h, dt : float
        Node spacing [m], time step [s].
    gravity : ndarray of float64, shape (2,)
        Gravity in the vessel frame [m/s^2].
    omega : float
        Angular velocity of the vessel about +z [rad/s].
    damping : float
        Velocity damping per step, in [0, 1) (settling only; 0 otherwise).
    node_sdf : ndarray of float64, shape (nx, ny)
        Signed distance to the vessel wall at the nodes [m], negative inside.
    node_normal : ndarray of float64, shape (nx, ny, 2)
        Outward unit wall normals at the nodes (not renormalised here).
    mu_wall : float
        Wall friction coefficient.
    band : float
        Contact band [m], >= 0: nodes with ``node_sdf > -band`` feel the wall.
    """
    nx, ny = out_m.shape
    w2 = omega * omega
    cos_c = math.cos(2.0 * omega * dt)
    sin_c = math.sin(2.0 * omega * dt)
    keep = 1.0 - damping
    for i in prange(nx):
        px = origin[0] + i * h
        for j in range(ny):
            mass = out_m[i, j]
            if not mass > GRID_MASS_TINY:
                vel[i, j, 0] = 0.0
                vel[i, j, 1] = 0.0
                continue
            py = origin[1] + j * h
            vx = out_p[i, j, 0] / mass + dt * (gravity[0] + w2 * px)
            vy = out_p[i, j, 1] / mass + dt * (gravity[1] + w2 * py)
            vx, vy = (vx * cos_c + vy * sin_c) * keep, (vy * cos_c - vx * sin_c) * keep
            if node_sdf[i, j] > -band:
                vx, vy = _wall_2d(vx, vy, node_normal[i, j, 0], node_normal[i, j, 1], mu_wall)
            vel[i, j, 0] = vx
            vel[i, j, 1] = vy


@njit(**_JIT)
def grid_update_3d(
    out_m,
    out_p,
    vel,
    origin,
    h,
    dt,
    gravity,
    omega,
    damping,
    node_sdf,
    node_normal,
    mu_wall,
    band,
):
    """Node velocities after body forces, Coriolis, damping and walls (3-D).

    As :func:`grid_update_2d`, with node arrays of shape (nx, ny, nz) and vector arrays of
    shape (nx, ny, nz, 3). Centrifugal acceleration is ``omega**2 * (x, y, 0)``; Coriolis
    rotates (vx, vy) by ``-2 omega dt`` and leaves vz.

    Parameters
    ----------
    out_m : ndarray of float64, shape (nx, ny, nz)
        Node masses [kg].
    out_p : ndarray of float64, shape (nx, ny, nz, 3)
        Node momenta [kg m/s].
    vel : ndarray of float64, shape (nx, ny, nz, 3)
        Receives node velocities [m/s] (zero at nodes without mass).
    origin : ndarray of float64, shape (3,)
        Position of node 0 [m], relative to the rotation axis.
    h, dt : float
        Node spacing [m], time step [s].
    gravity : ndarray of float64, shape (3,)
        Gravity in the vessel frame [m/s^2].
    omega : float
        Angular velocity of the vessel about +z [rad/s].
    damping : float
        Velocity damping per step, in [0, 1).
    node_sdf : ndarray of float64, shape (nx, ny, nz)
        Signed distance to the vessel wall at the nodes [m], negative inside.
    node_normal : ndarray of float64, shape (nx, ny, nz, 3)
        Outward unit wall normals at the nodes.
    mu_wall : float
        Wall friction coefficient.
    band : float
        Contact band [m], >= 0.
    """
    nx, ny, nz = out_m.shape
    w2 = omega * omega
    cos_c = math.cos(2.0 * omega * dt)
    sin_c = math.sin(2.0 * omega * dt)
    keep = 1.0 - damping
    for i in prange(nx):
        ax = dt * (gravity[0] + w2 * (origin[0] + i * h))
        for j in range(ny):
            ay = dt * (gravity[1] + w2 * (origin[1] + j * h))
            for k in range(nz):
                mass = out_m[i, j, k]
                if not mass > GRID_MASS_TINY:
                    vel[i, j, k, 0] = 0.0
                    vel[i, j, k, 1] = 0.0
                    vel[i, j, k, 2] = 0.0
                    continue
                vx = out_p[i, j, k, 0] / mass + ax
                vy = out_p[i, j, k, 1] / mass + ay
                vz = (out_p[i, j, k, 2] / mass + dt * gravity[2]) * keep
                vx, vy = (vx * cos_c + vy * sin_c) * keep, (vy * cos_c - vx * sin_c) * keep
                if node_sdf[i, j, k] > -band:
                    vx, vy, vz = _wall_3d(
                        vx,
                        vy,
                        vz,
                        node_normal[i, j, k, 0],
                        node_normal[i, j, k, 1],
                        node_normal[i, j, k, 2],
                        mu_wall,
                    )
                vel[i, j, k, 0] = vx
                vel[i, j, k, 1] = vy
                vel[i, j, k, 2] = vz


# ---------------------------------------------------------------------------------------
# G2P
#
# The gather sums w_i v_i and B = sum w_i v_i (x_i - x_p)^T. Offsets are measured in grid
# units, so B is built as sum w_i v_i i - (sum w_i v_i) r, and the weights factor per
# axis: each line of three nodes along the last axis is summed first (with its first
# moment), then the lines are weighted. That needs a third fewer operations than the
# node-by-node form, and the three nodes of a line are adjacent in memory.
# ---------------------------------------------------------------------------------------


@njit(**_JIT_SERIAL)
def _bounded_gap(gap, packing):
    """The contact gap a particle may keep where the grid holds ``packing`` times the
    seeded packing's mass: at most ``1 - packing``, the volume per unit volume that the
    material around it really lacks.

    The gap itself integrates the divergence of the particle's own motion, which drifts
    from the packing it describes (a gap opened by the noisy divergence of stress-free
    particles would close more than the grains had opened, and a bed compacts past its
    seeded packing); the node masses are exact and conserved, so where the material is
    at its seeded packing or denser no volume is left to close without stress.
    """
    return min(gap, max(0.0, 1.0 - packing))


@njit(**_JIT_SERIAL)
def _stress_update(stress, codes, gap, p, l, dt, material):
    """Mohr-Coulomb update of particle p's stress (and contact gap) with the gradient ``l``."""
    old = read_stress(stress, p)
    sin_phi, cos_phi = rate_friction(
        l, old, material[2], material[3], material[8], material[9], material[10]
    )
    s, codes[p], gap[p] = stress_step(
        old, l, dt, material[0], material[1], sin_phi, cos_phi, material[4], material[5],
        material[6], gap[p], material[7] > 0.0,
    )  # fmt: skip
    write_stress(stress, p, s)


@njit(**_JIT_SERIAL)
def _g2p_range_2d(
    lo, hi, x, v, C, vol, J, gap, stress, codes, vel, mass, origin, inv_h, dt, material
):
    """G2P and stress update of particles lo:hi (see :func:`g2p_2d`)."""
    nx, ny = vel.shape[0], vel.shape[1]
    contact = material[7] > 0.0
    scale = 4.0 * inv_h  # D^-1 times h: B is in grid units
    for p in range(lo, hi):
        bx, rx, wx0, wx1, wx2 = _stencil((x[p, 0] - origin[0]) * inv_h, nx)
        by, ry, wy0, wy1, wy2 = _stencil((x[p, 1] - origin[1]) * inv_h, ny)
        wx = (wx0, wx1, wx2)
        wy2b = 2.0 * wy2
        v0 = 0.0
        v1 = 0.0
        b00 = 0.0
        b01 = 0.0
        b10 = 0.0
        b11 = 0.0
        for a in range(3):
            i = bx + a
            wa = wx[a]
            u00 = vel[i, by, 0]
            u01 = vel[i, by, 1]
            u10 = vel[i, by + 1, 0]
            u11 = vel[i, by + 1, 1]
            u20 = vel[i, by + 2, 0]
            u21 = vel[i, by + 2, 1]
            l0 = wa * (wy0 * u00 + wy1 * u10 + wy2 * u20)
            l1 = wa * (wy0 * u01 + wy1 * u11 + wy2 * u21)
            v0 += l0
            v1 += l1
            b01 += wa * (wy1 * u10 + wy2b * u20)
            b11 += wa * (wy1 * u11 + wy2b * u21)
            if a > 0:
                b00 += a * l0
                b10 += a * l1
        if contact and gap[p] > 0.0:
            # a closed gap stays closed whatever the packing: no mass gather
            packing = 0.0
            for a in range(3):
                i = bx + a
                packing += wx[a] * (
                    wy0 * mass[i, by] + wy1 * mass[i, by + 1] + wy2 * mass[i, by + 2]
                )
            gap[p] = _bounded_gap(gap[p], packing * material[7])
        c00 = scale * (b00 - v0 * rx)
        c01 = scale * (b01 - v0 * ry)
        c10 = scale * (b10 - v1 * rx)
        c11 = scale * (b11 - v1 * ry)
        C[p, 0, 0] = c00
        C[p, 0, 1] = c01
        C[p, 1, 0] = c10
        C[p, 1, 1] = c11
        growth = (1.0 + dt * c00) * (1.0 + dt * c11) - dt * dt * c01 * c10
        J[p] *= growth
        vol[p] *= growth
        x[p, 0] += dt * v0
        x[p, 1] += dt * v1
        v[p, 0] = v0
        v[p, 1] = v1
        l = (c00, c01, 0.0, c10, c11, 0.0, 0.0, 0.0, 0.0)
        _stress_update(stress, codes, gap, p, l, dt, material)


@njit(**_JIT_SERIAL)
def _packing(x, p, mass, origin, inv_h):
    """Σ w m_i of particle p's stencil: the node mass around it."""
    nx, ny, nz = mass.shape
    bx, _, wx0, wx1, wx2 = _stencil((x[p, 0] - origin[0]) * inv_h, nx)
    by, _, wy0, wy1, wy2 = _stencil((x[p, 1] - origin[1]) * inv_h, ny)
    bz, _, wz0, wz1, wz2 = _stencil((x[p, 2] - origin[2]) * inv_h, nz)
    wx = (wx0, wx1, wx2)
    wy = (wy0, wy1, wy2)
    packing = 0.0
    for a in range(3):
        i = bx + a
        for b in range(3):
            j = by + b
            packing += (wx[a] * wy[b]) * (
                wz0 * mass[i, j, bz] + wz1 * mass[i, j, bz + 1] + wz2 * mass[i, j, bz + 2]
            )
    return packing


@njit(**_JIT_SERIAL)
def _gather_nodes(lo, m, x, flat, origin, inv_h, shape, nodes, weights):
    """Stencil weights and the 27 node velocities of particles lo .. lo + m - 1, one
    particle a column of the flat work arrays (row r at ``r * GATHER_WIDTH``).

    ``weights`` rows: wx0..2, wy0..2, wz0..2, rx, ry, rz; ``nodes`` row ``9 (3 a + b) +
    c``: number c of the line of three nodes along z at offsets (a, b), that is node c // 3,
    component c % 3.
    """
    nx, ny, nz = shape
    line_x = np.uint64(ny * nz * 3)
    line_y = np.uint64(nz * 3)
    for k in range(m):
        p = lo + k
        bx, rx, wx0, wx1, wx2 = _stencil((x[p, 0] - origin[0]) * inv_h, nx)
        by, ry, wy0, wy1, wy2 = _stencil((x[p, 1] - origin[1]) * inv_h, ny)
        bz, rz, wz0, wz1, wz2 = _stencil((x[p, 2] - origin[2]) * inv_h, nz)
        w = (wx0, wx1, wx2, wy0, wy1, wy2, wz0, wz1, wz2, rx, ry, rz)
        for r in range(12):
            weights[r * GATHER_WIDTH + k] = w[r]
        for a in range(3):
            for b in range(3):
                q = np.uint64(bx + a) * line_x + np.uint64(by + b) * line_y + np.uint64(3 * bz)
                row = 9 * (3 * a + b)
                for c in range(9):
                    nodes[(row + c) * GATHER_WIDTH + k] = flat[q + np.uint64(c)]


@njit(inline="always", **_JIT_SERIAL)
def _line(nodes, row, k, wab, wz):
    """One line of three nodes along z in column k (rows ``row`` .. ``row + 8``): its
    share of v, ``wab (wz0 u0 + wz1 u1 + wz2 u2)``, and of B's z column, ``wab (wz1 u1 +
    2 wz2 u2)``."""
    W = GATHER_WIDTH
    wz0, wz1, wz2 = wz
    wz2b = 2.0 * wz2
    u00 = nodes[row * W + k]
    u01 = nodes[(row + 1) * W + k]
    u02 = nodes[(row + 2) * W + k]
    u10 = nodes[(row + 3) * W + k]
    u11 = nodes[(row + 4) * W + k]
    u12 = nodes[(row + 5) * W + k]
    u20 = nodes[(row + 6) * W + k]
    u21 = nodes[(row + 7) * W + k]
    u22 = nodes[(row + 8) * W + k]
    return (
        wab * (wz0 * u00 + wz1 * u10 + wz2 * u20),
        wab * (wz0 * u01 + wz1 * u11 + wz2 * u21),
        wab * (wz0 * u02 + wz1 * u12 + wz2 * u22),
        wab * (wz1 * u10 + wz2b * u20),
        wab * (wz1 * u11 + wz2b * u21),
        wab * (wz1 * u12 + wz2b * u22),
    )


@njit(inline="always", **_JIT_SERIAL)
def _accumulate(acc, a, b, line):
    """Add the line at stencil offsets (a, b) to (v0, v1, v2, b00, b01, ..., b22)."""
    v0, v1, v2, b00, b01, b02, b10, b11, b12, b20, b21, b22 = acc
    l0, l1, l2, m0, m1, m2 = line
    v0 += l0
    v1 += l1
    v2 += l2
    b02 += m0
    b12 += m1
    b22 += m2
    if a > 0:
        b00 += a * l0
        b10 += a * l1
        b20 += a * l2
    if b > 0:
        b01 += b * l0
        b11 += b * l1
        b21 += b * l2
    return v0, v1, v2, b00, b01, b02, b10, b11, b12, b20, b21, b22


@njit(**_JIT_SERIAL)
def _contract_nodes(nodes, weights, sums, m):
    """Sums of :func:`_gather_nodes`' columns: v and the nine sums of B (rows 0..2 and
    3..11 of ``sums``: b00, b01, ..., b22). A SIMD loop over the particles, each doing
    the scalar gather's operations (see above) in its order, so the same bits; the nine
    lines are written out, so that no loop is left inside the one LLVM vectorises."""
    W = GATHER_WIDTH
    for k in range(m):
        wx0, wx1, wx2 = weights[k], weights[W + k], weights[2 * W + k]
        wy0, wy1, wy2 = weights[3 * W + k], weights[4 * W + k], weights[5 * W + k]
        wz = (weights[6 * W + k], weights[7 * W + k], weights[8 * W + k])
        acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        acc = _accumulate(acc, 0, 0, _line(nodes, 0, k, wx0 * wy0, wz))
        acc = _accumulate(acc, 0, 1, _line(nodes, 9, k, wx0 * wy1, wz))
        acc = _accumulate(acc, 0, 2, _line(nodes, 18, k, wx0 * wy2, wz))
        acc = _accumulate(acc, 1, 0, _line(nodes, 27, k, wx1 * wy0, wz))
        acc = _accumulate(acc, 1, 1, _line(nodes, 36, k, wx1 * wy1, wz))
        acc = _accumulate(acc, 1, 2, _line(nodes, 45, k, wx1 * wy2, wz))
        acc = _accumulate(acc, 2, 0, _line(nodes, 54, k, wx2 * wy0, wz))
        acc = _accumulate(acc, 2, 1, _line(nodes, 63, k, wx2 * wy1, wz))
        acc = _accumulate(acc, 2, 2, _line(nodes, 72, k, wx2 * wy2, wz))
        for r in range(12):
            sums[r * W + k] = acc[r]


@njit(**_JIT_SERIAL)
def _g2p_block_3d(
    lo,
    hi,
    x,
    v,
    C,
    vol,
    J,
    gap,
    stress,
    vel,
    mass,
    origin,
    inv_h,
    dt,
    trial,
    before,
    grad,
    gather,
    material,
):
    """G2P of particles lo:hi: their stresses into ``before[:, p - lo]`` and their
    velocity gradients into ``grad[:, p - lo]``, for :func:`trial_batch` (and with a
    rate-dependent friction each particle's sin φ into ``trial[6, p - lo]``).

    The gather runs in sub-blocks of :data:`GATHER_WIDTH` particles: their node
    velocities copied into columns (:func:`_gather_nodes`), then summed in a SIMD loop
    (:func:`_contract_nodes`); ``gather`` holds the three flat work arrays.
    """
    nodes, weights, sums = gather
    W = GATHER_WIDTH
    contact = material[7] > 0.0
    shape = (vel.shape[0], vel.shape[1], vel.shape[2])
    scale = 4.0 * inv_h  # D^-1 times h: B is in grid units
    # node velocities as one flat array with unsigned offsets: a line of three nodes
    # along z is nine adjacent numbers, and no index needs a negative-index check
    flat = vel.reshape(-1)
    for sub in range(lo, hi, W):
        m = min(W, hi - sub)
        _gather_nodes(sub, m, x, flat, origin, inv_h, shape, nodes, weights)
        _contract_nodes(nodes, weights, sums, m)
        for kk in range(m):
            p = sub + kk
            v0, v1, v2 = sums[kk], sums[W + kk], sums[2 * W + kk]
            b00, b01, b02 = sums[3 * W + kk], sums[4 * W + kk], sums[5 * W + kk]
            b10, b11, b12 = sums[6 * W + kk], sums[7 * W + kk], sums[8 * W + kk]
            b20, b21, b22 = sums[9 * W + kk], sums[10 * W + kk], sums[11 * W + kk]
            rx, ry, rz = weights[9 * W + kk], weights[10 * W + kk], weights[11 * W + kk]
            if contact and gap[p] > 0.0:
                gap[p] = _bounded_gap(gap[p], _packing(x, p, mass, origin, inv_h) * material[7])
            c00 = scale * (b00 - v0 * rx)
            c01 = scale * (b01 - v0 * ry)
            c02 = scale * (b02 - v0 * rz)
            c10 = scale * (b10 - v1 * rx)
            c11 = scale * (b11 - v1 * ry)
            c12 = scale * (b12 - v1 * rz)
            c20 = scale * (b20 - v2 * rx)
            c21 = scale * (b21 - v2 * ry)
            c22 = scale * (b22 - v2 * rz)
            C[p, 0, 0] = c00
            C[p, 0, 1] = c01
            C[p, 0, 2] = c02
            C[p, 1, 0] = c10
            C[p, 1, 1] = c11
            C[p, 1, 2] = c12
            C[p, 2, 0] = c20
            C[p, 2, 1] = c21
            C[p, 2, 2] = c22
            # det(I + dt L) by cofactors along the first row
            a00 = 1.0 + dt * c00
            a11 = 1.0 + dt * c11
            a22 = 1.0 + dt * c22
            a01 = dt * c01
            a02 = dt * c02
            a10 = dt * c10
            a12 = dt * c12
            a20 = dt * c20
            a21 = dt * c21
            growth = (
                a00 * (a11 * a22 - a12 * a21)
                - a01 * (a10 * a22 - a12 * a20)
                + a02 * (a10 * a21 - a11 * a20)
            )
            J[p] *= growth
            vol[p] *= growth
            x[p, 0] += dt * v0
            x[p, 1] += dt * v1
            x[p, 2] += dt * v2
            v[p, 0] = v0
            v[p, 1] = v1
            v[p, 2] = v2
            l = (c00, c01, c02, c10, c11, c12, c20, c21, c22)
            old = read_stress(stress, p)
            k = p - lo
            for r in range(6):
                before[r, k] = old[r]
            for r in range(9):
                grad[r, k] = l[r]
            if material[8] > 0.0:
                trial[6, k] = rate_friction(
                    l, old, material[2], material[3], material[8], material[9], material[10]
                )[0]


@njit(**_JIT)
def g2p_2d(
    x, v, C, vol, J, gap, stress, codes, vel, mass, origin, inv_h, dt, material, starts, work
):
    """Gather velocities and affine matrices, advect, update the stress (2-D plane strain).

    Per particle: ``v = sum w v_i``, ``C = D^-1 sum w v_i (x_i - x)^T`` (``D^-1 = 4/h**2``);
    ``x += dt v``; with ``f = det(I + dt C)``, ``J *= f`` and ``vol *= f`` (so ``vol / J``
    stays the initial volume up to round-off); then the Mohr-Coulomb stress update
    (:func:`blendxr.flow.mohr_coulomb.stress_step`) with the velocity gradient ``L = C``
    (z row and column zero), done here while ``C`` is in registers: one pass over the
    particles instead of two, and no stored ``L``. Particles that left the vessel are
    put back afterwards by :func:`blendxr.flow.walls.project_into_vessel`, with the
    vessel's exact distance.

    Parameters
    ----------
    x : ndarray of float64, shape (N, 2)
        Particle positions [m], updated in place.
    v : ndarray of float64, shape (N, 2)
        Receives particle velocities [m/s].
    C : ndarray of float64, shape (N, 2, 2)
        Receives APIC affine matrices (velocity gradients) [1/s].
    vol, J : ndarray of float64, shape (N,)
        Current volumes [m^3] and Jacobians, updated in place.
    gap : ndarray of float64, shape (N,)
        Volume lost to contact per unit volume (``mohr_coulomb.close_gap``), >= 0,
        updated in place.
    stress : ndarray of float64, shape (N, 3, 3)
        Cauchy stresses [Pa], tension positive, updated in place.
    codes : ndarray of int8, shape (N,)
        Receives the return code of each particle's stress update (``mohr_coulomb``).
    vel : ndarray of float64, shape (nx, ny, 2)
        Node velocities [m/s] from :func:`grid_update_2d`.
    mass : ndarray of float64, shape (nx, ny)
        Node masses [kg/m] of the same step (read only with lost contact).
    origin : ndarray of float64, shape (2,)
        Position of node 0 [m].
    inv_h, dt : float
        Inverse node spacing [1/m], time step [s].
    material : tuple of 11 float
        ``(K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff)`` as for
        :func:`blendxr.flow.mohr_coulomb.update_stress`; then, to keep the volume
        gained at the apex or cap as lost contact (``mohr_coulomb.close_gap``), the
        inverse of a node's mass at the seeded packing, ``1 / (ρ h**d)`` (else 0.0):
        before its stress update each particle's gap is capped at ``1 - sum w m_i / (ρ
        h**d)``, what the material around it lacks of that packing (:func:`_bounded_gap`);
        then the μ(I) friction's ``(rise, I0, inertial_scale)``
        (:func:`blendxr.flow.mohr_coulomb.rate_friction`; rise 0: rate-independent).
    starts : ndarray of int64, shape (T + 1,)
        Contiguous particle chunks, one per parallel task (:func:`chunk_starts`).
    work : tuple of ndarray
        The work arrays of :func:`g2p_3d`; unused in plane strain, where σxz = σyz = 0
        and the in-plane closed form needs none.
    """
    for t in prange(starts.shape[0] - 1):
        _g2p_range_2d(
            starts[t], starts[t + 1], x, v, C, vol, J, gap, stress, codes, vel, mass, origin,
            inv_h, dt, material,
        )  # fmt: skip


@njit(**_JIT)
def g2p_3d(
    x, v, C, vol, J, gap, stress, codes, vel, mass, origin, inv_h, dt, material, starts, work
):
    """Gather velocities and affine matrices, advect, update the stress (3-D).

    As :func:`g2p_2d` in three dimensions.

    Parameters
    ----------
    x : ndarray of float64, shape (N, 3)
        Particle positions [m], updated in place.
    v : ndarray of float64, shape (N, 3)
        Receives particle velocities [m/s].
    C : ndarray of float64, shape (N, 3, 3)
        Receives APIC affine matrices (velocity gradients) [1/s].
    vol, J : ndarray of float64, shape (N,)
        Current volumes [m^3] and Jacobians, updated in place (``*= det(I + dt C)``).
    gap : ndarray of float64, shape (N,)
        Volume lost to contact per unit volume, >= 0, updated in place.
    stress : ndarray of float64, shape (N, 3, 3)
        Cauchy stresses [Pa], tension positive, updated in place.
    codes : ndarray of int8, shape (N,)
        Receives the return code of each particle's stress update.
    vel : ndarray of float64, shape (nx, ny, nz, 3)
        Node velocities [m/s] from :func:`grid_update_3d`.
    mass : ndarray of float64, shape (nx, ny, nz)
        Node masses [kg] of the same step (read only with lost contact).
    origin : ndarray of float64, shape (3,)
        Position of node 0 [m].
    inv_h, dt : float
        Inverse node spacing [1/m], time step [s].
    material : tuple of 11 float
        ``(K, G, sin_phi, cos_phi, cohesion, sin_psi, tension_cutoff, lost_contact, rise,
        I0, inertial_scale)`` as for :func:`g2p_2d`.
    starts : ndarray of int64, shape (T + 1,)
        Contiguous particle chunks, one per parallel task (:func:`chunk_starts`).
    work : tuple of 10 ndarray of float64
        Per-task work arrays, :func:`g2p_work` (T, B): each task
        runs its chunk in blocks of B particles, gathering the velocities and gradients
        of a block, then forming its elastic trial stresses and decomposing them all at
        once with the SIMD loops of :func:`blendxr.flow.mohr_coulomb.trial_batch` and
        :func:`blendxr.flow.mohr_coulomb.eigh3_batch`, then returning them.
    """
    K, G = material[0], material[1]
    lam = K - 2.0 * G / 3.0
    contact = material[7] > 0.0
    trial, alpha, e, uw, out, grad, ret, nodes, weights, sums = work
    block = trial.shape[2]
    for t in prange(starts.shape[0] - 1):
        for lo in range(starts[t], starts[t + 1], block):
            hi = min(lo + block, starts[t + 1])
            n = hi - lo
            _g2p_block_3d(
                lo, hi, x, v, C, vol, J, gap, stress, vel, mass, origin, inv_h, dt, trial[t],
                uw[t], grad[t], (nodes[t], weights[t], sums[t]), material,
            )  # fmt: skip
            # the stresses before the step wait in uw, which eigh3_batch fills next
            trial_batch(uw[t], grad[t], trial[t], gap, lo, n, dt, lam, G, contact)
            eigh3_batch(trial[t], alpha[t], e[t], uw[t], out[t], n)
            return_batch(
                lo, n, trial[t], e[t], uw[t], out[t], grad[t], ret[t], stress, codes, gap, contact,
                lam, G,
                material[2], material[3], material[4], material[5], material[6],
                material[8] > 0.0,
            )  # fmt: skip


# ---------------------------------------------------------------------------------------
# Deposit onto the output grid
#
# The output fill is the material's volume fraction as the solver's own grid sees it:
# each particle spreads its volume over the 3**d output cells around it with the same
# quadratic B-spline weights as P2G, centred on the cell centres. Counting particles per
# cell instead (nearest cell) measures how the material points happen to sit inside the
# cells: with a few per cell they cluster at the cell scale, where no stress sees it, and
# such counts reached twice the seeded packing where every grid node held its packing
# (docs/flow.md, "Output"). The weights of each particle are renormalised over the cells
# inside the vessel (``inside``), so a particle by a wall puts none of its volume outside
# and every particle deposits exactly its volume. With ``mirror_z`` the cells are the
# upper half of a grid symmetric about z = 0 (a mirror-symmetric run): a weight below the
# plane belongs to the particle's image and is folded onto the cell it mirrors, with
# its z momentum reversed.
#
# Serial: it runs every few steps and costs about one serial P2G; a parallel version would
# need per-thread accumulators.
# ---------------------------------------------------------------------------------------


@njit(**_JIT_SERIAL)
def _centre_stencil(f):
    """First cell and B-spline weights along one axis of the cell-centred stencil.

    ``f`` is the position in cell units, ``(x - origin) / h``; cell c is centred at
    c + 1/2. Returns ``(base, w0, w1, w2)`` for cells base, base + 1, base + 2 (not
    clamped: the caller skips cells off the grid).
    """
    b = math.floor(f - 1.0)
    r = f - 0.5 - b
    return int(b), 0.5 * (1.5 - r) ** 2, 0.75 - (r - 1.0) ** 2, 0.5 * (r - 0.5) ** 2


@njit(**_JIT_SERIAL)
def deposit_2d(x, v, vol, origin_out, inv_h_out, inside, acc_vol, acc_mom):
    """Add particle volume and volume-weighted velocity to output cells (2-D).

    Quadratic B-spline weights onto the cell centres, renormalised over the cells with
    ``inside != 0``: cell (i, j) is centred at ``origin_out + (i + 1/2, j + 1/2) h_out``.
    A particle with no inside cell in its stencil is skipped. The driver divides
    ``acc_mom`` by ``acc_vol`` (velocity) and ``acc_vol`` by the cell volume and the
    number of deposits (fill).

    Parameters
    ----------
    x, v : ndarray of float64, shape (N, 2)
        Particle positions [m] and velocities [m/s].
    vol : ndarray of float64, shape (N,)
        Particle volumes [m^3].
    origin_out : ndarray of float64, shape (2,)
        Lower corner of output cell (0, 0) [m].
    inv_h_out : float
        Inverse output cell size [1/m].
    inside : ndarray of int8, shape (mx, my)
        Nonzero for the cells that may receive material (the vessel's).
    acc_vol : ndarray of float64, shape (mx, my)
        Accumulated volume [m^3], added to.
    acc_mom : ndarray of float64, shape (mx, my, 2)
        Accumulated volume times velocity [m^4/s], added to.
    """
    _deposit_2d(x, v, vol, 0, 1, origin_out, inv_h_out, inside, acc_vol, acc_mom)


@njit(**_JIT)
def deposit_parts_2d(x, v, vol, origin_out, inv_h_out, inside, acc_vol, acc_mom):
    """:func:`deposit_2d` into ``P`` accumulators at once, part q taking particles
    q, q + P, q + 2P, ... (``acc_vol`` of shape (P, mx, my), ``acc_mom`` (P, mx, my, 2)).

    The parts run in parallel (each owns its accumulator, so no two threads add to the
    same cell) and each adds its particles in the order :func:`deposit_2d` would: the
    result is the same, bit for bit, as P serial calls on ``x[q::P]``.
    """
    parts = acc_vol.shape[0]
    for q in prange(parts):
        _deposit_2d(x, v, vol, q, parts, origin_out, inv_h_out, inside, acc_vol[q], acc_mom[q])


@njit(**_JIT_SERIAL)
def _deposit_2d(x, v, vol, first, stride, origin_out, inv_h_out, inside, acc_vol, acc_mom):
    """The loop of :func:`deposit_2d` over particles first, first + stride, ..."""
    mx, my = acc_vol.shape
    wx = np.empty(3)
    wy = np.empty(3)
    # the stencil's cells inside, gathered once: weight and (i, j) of each
    w = np.empty(9)
    cell = np.empty((9, 2), np.int64)
    for p in range(first, x.shape[0], stride):
        fx = (x[p, 0] - origin_out[0]) * inv_h_out
        fy = (x[p, 1] - origin_out[1]) * inv_h_out
        if not (-1.0 < fx < mx + 1.0 and -1.0 < fy < my + 1.0):
            continue
        bi, wx[0], wx[1], wx[2] = _centre_stencil(fx)
        bj, wy[0], wy[1], wy[2] = _centre_stencil(fy)
        n = 0
        total = 0.0
        for a in range(3):
            i = bi + a
            for b in range(3):
                j = bj + b
                if 0 <= i < mx and 0 <= j < my and inside[i, j] != 0:
                    w[n] = wx[a] * wy[b]
                    cell[n, 0], cell[n, 1] = i, j
                    total += w[n]
                    n += 1
        if total <= 0.0:
            continue
        scale = vol[p] / total
        for m in range(n):
            i, j = cell[m, 0], cell[m, 1]
            wv = scale * w[m]
            acc_vol[i, j] += wv
            acc_mom[i, j, 0] += wv * v[p, 0]
            acc_mom[i, j, 1] += wv * v[p, 1]


@njit(**_JIT_SERIAL)
def _folded(k, mz, mirror_z):
    """(cell, z sign) of stencil cell k along z: below the mirror plane, the cell it
    mirrors and -1; off the grid, -1 as the cell."""
    if k < 0 and mirror_z:
        return -k - 1, -1.0
    if 0 <= k < mz:
        return k, 1.0
    return -1, 1.0


@njit(**_JIT_SERIAL)
def deposit_3d(x, v, vol, origin_out, inv_h_out, inside, mirror_z, acc_vol, acc_mom):
    """Add particle volume and volume-weighted velocity to output cells (3-D).

    As :func:`deposit_2d` with cells (i, j, k); with ``mirror_z`` the cells are the upper
    half of a grid symmetric about z = 0 (``origin_out[2] = 0``) and a weight below the
    plane is folded onto the cell it mirrors with the z momentum reversed.

    Parameters
    ----------
    x, v : ndarray of float64, shape (N, 3)
        Particle positions [m] and velocities [m/s].
    vol : ndarray of float64, shape (N,)
        Particle volumes [m^3].
    origin_out : ndarray of float64, shape (3,)
        Lower corner of output cell (0, 0, 0) [m].
    inv_h_out : float
        Inverse output cell size [1/m].
    inside : ndarray of int8, shape (mx, my, mz)
        Nonzero for the cells that may receive material (the vessel's).
    mirror_z : bool
        Fold the weights below z = 0 back (the particles' images).
    acc_vol : ndarray of float64, shape (mx, my, mz)
        Accumulated volume [m^3], added to.
    acc_mom : ndarray of float64, shape (mx, my, mz, 3)
        Accumulated volume times velocity [m^4/s], added to.
    """
    _deposit_3d(x, v, vol, 0, 1, origin_out, inv_h_out, inside, mirror_z, acc_vol, acc_mom)


@njit(**_JIT)
def deposit_parts_3d(x, v, vol, origin_out, inv_h_out, inside, mirror_z, acc_vol, acc_mom):
    """:func:`deposit_3d` into ``P`` accumulators at once, part q taking particles
    q, q + P, q + 2P, ... (``acc_vol`` of shape (P, mx, my, mz), ``acc_mom``
    (P, mx, my, mz, 3)); parallel over the parts and, like :func:`deposit_parts_2d`,
    the same bit for bit as P serial calls on ``x[q::P]``.
    """
    parts = acc_vol.shape[0]
    for q in prange(parts):
        _deposit_3d(
            x, v, vol, q, parts, origin_out, inv_h_out, inside, mirror_z, acc_vol[q], acc_mom[q]
        )


# The deposit's loops are inlined into the particle loop (a call that passes arrays is
# not inlined by LLVM and costs more than the particle's work) and take the accumulators
# C-contiguous (the phase averager keeps one block per phase bin and part). Particles
# whose stencil lies on the grid in x and y (almost all, the mirror plane's included) add
# in place; the rest (at the grid's sides) gather their cells first. Both paths sum and
# multiply in the same order, so they give the same bits.


@njit(**_JIT_INLINE)
def _deposit_in_xy_3d(bi, bj, ks, sz, wx, wy, wz, vol, v0, v1, v2, inside, acc_vol, acc_mom):
    """One particle's deposit when its stencil lies on the grid in x and y: the weights of
    the inside cells summed and added in place, without gathering them. ``ks`` are the z
    cells (-1: off the grid), ``sz`` their z signs (-1: the image of a cell below the
    mirror plane, whose z momentum is reversed)."""
    total = 0.0
    for a in range(3):
        for b in range(3):
            wab = wx[a] * wy[b]
            for c in range(3):
                if ks[c] >= 0 and inside[bi + a, bj + b, ks[c]] != 0:
                    total += wab * wz[c]
    if total <= 0.0:
        return
    scale = vol / total
    for a in range(3):
        i = bi + a
        for b in range(3):
            j = bj + b
            wab = wx[a] * wy[b]
            for c in range(3):
                k = ks[c]
                if k >= 0 and inside[i, j, k] != 0:
                    wv = scale * (wab * wz[c])
                    acc_vol[i, j, k] += wv
                    acc_mom[i, j, k, 0] += wv * v0
                    acc_mom[i, j, k, 1] += wv * v1
                    acc_mom[i, j, k, 2] += wv * sz[c] * v2


@njit(**_JIT_INLINE)
def _deposit_edge_3d(bi, bj, bk, wx, wy, wz, vol, v0, v1, v2, inside, mirror_z, acc_vol,
                     acc_mom, w, sign, cell):  # fmt: skip
    """The general deposit: the stencil's cells on the grid and inside gathered first."""
    mx, my, mz = acc_vol.shape
    n = 0
    total = 0.0
    for a in range(3):
        i = bi + a
        for b in range(3):
            j = bj + b
            if not (0 <= i < mx and 0 <= j < my):
                continue
            for c in range(3):
                k, s = _folded(bk + c, mz, mirror_z)
                if k >= 0 and inside[i, j, k] != 0:
                    w[n] = wx[a] * wy[b] * wz[c]
                    sign[n] = s
                    cell[n, 0], cell[n, 1], cell[n, 2] = i, j, k
                    total += w[n]
                    n += 1
    if total <= 0.0:
        return
    scale = vol / total
    for m in range(n):
        i, j, k = cell[m, 0], cell[m, 1], cell[m, 2]
        wv = scale * w[m]
        acc_vol[i, j, k] += wv
        acc_mom[i, j, k, 0] += wv * v0
        acc_mom[i, j, k, 1] += wv * v1
        acc_mom[i, j, k, 2] += wv * sign[m] * v2


@njit(**_JIT_SERIAL)
def _deposit_3d(x, v, vol, first, stride, origin_out, inv_h_out, inside, mirror_z, acc_vol,
                acc_mom):  # fmt: skip
    """The loop of :func:`deposit_3d` over particles first, first + stride, ..."""
    mx, my, mz = acc_vol.shape
    # the general path's gathered cells: weight, z sign and (i, j, k) of each
    w = np.empty(27)
    sign = np.empty(27)
    cell = np.empty((27, 3), np.int64)
    for p in range(first, x.shape[0], stride):
        fx = (x[p, 0] - origin_out[0]) * inv_h_out
        fy = (x[p, 1] - origin_out[1]) * inv_h_out
        fz = (x[p, 2] - origin_out[2]) * inv_h_out
        if not (-1.0 < fx < mx + 1.0 and -1.0 < fy < my + 1.0 and -1.0 < fz < mz + 1.0):
            continue
        bi, wx0, wx1, wx2 = _centre_stencil(fx)
        bj, wy0, wy1, wy2 = _centre_stencil(fy)
        bk, wz0, wz1, wz2 = _centre_stencil(fz)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        v0, v1, v2 = v[p, 0], v[p, 1], v[p, 2]
        if 0 <= bi and bi + 3 <= mx and 0 <= bj and bj + 3 <= my and bk + 3 <= mz:
            k0, s0 = _folded(bk, mz, mirror_z)
            k1, s1 = _folded(bk + 1, mz, mirror_z)
            k2, s2 = _folded(bk + 2, mz, mirror_z)
            _deposit_in_xy_3d(bi, bj, (k0, k1, k2), (s0, s1, s2), wx, wy, wz, vol[p], v0, v1,
                              v2, inside, acc_vol, acc_mom)  # fmt: skip
        else:
            _deposit_edge_3d(bi, bj, bk, wx, wy, wz, vol[p], v0, v1, v2, inside, mirror_z,
                             acc_vol, acc_mom, w, sign, cell)  # fmt: skip


# ---------------------------------------------------------------------------------------
# Helpers of the density projection (blendxr.flow.projection)
# ---------------------------------------------------------------------------------------


@njit(**_JIT_SERIAL)
def _stencil_slopes(r):
    """Derivatives with respect to r of the three weights :func:`_stencil` returns."""
    return r - 1.5, 2.0 * (1.0 - r), r - 0.5


@njit(**_JIT_SERIAL)
def _limited(dx, dy, dz, max_shift):
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    if n > max_shift:
        s = max_shift / n
        return dx * s, dy * s, dz * s
    return dx, dy, dz
