"""The steady flow's divergence removal (blendxr/ade/solenoidal.py).

Checked against facts independent of the solver: the face-flux divergence is counted by a
second reduction (``face_divergence``); a field built from a stream function or a vector
potential is discretely solenoidal and must come back unchanged; a gradient added to it
must go, at the approximate projection's second order.
"""

import numpy as np
import pytest

import blendxr as bx
from blendxr.ade.phases import _divergence_treatment
from blendxr.ade.solenoidal import BED_FILL, face_divergence, remove_divergence


def disc_bed(n=40, radius=0.42):
    """Fill of a disc of material in an n x n grid of unit extent, with partial edge cells."""
    x = (np.arange(n) + 0.5) / n
    X, Y = np.meshgrid(x, x, indexing="ij")
    r = np.hypot(X - 0.5, Y - 0.5)
    return np.clip((radius - r) * n + 0.5, 0.0, 1.0), X, Y, 1.0 / n


def test_a_random_field_is_counted_by_both_reductions_and_outside_cells_are_untouched():
    fill, X, _, h = disc_bed()
    rng = np.random.default_rng(3)
    u = rng.normal(size=fill.shape), rng.normal(size=fill.shape)
    projected, info = remove_divergence(u, fill, (h, h))
    bed = fill > BED_FILL
    assert info["bed_cells"] == bed.sum()
    before = np.abs(face_divergence(u, bed, (h, h)))[bed.ravel()].mean()
    after = np.abs(face_divergence(projected, bed, (h, h)))[bed.ravel()].mean()
    assert info["divergence_before"] == pytest.approx(before, rel=1e-12)
    assert info["divergence_after"] == pytest.approx(after, rel=1e-12)
    assert after < before
    for given, out in zip(u, projected, strict=True):
        np.testing.assert_array_equal(out[~bed], given[~bed])


def _bump(r2, radius):
    """A smooth bump that is exactly zero beyond ``radius``."""
    return np.clip(1 - r2 / radius**2, 0, None) ** 4


def _central(field, axis, h):
    return (np.roll(field, -1, axis) - np.roll(field, 1, axis)) / (2 * h)


def test_a_gradient_is_removed_at_second_order():
    # u = grad(phi) + curl(psi): the projection must return the curl, the gradient gone
    # to the error of the approximate projection (second order for a smooth field)
    errors = []
    for n in (24, 48, 96):
        fill, X, Y, h = disc_bed(n=n)
        r2 = (X - 0.5) ** 2 + (Y - 0.5) ** 2
        a2 = 0.3**2
        w = _bump(r2, 0.3)
        # phi = w(r) * (1 + X): its gradient, exactly
        dw = -8 * (1 - r2 / a2) ** 3 / a2 * (r2 < a2)
        gx = dw * (X - 0.5) * (1 + X) + w
        gy = dw * (Y - 0.5) * (1 + X)
        psi = w * np.sin(7 * X)
        cx, cy = _central(psi, 1, h), -_central(psi, 0, h)
        (px, py), _ = remove_divergence((gx + cx, gy + cy), fill, (h, h))
        errors.append(np.abs(px - cx).sum() + np.abs(py - cy).sum())
        errors[-1] /= np.abs(gx).sum() + np.abs(gy).sum()
    orders = np.log2(np.array(errors[:-1]) / errors[1:])
    assert errors[-1] < 0.02, errors
    assert orders.min() > 1.7, (errors, orders)


def test_a_field_from_a_stream_function_is_unchanged():
    # central differences of a stream function: D F u is the central divergence, which
    # vanishes identically; the stream function is flat near the bed's edge, so the
    # closed edge drops no flux
    fill, X, Y, h = disc_bed(n=48)
    r2 = (X - 0.5) ** 2 + (Y - 0.5) ** 2
    psi = _bump(r2, 0.3) * np.sin(7 * X)
    u, v = _central(psi, 1, h), -_central(psi, 0, h)
    assert np.abs(psi[fill < 1]).max() == 0.0
    (pu, pv), _ = remove_divergence((u, v), fill, (h, h))
    scale = np.abs(u).max()
    np.testing.assert_allclose(pu, u, atol=1e-9 * scale)
    np.testing.assert_allclose(pv, v, atol=1e-9 * scale)


def test_a_curl_is_unchanged_in_3d_with_cells_that_are_not_cubes():
    # the central curl of a vector potential has zero central divergence identically
    n = 20
    h = (1 / n, 1 / n, 0.8 / n)
    x = (np.arange(n) + 0.5) / n
    X, Y, Z = np.meshgrid(x, x, 0.8 * x, indexing="ij")
    fill = ((np.hypot(X - 0.5, Y - 0.5) < 0.45) & (Z < 0.7)).astype(float)
    r2 = (X - 0.5) ** 2 + (Y - 0.5) ** 2 + (Z - 0.35) ** 2
    w = _bump(r2, 0.3)
    A = (w * np.sin(5 * Y), w * X, w * np.cos(3 * X))
    d = [[_central(A[c], a, h[a]) for a in range(3)] for c in range(3)]
    u = (d[2][1] - d[1][2], d[0][2] - d[2][0], d[1][0] - d[0][1])
    out, _ = remove_divergence(u, fill, h)
    scale = max(np.abs(c).max() for c in u)
    for given, got in zip(u, out, strict=True):
        np.testing.assert_allclose(got, given, atol=1e-9 * scale)


def test_a_bed_of_one_cell_is_left_as_it_is():
    fill = np.zeros((5, 5))
    fill[2, 2] = 1.0
    u = np.ones((5, 5)), np.zeros((5, 5))
    out, info = remove_divergence(u, fill, (0.1, 0.1))
    np.testing.assert_array_equal(out[0], u[0])
    assert info["bed_cells"] == 1


def test_only_steady_computed_flows_are_projected():
    steady = bx.flows.rolling_drum(ndim=2, cells=16)
    assert _divergence_treatment(steady, 1, "remove") == "keep (analytic flow)"
    computed = steady.copy()
    del computed.attrs["analytic"]
    assert _divergence_treatment(computed, 1, "remove") == "remove"
    assert _divergence_treatment(computed, 1, "keep") == "keep"
    assert _divergence_treatment(computed, 12, "remove") == "keep (transient flow)"
    with pytest.raises(ValueError, match="'remove' or 'keep'"):
        _divergence_treatment(computed, 1, "drop")


def test_the_mixing_run_projects_a_steady_computed_flow_and_records_it():
    flow = bx.flows.rolling_drum(ndim=2, cells=24)
    del flow.attrs["analytic"]  # stands in for a steady flow from the solver or a file
    runs = {}
    for treatment in ("remove", "keep"):
        runs[treatment] = bx.mix(
            flow, revolutions=0.2, cells=48, progress=False, steady_divergence=treatment
        )
    removed, kept = runs["remove"].attrs, runs["keep"].attrs
    assert removed["steady_divergence"] == "remove"
    assert removed["flow_divergence_after"] < removed["flow_divergence_before"]
    assert kept["steady_divergence"] == "keep" and "flow_divergence_before" not in kept


def test_a_projection_cut_short_by_its_iteration_limit_says_so(monkeypatch):
    from blendxr.ade import solenoidal

    real = solenoidal.spl.lsmr

    def capped(A, b, **kwargs):
        return real(A, b, **{**kwargs, "maxiter": 2})

    monkeypatch.setattr(solenoidal.spl, "lsmr", capped)
    fill, _, _, h = disc_bed(n=24)
    rng = np.random.default_rng(1)
    u = rng.normal(size=fill.shape), rng.normal(size=fill.shape)
    with pytest.warns(RuntimeWarning, match="iteration limit"):
        remove_divergence(u, fill, (h, h))
