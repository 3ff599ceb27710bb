"""Property-based tests: scene values and corrupted flows end in a result or a clear
blendxr error, within a bounded time -- never another exception, never a hang."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import blendxr as bx
from blendxr.scene import scene_keys

#: what a user may be told: a bad value or file (ValueError, SceneError and SchemaError
#: are ValueErrors), or a run that went unstable and was stopped (BlowUpError)
CLEAR = (ValueError, bx.BlowUpError)
#: seconds any one example may take (the mixing runs carry a wall_time well below it)
BOUND_S = 30.0

VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(10**12), max_value=10**12),
    st.sampled_from([0, 1, -1, 0.5, 1e-12, 1e30, "", "floor", "top-bottom", True, None]),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.text(max_size=8),
)


@settings(max_examples=300, deadline=None)
@given(key=st.sampled_from(scene_keys()), value=VALUES)
def test_any_scene_value_gives_a_scene_or_a_scene_error(key, value):
    if value is None:
        return
    try:
        scene = bx.load_scene("tote-small", {key: value})
    except bx.SceneError:
        return
    assert isinstance(scene, bx.Scene)


@pytest.fixture(scope="module")
def small_flow():
    return bx.flows.swirl(ndim=2, cells=8, n_phases=4, size=0.2)


MIX_KEYS = [k for k in scene_keys() if k.startswith(("mixing.", "numerics."))]


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(key=st.sampled_from(MIX_KEYS), value=VALUES)
def test_any_mixing_value_ends_in_a_result_or_a_clear_error(small_flow, key, value):
    if value is None:
        return
    started = time.perf_counter()
    try:
        scene = bx.load_scene("swirl-2d", {key: value})
        bx.mix(small_flow, scene, wall_time=2.0, progress=False)
    except CLEAR:
        pass
    assert time.perf_counter() - started < BOUND_S


def _drop(ds, name):
    return ds.drop_vars(name)


def _nan_patch(ds, name, k):
    values = ds[name].values.copy()
    values.reshape(-1)[k % values.size] = np.nan
    return ds.assign({name: (ds[name].dims, values, ds[name].attrs)})


def _scale(ds, name, factor):
    return ds.assign({name: ds[name] * factor})


def _permute(ds, name):
    return ds.assign({name: ds[name].transpose(*reversed(ds[name].dims))})


def _shift(ds, coord, k):
    values = ds[coord].values.copy()
    values[k % len(values)] += 0.37 * float(values[1] - values[0])
    return ds.assign_coords({coord: (coord, values, ds[coord].attrs)})


def _drop_attr(ds, name):
    out = ds.copy()
    out.attrs = {k: v for k, v in ds.attrs.items() if k != name}
    return out


def _unit(ds, name):
    out = ds.copy()
    out[name] = ds[name].assign_attrs(units="furlong")
    return out


CORRUPTIONS = st.one_of(
    st.tuples(st.just(_drop), st.sampled_from(["vx", "vy", "fill", "vessel"])),
    st.tuples(st.just(_nan_patch), st.sampled_from(["vx", "vy", "fill"]), st.integers(0, 10**6)),
    st.tuples(
        st.just(_scale),
        st.sampled_from(["vx", "vy", "fill"]),
        st.sampled_from([-1.0, 0.0, 1e-30, 2.0, 1e3, 1e30]),
    ),
    st.tuples(st.just(_permute), st.sampled_from(["vx", "fill", "vessel"])),
    st.tuples(st.just(_shift), st.sampled_from(["x", "y", "rev_phase"]), st.integers(0, 100)),
    st.tuples(st.just(_drop_attr), st.sampled_from(["rpm", "frame", "gravity", "scene"])),
    st.tuples(st.just(_unit), st.sampled_from(["vx", "fill", "x"])),
)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(corruptions=st.lists(CORRUPTIONS, min_size=1, max_size=3))
def test_a_corrupted_flow_mixes_or_is_refused_clearly(small_flow, corruptions, tmp_path_factory):
    flow = small_flow.copy(deep=True)
    try:
        for make, *args in corruptions:
            flow = make(flow, *args)
    except (ValueError, KeyError):
        return  # the corruption itself does not apply to this dataset
    started = time.perf_counter()
    for source in ("memory", "file"):
        try:
            if source == "file":
                path = tmp_path_factory.mktemp("fuzz") / "flow.nc"
                flow.to_netcdf(path)
                flow_in = path
            else:
                flow_in = flow
            mixed = bx.mix(flow_in, revolutions=0.1, cells=8, wall_time=2.0, progress=False)
        except CLEAR:
            continue
        assert math.isfinite(float(mixed["rsd"].values[0]))
    assert time.perf_counter() - started < BOUND_S
