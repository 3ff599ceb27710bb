"""Pure-NumPy reference twins of the MPM kernels in :mod:`blendxr.flow.kernels`.

Slow and written for reading: one code path for 2-D and 3-D, whole-array expressions, a
loop over the 3**d stencil offsets. Used only by the tests, which check that each numba
kernel gives the same numbers. The twins return their results as new arrays instead of
writing into arguments, and use one grid instead of per-thread private grids.
"""

from __future__ import annotations

import itertools

import numpy as np

from .kernels import GRID_MASS_TINY
from .mohr_coulomb_reference import update_stress, update_stresses

__all__ = [
    "bounded_gap",
    "bulk_pressure",
    "deposit",
    "displace",
    "g2p",
    "grid_update",
    "p2g",
    "fastest_particle",
    "particles_in_range",
    "poisson_matrix",
    "scatter_volume",
    "sort_by_cell",
    "stencil",
]


def stencil(x, origin, inv_h):
    """Quadratic B-spline stencils of all particles.

    Returns ``base`` (N, d) int, the first stencil node per axis; ``r`` (N, d), the
    particle position in grid units measured from ``base``; ``w`` (3, N, d), the weight of
    node ``base + a`` along each axis.
    """
    f = (x - origin) * inv_h
    base = np.floor(f - 0.5).astype(np.int64)
    r = f - base
    w = np.stack([0.5 * (1.5 - r) ** 2, 0.75 - (r - 1.0) ** 2, 0.5 * (r - 0.5) ** 2])
    return base, r, w


def _stencil_nodes(x, origin, inv_h):
    """Yield ``(node_index, weight, offset_in_metres)`` for each of the 3**d offsets."""
    d = x.shape[1]
    base, r, w = stencil(x, origin, inv_h)
    for offset in itertools.product(range(3), repeat=d):
        offset = np.array(offset)
        weight = np.prod([w[offset[a], :, a] for a in range(d)], axis=0)
        node = tuple((base + offset).T)
        yield node, weight, (offset - r) / inv_h


def p2g(x, v, C, m, vol, stress, origin, inv_h, dt, shape, bulk=(0.0, 0.0)):
    """Node masses and MLS-MPM momenta ``sum_p w [m v + (m C - dt vol D^-1 (sigma + q I)) dx]``,
    ``q`` the bulk-viscous pressure of :func:`bulk_pressure`."""
    d = x.shape[1]
    d_inv = 4.0 * inv_h**2
    total = stress[:, :d, :d] + bulk_pressure(C, *bulk)[:, None, None] * np.eye(d)
    affine = m[:, None, None] * C - (dt * vol * d_inv)[:, None, None] * total
    grid_m = np.zeros(shape)
    grid_p = np.zeros((*shape, d))
    for node, weight, dx in _stencil_nodes(x, origin, inv_h):
        momentum = m[:, None] * v + np.einsum("pij,pj->pi", affine, dx)
        np.add.at(grid_m, node, weight * m)
        np.add.at(grid_p, node, weight[:, None] * momentum)
    return grid_m, grid_p


def grid_update(
    grid_m, grid_p, origin, h, dt, gravity, omega, damping, node_sdf, node_normal, mu_wall, band
):
    """Node velocities: forces, exact Coriolis rotation, damping, frictional walls."""
    d = grid_m.ndim
    axes = [origin[a] + h * np.arange(n) for a, n in enumerate(grid_m.shape)]
    position = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    has_mass = grid_m > GRID_MASS_TINY
    vel = np.zeros_like(grid_p)
    vel[has_mass] = grid_p[has_mass] / grid_m[has_mass][:, None]

    centrifugal = omega**2 * position
    if d == 3:
        centrifugal[..., 2] = 0.0
    vel += dt * (np.asarray(gravity) + centrifugal)

    angle = -2.0 * omega * dt  # dv/dt = -2 omega z x v turns (vx, vy) at rate -2 omega
    vx, vy = vel[..., 0].copy(), vel[..., 1].copy()
    vel[..., 0] = np.cos(angle) * vx - np.sin(angle) * vy
    vel[..., 1] = np.sin(angle) * vx + np.cos(angle) * vy
    vel *= 1.0 - damping

    vn = np.sum(vel * node_normal, axis=-1)
    contact = (node_sdf > -band) & (vn > 0.0)
    tangential = vel - vn[..., None] * node_normal
    speed = np.linalg.norm(tangential, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        keep = np.where(speed > mu_wall * vn, 1.0 - mu_wall * vn / speed, 0.0)
    vel = np.where(contact[..., None], keep[..., None] * tangential, vel)
    vel[~has_mass] = 0.0
    return vel


def g2p(x, v, C, vol, J, vel, origin, inv_h, dt, stress, material, rate=None):
    """Gather, advect, update J and volume, then the stress with the twin of the
    Mohr-Coulomb update (:mod:`blendxr.flow.mohr_coulomb_reference`) and ``L = C``.

    ``rate = (rise, I0, inertial_scale)`` turns on the μ(I) friction (twin of
    ``mohr_coulomb.rate_friction``): each particle returns with the angle atan(μ(I)).
    Returns ``(x, v, C, vol, J, stress, codes)`` as new arrays.
    """
    n, d = x.shape
    v_new = np.zeros((n, d))
    b = np.zeros((n, d, d))
    for node, weight, dx in _stencil_nodes(x, origin, inv_h):
        v_node = vel[node]
        v_new += weight[:, None] * v_node
        b += weight[:, None, None] * np.einsum("pi,pj->pij", v_node, dx)
    C_new = 4.0 * inv_h**2 * b
    L = np.zeros((n, 3, 3))
    L[:, :d, :d] = C_new
    growth = np.linalg.det(np.eye(d) + dt * C_new)
    if rate is None:
        new_stress, codes = update_stresses(stress, L, np.ones(n, bool), dt, *material)
    else:
        sin_phi, cos_phi = rate_friction(L, stress, material[2], material[3], *rate)
        new_stress = np.empty_like(stress)
        codes = np.empty(n, np.int8)
        for p in range(n):
            new_stress[p], codes[p] = update_stress(
                stress[p], L[p], dt, *material[:2], sin_phi[p], cos_phi[p], *material[4:]
            )
    return x + dt * v_new, v_new, C_new, vol * growth, J * growth, new_stress, codes


def bounded_gap(x, gap, mass, origin, inv_h, inverse_packed_mass):
    """Contact gaps capped at what the material around each particle lacks of the seeded
    packing: ``min(gap, max(0, 1 - sum w m_i * inverse_packed_mass))`` (twin of
    ``kernels._bounded_gap`` with its gather)."""
    packing = np.zeros(len(x))
    for node, weight, _ in _stencil_nodes(x, origin, inv_h):
        packing += weight * mass[node]
    return np.minimum(gap, np.maximum(0.0, 1.0 - packing * inverse_packed_mass))


def rate_friction(L, stress, sin_phi, cos_phi, rise, i0, inertial_scale):
    """sin and cos of atan(μ(I)) per particle, μ(I) = tan φ + rise I / (I0 + I) with
    I = |γ̇| inertial_scale / sqrt(p), |γ̇| = sqrt(2 D':D'), p = −tr σ / 3 (μ2 where
    p <= 0)."""
    D = 0.5 * (L + L.transpose(0, 2, 1))
    dev = D - np.trace(D, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
    rate = np.sqrt(2.0 * np.einsum("pij,pij->p", dev, dev))
    pressure = -np.trace(stress, axis1=1, axis2=2) / 3.0
    with np.errstate(divide="ignore"):
        inertial = np.where(pressure > 0, rate * inertial_scale / np.sqrt(np.abs(pressure)), np.inf)
    mu = sin_phi / cos_phi + np.where(np.isinf(inertial), rise, rise * inertial / (i0 + inertial))
    return mu / np.sqrt(1.0 + mu**2), 1.0 / np.sqrt(1.0 + mu**2)


def deposit(x, v, vol, origin_out, inv_h_out, inside, mirror_z=False):
    """Volume and volume times velocity spread over the output cells by quadratic
    B-splines on the cell centres, each particle's weights renormalised over the cells
    with ``inside`` set; with ``mirror_z`` (3-D) the weights below z = 0 fold onto the
    cells they mirror, the z momentum reversed.

    Returns ``(acc_vol, acc_mom)``.
    """
    d = x.shape[1]
    shape = np.array(inside.shape)
    # the stencil of :func:`stencil` on the lattice of cell centres
    base, r, w = stencil(x, origin_out + 0.5 / inv_h_out, inv_h_out)
    cells, weights, signs = [], [], []
    for offset in itertools.product(range(3), repeat=d):
        cell = base + np.array(offset)
        sign = np.ones(len(x))
        if mirror_z:
            below = cell[:, 2] < 0
            cell[below, 2] = -cell[below, 2] - 1
            sign[below] = -1.0
        ok = np.all((cell >= 0) & (cell < shape), axis=1)
        ok[ok] = inside[tuple(cell[ok].T)] != 0
        weight = np.prod([w[offset[a], :, a] for a in range(d)], axis=0) * ok
        cells.append(np.where(ok[:, None], cell, 0))
        weights.append(weight)
        signs.append(sign)
    total = np.sum(weights, axis=0)
    keep = total > 0
    acc_vol = np.zeros(inside.shape)
    acc_mom = np.zeros((*inside.shape, d))
    for cell, weight, sign in zip(cells, weights, signs, strict=True):
        share = np.where(keep, vol * weight / np.where(keep, total, 1.0), 0.0)
        index = tuple(cell.T)
        np.add.at(acc_vol, index, share)
        momentum = share[:, None] * v
        if mirror_z:
            momentum[:, 2] *= sign
        np.add.at(acc_mom, index, momentum)
    return acc_vol, acc_mom


def sort_by_cell(x, origin, inv_h, shape):
    """Stable permutation ordering particles by (ix, iy[, iz]) cell, x-major."""
    cell = np.clip(np.floor((x - origin) * inv_h), 0, np.array(shape) - 1).astype(np.int64)
    return np.lexsort(cell.T[::-1])


def fastest_particle(v):
    """Index of the first particle of greatest speed, a non-finite speed counting as
    infinite (-1 with no particles)."""
    if v.shape[0] == 0:
        return -1
    speed = np.sqrt(np.einsum("ij,ij->i", v, v))
    return int(np.argmax(np.where(np.isfinite(speed), speed, np.inf)))


def particles_in_range(x, origin, inv_h, shape):
    """Index of the first particle whose stencil leaves the grid, or -1."""
    f = (x - origin) * inv_h
    ok = np.all((f >= 0.5) & (f < np.array(shape) - 1.5), axis=1)
    bad = np.flatnonzero(~ok)
    return int(bad[0]) if bad.size else -1


def bulk_pressure(C, linear, quadratic):
    """Bulk-viscous pressure of each particle from tr(C) (twin of ``kernels._bulk_pressure``)."""
    rate = np.trace(C, axis1=1, axis2=2)
    return linear * rate + quadratic * np.minimum(rate, 0.0) * np.abs(rate)


def _bspline(u):
    """The quadratic B-spline N(u) and its derivative N'(u), u in grid units."""
    a = np.abs(u)
    inner = a < 0.5
    value = np.where(inner, 0.75 - u * u, 0.5 * np.clip(1.5 - a, 0.0, None) ** 2)
    slope = np.where(inner, -2.0 * u, -np.sign(u) * np.clip(1.5 - a, 0.0, None))
    return value, slope


def scatter_volume(x, vol, origin, inv_h, shape):
    """Node fill ``sum_p vol_p w_ip / h^d`` with the quadratic B-splines: the twin of
    ``projection.scatter_volume_2d`` / ``_3d``."""
    out = np.zeros(shape)
    for node, weight, _ in _stencil_nodes(x, origin, inv_h):
        np.add.at(out, node, vol * weight * inv_h ** x.shape[1])
    return out


def poisson_matrix(code, regularisation):
    """The sparse matrix of ``projection.assemble_poisson_2d`` / ``_3d`` (no mirror) on the
    material nodes, and their index: links to air see 0, links to walls carry no flux."""
    import scipy.sparse as sp

    from .projection import MATERIAL, SOLID

    material = code == MATERIAL
    index = -np.ones(code.shape, np.int64)
    index[material] = np.arange(int(material.sum()))
    rows, cols, vals = [], [], []
    diagonal = np.full(int(material.sum()), regularisation)
    for axis in range(code.ndim):
        for step in (-1, 1):
            here = np.argwhere(material)
            there = here.copy()
            there[:, axis] += step
            inside = (there[:, axis] >= 0) & (there[:, axis] < code.shape[axis])
            here, there = here[inside], there[inside]
            kind = code[tuple(there.T)]
            i = index[tuple(here.T)]
            open_ = kind != SOLID
            np.add.at(diagonal, i[open_], 1.0)
            linked = kind == MATERIAL
            rows.append(i[linked])
            cols.append(index[tuple(there[linked].T)])
            vals.append(-np.ones(int(linked.sum())))
    n = int(material.sum())
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals.append(diagonal)
    matrix = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    return matrix, index


def displace(x, phi, origin, inv_h, max_shift):
    """Positions moved by ``-h grad phi`` interpolated with the quadratic B-splines, at
    most ``max_shift`` each: the twin of ``projection.displace_2d`` / ``_3d``."""
    d = x.shape[1]
    f = (x - origin) * inv_h
    base = np.floor(f - 0.5).astype(np.int64)
    grad = np.zeros_like(x)
    for offset in itertools.product(range(3), repeat=d):
        node = base + np.array(offset)
        value, slope = _bspline(node - f)
        v = phi[tuple(node.T)]
        for a in range(d):
            others = np.prod([value[:, b] for b in range(d) if b != a], axis=0)
            grad[:, a] += -slope[:, a] * others * v
    move = -grad / inv_h
    norm = np.sqrt((move**2).sum(axis=1))
    scale = np.where(norm > max_shift, max_shift / np.where(norm > 0, norm, 1.0), 1.0)
    return x + move * scale[:, None]
