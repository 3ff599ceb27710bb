"""Remove the divergence of a steady flow's stored velocity inside its bed.

A steady bed conserves its material: where the bed is full, the velocity the ADE carries
the colour with must be divergence-free. The solver's time-averaged velocity is not
exactly: averaging particle velocities into cells leaves a small divergence of one sign
over much of the bed (docs/studies.md gives the drum's figures). Small as it is, it never
averages out along a closed streamline: every loop spirals inward, the bed's outermost
material is fed from the wall instead of from upstream, and a band of unmixed colour
stays along the wall and the free surface.

This module removes that divergence with an approximate projection (the cell-centred
projection of incompressible flow solvers, as in Almgren, Bell & Szymczak 1996) on the
flow grid, over the bed's cells (fill above ``BED_FILL``) only:

* a face between two bed cells carries the mean of their velocities (``F``); a face to a
  cell outside the bed carries no flux, so the bed's edge is closed — as it is in a steady
  bed, whose wall and free surface are streamlines;
* the divergence of a cell is the sum of its outgoing face fluxes over h (``D``);
* a potential p has face gradients (``G``, zero across the bed's edge) and its compact
  Laplacian is ``L = sum_a D_a G_a``; a cell's correction is the mean of the gradients on
  its bed faces (``A``).

``L p = sum_a D_a F_a u_a`` is solved (LSMR: L is singular, one constant per connected
piece of bed, and the right side sums to zero over each piece because the edge is
closed), and ``u_a - A_a G_a p`` is returned. The projection is approximate: the
divergence left is what separates the compact Laplacian from ``D F A G`` — second order
in the cell for a smooth field. The exact alternative, solving with ``D F A G`` itself,
leaves no divergence but its wide stencil decouples neighbouring cells: its solution
carries cell-to-cell oscillations that the face-mean divergence cannot see, and on a
coarse bed they are as large as the flow (a drum at 5 mm lost its mixing to them). It runs
once, on the flow grid (thousands to a few hundred thousand cells), before the velocity
is mapped onto the ADE grid.

Only steady flows (one stored phase) are projected: a transient flow's bed changes shape
between phases, and there the divergence balances the change of the fill.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl

__all__ = ["BED_FILL", "face_divergence", "remove_divergence"]

#: cells whose fill is above this are the bed the projection acts in
BED_FILL = 0.5


def _faces(bed: np.ndarray, axis: int):
    """Flat indices (low, high) of the pairs of bed cells adjacent along ``axis``."""
    n = bed.shape[axis]
    low = [slice(None)] * bed.ndim
    high = [slice(None)] * bed.ndim
    low[axis], high[axis] = slice(0, n - 1), slice(1, n)
    both = bed[tuple(low)] & bed[tuple(high)]
    index = np.arange(bed.size).reshape(bed.shape)
    return index[tuple(low)][both], index[tuple(high)][both]


def face_divergence(velocities, bed: np.ndarray, spacing) -> np.ndarray:
    """The face-flux divergence of each bed cell (1/s; 0 outside the bed).

    Parameters
    ----------
    velocities : sequence of ndarray
        One component per axis, each of the grid's shape (m/s).
    bed : ndarray of bool
        The cells the flux is counted over; faces to other cells carry none.
    spacing : sequence of float
        Cell edge per axis (m).

    Returns
    -------
    ndarray
        Flattened (C order), one value per grid cell.
    """
    div = np.zeros(bed.size)
    for axis, (u, h) in enumerate(zip(velocities, spacing, strict=True)):
        lo, hi = _faces(bed, axis)
        flat = np.ravel(u)
        flux = 0.5 * (flat[lo] + flat[hi]) / h
        np.add.at(div, lo, flux)
        np.add.at(div, hi, -flux)
    return div


def _operators(bed: np.ndarray, spacing):
    """Per axis the sparse operators over the bed's cells: F (cells to faces, the mean of
    the two cells), D (faces to cells, the outgoing flux over h), G (cells to faces, the
    difference over h) and A (faces to cells, the mean of the cell's faces)."""
    cells = np.flatnonzero(bed.ravel())
    n = cells.size
    number = -np.ones(bed.size, np.int64)
    number[cells] = np.arange(n)
    out = []
    for axis, h in enumerate(spacing):
        lo, hi = (number[i] for i in _faces(bed, axis))
        m = lo.size
        face = np.arange(m)
        pair = (np.concatenate([face, face]), np.concatenate([lo, hi]))
        F = sp.csr_matrix((np.full(2 * m, 0.5), pair), shape=(m, n))
        G = sp.csr_matrix((np.concatenate([np.full(m, -1 / h), np.full(m, 1 / h)]), pair),
                          shape=(m, n))  # fmt: skip
        D = sp.csr_matrix(
            (np.concatenate([np.full(m, 1 / h), np.full(m, -1 / h)]), pair[::-1]), shape=(n, m)
        )
        count = np.bincount(np.concatenate([lo, hi]), minlength=n).astype(float)
        weight = 1.0 / np.maximum(count, 1.0)
        A = sp.csr_matrix((np.concatenate([weight[lo], weight[hi]]), pair[::-1]), shape=(n, m))
        out.append((F, D, G, A))
    return cells, out


def remove_divergence(velocities, fill: np.ndarray, spacing) -> tuple[tuple, dict]:
    """The velocity without its divergence inside the bed (fill > ``BED_FILL``).

    Solves ``sum_a D_a G_a p = sum_a D_a F_a u_a`` (LSMR) and returns ``u_a - A_a G_a p``:
    the approximate projection of the module's docstring, which leaves a divergence of
    second order in the cell for a smooth field.

    Parameters
    ----------
    velocities : sequence of ndarray
        One component per axis (m/s), each of ``fill``'s shape; not modified.
    fill : ndarray
        The material's volume fraction per cell.
    spacing : sequence of float
        Cell edge per axis (m).

    Returns
    -------
    velocities : tuple of ndarray
        The projected components (float64); cells outside the bed are unchanged.
    info : dict
        ``divergence_before`` and ``divergence_after``: the mean |divergence| over the bed
        (1/s), ``bed_cells`` and ``iterations`` of the solver.
    """
    bed = np.asarray(fill) > BED_FILL
    out = tuple(np.array(u, dtype=float, copy=True) for u in velocities)
    info = {"bed_cells": int(bed.sum()), "divergence_before": 0.0, "divergence_after": 0.0,
            "iterations": 0}  # fmt: skip
    if info["bed_cells"] < 2:
        return out, info
    cells, ops = _operators(bed, spacing)

    def divergence(components):
        return sum(D @ (F @ u) for (F, D, _, _), u in zip(ops, components, strict=True))

    u_bed = [u.reshape(-1)[cells] for u in out]
    laplacian = sum(D @ G for _, D, G, _ in ops)
    div = divergence(u_bed)
    p, stop, iterations, *_ = spl.lsmr(
        laplacian, div, atol=1e-12, btol=1e-12, maxiter=20 * cells.size
    )
    if stop == 7:  # LSMR's iteration limit: the projection is partial, say so
        warnings.warn(
            f"the steady flow's divergence projection stopped at its iteration limit "
            f"({iterations}) on {cells.size} bed cells; the divergence is reduced, not removed",
            RuntimeWarning,
            stacklevel=3,
        )
    projected = [u - A @ (G @ p) for (_, _, G, A), u in zip(ops, u_bed, strict=True)]
    for flat, u in zip(out, projected, strict=True):
        flat.reshape(-1)[cells] = u
    info.update(
        divergence_before=float(np.abs(div).mean()),
        divergence_after=float(np.abs(divergence(projected)).mean()),
        iterations=int(iterations),
    )
    return out, info
