"""Particles that end up in a wall are put back, with the vessel's exact distance function.

Numba only: plain arrays in and out. The background-grid kernels keep material off the
walls through the node velocities; a particle can still cross a wall within a step (its
velocity is interpolated from nodes on both sides). Projecting with the bilinear
interpolation of node distances would misplace it: that interpolant overestimates the
distance of a convex wall (the distance function is convex there), so particles just
inside would be pushed further in, piling up a dense layer along the wall. The exact
signed distance (``blendxr.vessels.sdf_normal``) has no such bias.
"""

from __future__ import annotations

import math

import numba
from numba import prange

from ..vessels import sdf_normal

__all__ = ["MAX_PROJECTIONS", "project_into_vessel", "reflect_across_mirror"]

MAX_PROJECTIONS = 8  # projections per particle and step (one suffices off edges)


@numba.njit(parallel=True, cache=True)
def project_into_vessel(kind, params, x, v, skin, starts, scratch, node_sdf, origin, h, shape):
    """Move particles outside the vessel back to ``skin`` inside the wall (in place).

    For a particle on the wrong side (signed distance ``phi > 0``) the position moves by
    ``-(phi + skin) n`` along the outward normal ``n``, and an outward normal velocity
    ``v . n > 0`` is removed.

    Parameters
    ----------
    kind : int
        Vessel kind code (``blendxr.vessels``).
    params : ndarray of float64
        The vessel's parameters.
    x, v : ndarray of float64, shape (N, d)
        Positions (m) and velocities (m/s), updated in place.
    skin : float
        Depth inside the wall a projected particle is put at (m, >= 0).
    starts : ndarray of int64, shape (T + 1,)
        Contiguous particle chunks, one per parallel task.
    scratch : ndarray of float64, shape (T, 4)
        Per-task workspace (the normal; the last column receives the task's count).
    node_sdf : ndarray of float64, shape (n_nodes,)
        The signed distance at the background-grid nodes, flattened (C order): a cheap
        test that skips the exact distance for particles clearly inside. A signed
        distance is 1-Lipschitz, so a particle whose nearest node lies deeper than
        ``h sqrt(d) / 2`` (the farthest a particle is from its nearest node) is inside.
    origin : ndarray of float64, shape (d,)
        Position of node 0 (m).
    h : float
        Node spacing (m).
    shape : ndarray of int64, shape (d,)
        Nodes per axis.

    Returns
    -------
    int
        Number of particles moved.
    """
    d = x.shape[1]
    tasks = starts.shape[0] - 1
    deep = -h * (0.5 * d**0.5 + 1e-6)
    # the nearest node by a product: where rounding picks the other of two nodes at a
    # tie, that node is as near, so the test stays exact (the margin above covers it)
    inv_h = 1.0 / h
    for t in prange(tasks):
        normal = scratch[t]
        count = 0
        for p in range(starts[t], starts[t + 1]):
            node = 0
            for a in range(d):
                k = int(math.floor((x[p, a] - origin[a]) * inv_h + 0.5))
                k = min(max(k, 0), shape[a] - 1)
                node = node * shape[a] + k
            if node_sdf[node] < deep:
                continue
            z = x[p, 2] if d == 3 else 0.0
            phi = sdf_normal(kind, params, x[p, 0], x[p, 1], z, normal)
            if phi <= 0.0:
                continue
            count += 1
            # a distance that is only a lower bound outside (the tote's planes) may leave
            # the particle outside another face: repeat, as alternating projections onto
            # the faces of a convex vessel converge
            for _ in range(MAX_PROJECTIONS):
                vn = 0.0
                for a in range(d):
                    x[p, a] -= (phi + skin) * normal[a]
                    vn += v[p, a] * normal[a]
                if vn > 0.0:
                    for a in range(d):
                        v[p, a] -= vn * normal[a]
                z = x[p, 2] if d == 3 else 0.0
                phi = sdf_normal(kind, params, x[p, 0], x[p, 1], z, normal)
                if phi <= 0.0:
                    break
        normal[3] = count
    total = 0
    for t in range(tasks):
        total += int(scratch[t, 3])
    return total


@numba.njit(parallel=True, cache=True)
def reflect_across_mirror(x, v, C, stress, z0, starts, scratch):
    """Replace particles below the mirror plane z = z0 by their mirror images (in place).

    With a mirror-symmetric flow solved on one side of the plane (see
    :func:`blendxr.flow.kernels.fold_mirror_3d`) a particle that crossed the plane stands
    for its image, which crossed the other way: z - z0 and the z velocity change sign,
    and so do the xz and yz entries of the affine matrix and the stress (``R A R`` with
    ``R = diag(1, 1, -1)``).

    Parameters
    ----------
    x, v : ndarray of float64, shape (N, 3)
        Positions (m) and velocities (m/s).
    C : ndarray of float64, shape (N, 3, 3)
        Affine matrices (1/s).
    stress : ndarray of float64, shape (N, 3, 3)
        Cauchy stresses (Pa).
    z0 : float
        Height of the plane on the z axis (m).
    starts : ndarray of int64, shape (T + 1,)
        Contiguous particle chunks, one per parallel task.
    scratch : ndarray of float64, shape (T, 4)
        Per-task workspace, as for :func:`project_into_vessel` (the last column receives
        the task's count; the step calls this every step, so nothing is allocated).

    Returns
    -------
    int
        Number of particles reflected.
    """
    tasks = starts.shape[0] - 1
    for t in prange(tasks):
        count = 0
        for p in range(starts[t], starts[t + 1]):
            if x[p, 2] >= z0:
                continue
            count += 1
            x[p, 2] = 2.0 * z0 - x[p, 2]
            v[p, 2] = -v[p, 2]
            for a in range(2):
                C[p, a, 2] = -C[p, a, 2]
                C[p, 2, a] = -C[p, 2, a]
                stress[p, a, 2] = -stress[p, a, 2]
                stress[p, 2, a] = -stress[p, 2, a]
        scratch[t, 3] = count
    total = 0
    for t in range(tasks):
        total += int(scratch[t, 3])
    return total
