"""Exact wall projection of particles: against the vessels' own distance functions."""

from __future__ import annotations

import numpy as np
import pytest

from blendxr.flow.kernels import chunk_starts
from blendxr.flow.walls import project_into_vessel
from blendxr.vessels import Box, Drum, Tote


def _nodes(vessel, h):
    lower, upper = vessel.bounds
    origin = np.floor(np.asarray(lower) / h) * h - 2 * h
    shape = np.asarray(np.ceil((np.asarray(upper) - origin) / h) + 3, np.int64)
    axes = [origin[a] + h * np.arange(n) for a, n in enumerate(shape)]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    return vessel.sdf(nodes).reshape(-1), origin, shape


@pytest.mark.parametrize(
    "vessel",
    [Drum(0.15, ndim=2), Drum(0.15, ndim=3, length=0.05), Tote(), Box((0.2, 0.1))],
    ids=["drum-2d", "drum-3d", "tote", "box-2d"],
)
def test_projection_puts_escaped_particles_just_inside_and_leaves_the_rest(vessel):
    rng = np.random.default_rng(3)
    lower, upper = (np.asarray(b) for b in vessel.bounds)
    n = 4000
    x = lower - 0.05 * (upper - lower) + rng.random((n, vessel.ndim)) * 1.1 * (upper - lower)
    v = rng.normal(size=x.shape)
    before_x, before_v = x.copy(), v.copy()
    outside = vessel.sdf(x) > 0
    h, skin = 0.01, 1e-5
    node_sdf, origin, shape = _nodes(vessel, h)
    threads = 2
    moved = project_into_vessel(
        vessel.kind, vessel.params, x, v, skin, chunk_starts(n, threads),
        np.zeros((threads, 4)), node_sdf, origin, h, shape,
    )  # fmt: skip
    assert moved == outside.sum() > 0
    np.testing.assert_array_equal(x[~outside], before_x[~outside])
    np.testing.assert_array_equal(v[~outside], before_v[~outside])
    # moved particles are inside, at most skin deep (exactly skin off edges and corners)
    phi = vessel.sdf(x[outside])
    assert (phi < 0).all() and (phi >= -skin - 1e-12).all()
    if isinstance(vessel, Drum) and vessel.ndim == 2:  # no edges: exactly skin deep
        np.testing.assert_allclose(phi, -skin, atol=1e-12)
    # no velocity leaves through the wall it crossed
    normals = vessel.normal(before_x[outside])  # the normal the particle left by
    assert (np.einsum("ij,ij->i", v[outside], normals) <= 1e-12).all()
