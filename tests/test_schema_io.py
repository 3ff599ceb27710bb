"""Dataset contracts (blendxr.schema) and netCDF input/output (blendxr.io)."""

from __future__ import annotations

import errno
import json
import os
import pickle
import re
import shutil
import subprocess

import dask
import jsonschema
import netCDF4
import numpy as np
import pytest
import xarray as xr

import blendxr as bx
from blendxr import io as bio
from blendxr.flow import analytic
from blendxr.schema import (
    SchemaError,
    flow_dataset,
    load_schema,
    mixing_dataset,
    validate,
)


def faults_of(ds, **kwargs) -> list[str]:
    with pytest.raises(SchemaError) as info:
        validate(ds, **kwargs)
    return info.value.faults


def single_fault(ds, *words):
    """Validation fails, and some fault mentions every one of `words`."""
    faults = faults_of(ds)
    assert any(all(w in f for w in words) for f in faults), faults
    return faults


# ---------------------------------------------------------------------------------------
# The schema files
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["flow", "mixing"])
def test_schema_files_are_draft_2020_12(name):
    schema = load_schema(name)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)
    assert schema["x-blendxr-global-attrs"]["blendxr_schema"] == f"{name}/1"


def test_load_schema_scene_and_errors():
    assert isinstance(load_schema("scene"), dict)
    assert load_schema("flow/1") == load_schema("flow")
    with pytest.raises(ValueError, match="unknown schema"):
        load_schema("nonsense")


def test_load_schema_returns_a_copy():
    schema = load_schema("flow")
    schema["properties"].clear()
    assert load_schema("flow")["properties"]


def test_builders_take_units_and_names_from_the_schema(flow_3d, mixing_2d):
    for ds, kind in ((flow_3d, "flow"), (mixing_2d, "mixing")):
        props = load_schema(kind)["properties"]
        for group in ("coords", "data_vars"):
            for name, spec in props[group]["properties"].items():
                if name not in ds.variables:
                    continue
                for key, value in spec["x-blendxr-attrs"].items():
                    assert ds[name].attrs[key] == value
                assert ds[name].attrs["long_name"] == spec["x-blendxr-long_name"]
    assert flow_3d.x.attrs["axis"] == "X" and flow_3d.z.attrs["axis"] == "Z"
    assert flow_3d.vx.attrs["units"] == "m s-1"
    assert mixing_2d.mass_a.attrs["units"] == "m3"
    assert mixing_2d.time.attrs["units"] == "s"


def test_builders_set_global_attributes(flow_2d, mixing_3d, scene_toml):
    for ds, kind in ((flow_2d, "flow/1"), (mixing_3d, "mixing/1")):
        assert ds.attrs["Conventions"] == "CF-1.11"
        assert ds.attrs["blendxr_schema"] == kind
        assert re.fullmatch(r"blendxr \S+", ds.attrs["source"])
        assert re.match(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ blendxr ", ds.attrs["history"])
        assert isinstance(ds.attrs["scene"], str)
    assert flow_2d.attrs["scene"] == ""
    assert mixing_3d.attrs["scene"] == scene_toml
    assert flow_2d.attrs["frame"] in ("vessel", "lab")


# ---------------------------------------------------------------------------------------
# validate: acceptance
# ---------------------------------------------------------------------------------------


def test_validate_accepts_every_analytic_flow(any_flow):
    assert validate(any_flow) is any_flow


def test_validate_accepts_mixing(any_mixing):
    assert validate(any_mixing) is any_mixing


def test_mixing_without_snapshots_is_valid(make_mixing):
    ds = make_mixing(2, n_snapshots=0)
    assert ds.sizes["snapshot"] == 0
    validate(ds)


def test_float32_coordinates_pass_the_spacing_check(make_flow):
    # Far from the origin, float32 round-off dwarfs 1e-6 of the step.
    ds = make_flow("swirl-2d")
    ds = ds.assign_coords(x=(ds.x + 1000.0).astype(np.float32).assign_attrs(ds.x.attrs))
    validate(ds)


def test_validate_is_lazy_and_computes_once(flow_3d, monkeypatch):
    lazy = flow_3d.chunk({"rev_phase": 1})
    calls = []
    original = dask.compute

    def counting(*args, **kwargs):
        calls.append(1)
        return original(*args, **kwargs)

    monkeypatch.setattr(dask, "compute", counting)
    validate(lazy)
    assert len(calls) == 1
    assert isinstance(lazy.vx.data, dask.array.Array)  # nothing was loaded into the dataset


def test_validate_streams_a_file_opened_without_dask(tmp_path, flow_3d):
    path = bio.write_dataset(flow_3d, tmp_path / "flow.nc")
    with xr.open_dataset(path) as ds:
        validate(ds)
        # read slice by slice for the checks, never cached whole in the dataset
        assert not ds.variables["vx"]._in_memory


# ---------------------------------------------------------------------------------------
# validate: rejection, with the variable named and every fault listed
# ---------------------------------------------------------------------------------------


def test_missing_variable(flow_2d):
    single_fault(flow_2d.drop_vars("vy"), "vy", "missing")


def test_missing_coordinate(mixing_2d):
    single_fault(mixing_2d.drop_vars("revolution"), "revolution", "missing")


def test_missing_variable_attribute(flow_2d):
    ds = flow_2d.copy()
    del ds.fill.attrs["long_name"]
    single_fault(ds, "fill", "long_name")


def test_missing_axis(flow_2d):
    ds = flow_2d.copy()
    ds.y.attrs.pop("axis")
    single_fault(ds, "y", "axis")


def test_wrong_axis(flow_2d):
    ds = flow_2d.copy()
    ds.x.attrs["axis"] = "Y"
    single_fault(ds, "x", "axis", "'X'")


def test_wrong_units(flow_2d):
    ds = flow_2d.copy()
    ds.vx.attrs["units"] = "m/s"
    single_fault(ds, "vx", "units", "m s-1")


def test_nan_velocity_is_named(flow_3d):
    ds = flow_3d.copy(deep=True)
    ds.vz.values[1, 2, 3, 2] = np.nan
    single_fault(ds, "vz", "NaN")


def test_infinite_velocity_is_named(flow_2d):
    ds = flow_2d.copy(deep=True)
    ds.vx.values[0, 0, 0] = np.inf
    single_fault(ds, "vx")


@pytest.mark.parametrize("bad", [-0.1, 1.2, np.nan])
def test_fill_outside_unit_interval(flow_2d, bad):
    ds = flow_2d.copy(deep=True)
    ds.fill.values[2, 3, 3] = bad
    single_fault(ds, "fill")


def test_round_off_at_range_bounds_is_tolerated(flow_2d, mixing_2d):
    # A bounded scheme may leave -1e-20 where it means 0; that is not a fault.
    ds = flow_2d.copy(deep=True)
    ds.fill.values[0, 0, 0] = -1e-20
    ds.fill.values[0, 0, 1] = 1 + 1e-12
    validate(ds)
    mixed = mixing_2d.copy(deep=True)
    material = np.isfinite(mixed.c.values)
    mixed.c.values[material] = -1e-15
    validate(mixed)


def test_vessel_not_a_mask(flow_2d):
    ds = flow_2d.copy(deep=True)
    ds.vessel.values[0, 0] = 2
    single_fault(ds, "vessel", "[0, 1]")


def test_concentration_outside_unit_interval(mixing_2d):
    ds = mixing_2d.copy(deep=True)
    material = np.isfinite(ds.c.values)
    ds.c.values[material] = 1.5
    single_fault(ds, "c", "outside")


def test_concentration_may_be_nan(mixing_2d):
    assert np.isnan(mixing_2d.c.values).any()
    validate(mixing_2d)


def test_non_uniform_grid(flow_3d):
    z = flow_3d.z.values.copy()
    z[2] += 0.1 * (z[1] - z[0])
    ds = flow_3d.assign_coords(z=("z", z, flow_3d.z.attrs))
    single_fault(ds, "z", "equally spaced")


def test_decreasing_grid(flow_2d):
    ds = flow_2d.isel(x=slice(None, None, -1))
    single_fault(ds, "x", "increase")


@pytest.mark.parametrize(
    "phases, words",
    [
        ([0.1, 0.35, 0.6, 0.85], ("start at 0",)),
        ([0.0, 0.25, 0.5, 1.0], ("[0, 1)",)),
        ([0.0, 0.2, 0.5, 0.75], ("equally spaced",)),
        ([0.0, 0.1, 0.2, 0.3], ("equally spaced",)),  # even, but not one whole revolution
    ],
)
def test_bad_rev_phase(flow_2d, phases, words):
    ds = flow_2d.assign_coords(rev_phase=("rev_phase", phases, flow_2d.rev_phase.attrs))
    single_fault(ds, "rev_phase", *words)


@pytest.mark.parametrize("name", ["Conventions", "title", "source", "history", "scene", "rpm"])
def test_missing_global_attribute(flow_2d, name):
    ds = flow_2d.copy()
    del ds.attrs[name]
    single_fault(ds, name, "missing")


@pytest.mark.parametrize(
    "name, value, word",
    [
        ("frame", "rotor", "frame"),
        ("rpm", -1.0, "rpm"),
        ("rpm", float("nan"), "rpm"),
        ("gravity", "9.81", "gravity"),
        ("Conventions", "CF-1.6", "Conventions"),
        ("scene", "[vessel\nshape = 1", "scene"),
    ],
)
def test_bad_global_attribute(flow_2d, name, value, word):
    ds = flow_2d.copy()
    ds.attrs[name] = value
    single_fault(ds, word)


def test_missing_or_unknown_schema_attribute(flow_2d):
    ds = flow_2d.copy()
    del ds.attrs["blendxr_schema"]
    single_fault(ds, "blendxr_schema")
    ds.attrs["blendxr_schema"] = "flow/99"
    single_fault(ds, "blendxr_schema", "flow/99")


def test_expected_schema(mixing_2d):
    faults = faults_of(mixing_2d, schema="flow/1")
    assert "blendxr_schema" in faults[0] and "flow/1" in faults[0]


def test_2d_dataset_with_vz_or_z_coordinate(flow_2d):
    ds = flow_2d.assign(vz=flow_2d.vx.copy())
    single_fault(ds, "vz", "2-D")


def test_3d_dataset_without_vz(flow_3d):
    single_fault(flow_3d.drop_vars("vz"), "vz", "missing")


def test_transposed_variable(flow_3d):
    ds = flow_3d.assign(vx=flow_3d.vx.transpose("rev_phase", "z", "y", "x"))
    single_fault(ds, "vx", "dims")


def test_coordinate_with_fill_value(flow_2d):
    ds = flow_2d.copy()
    ds.x.encoding["_FillValue"] = np.nan
    single_fault(ds, "x", "_FillValue")


def test_every_fault_is_listed(flow_3d):
    ds = flow_3d.copy(deep=True)
    ds.vx.values[0, 4, 4, 4] = np.nan
    ds.vy.values[1, 4, 4, 4] = np.nan
    ds.fill.values[0, 4, 4, 4] = 1.5
    ds.vz.attrs["units"] = "cm s-1"
    del ds.attrs["history"]
    ds = ds.drop_vars("vessel")
    with pytest.raises(SchemaError) as info:
        validate(ds)
    faults, message = info.value.faults, str(info.value)
    for name in ("vx", "vy", "fill", "vz", "history", "vessel"):
        assert any(f.startswith(name) or name in f.split(":")[0] for f in faults), (name, faults)
        assert name in message
    assert len(faults) == 6
    assert "6 faults" in message
    assert all(f in message for f in faults)


def test_schema_error_is_a_value_error_and_pickles():
    error = SchemaError(["vx: 3 values are NaN", "fill: outside"], schema="flow/1", source="f.nc")
    assert isinstance(error, ValueError)
    again = pickle.loads(pickle.dumps(error))
    assert again.faults == error.faults and str(again) == str(error)
    assert str(error).startswith("f.nc: ")


# ---------------------------------------------------------------------------------------
# Builders: clear errors for bad input
# ---------------------------------------------------------------------------------------


def _grid2(n=4):
    x = (np.arange(n) + 0.5) / n
    return x, x.copy(), np.zeros((1, n, n)), np.ones((n, n), dtype=np.int8)


def test_flow_dataset_broadcasts_steady_fields():
    x, y, v, vessel = _grid2()
    ds = flow_dataset(x, y, [0.0, 0.5], v[0], v[0], vessel, vessel, rpm=1.0)
    assert ds.vx.shape == (2, 4, 4) and ds.fill.shape == (2, 4, 4)
    assert ds.vessel.dtype == np.int8


def test_flow_dataset_bad_shapes():
    x, y, v, vessel = _grid2()
    with pytest.raises(ValueError, match="vx has shape"):
        flow_dataset(x, y, [0.0], np.zeros((1, 3, 4)), v, vessel, vessel, rpm=1.0)
    with pytest.raises(ValueError, match="both z and vz"):
        flow_dataset(x, y, [0.0], v, v, vessel, vessel, z=x, rpm=1.0)
    with pytest.raises(ValueError, match="vessel has shape"):
        flow_dataset(x, y, [0.0], v, v, vessel, vessel[:2], rpm=1.0)


def test_flow_dataset_reports_bad_values():
    x, y, v, vessel = _grid2()
    bad = v.copy()
    bad[0, 1, 1] = np.nan
    with pytest.raises(SchemaError, match="vy"):
        flow_dataset(x, y, [0.0], v, bad, vessel, vessel, rpm=1.0)
    with pytest.raises(SchemaError, match="vessel"):
        flow_dataset(x, y, [0.0], v, v, vessel, vessel * 0.5, rpm=1.0)


def test_flow_dataset_attrs_and_history():
    x, y, v, vessel = _grid2()
    ds = flow_dataset(
        x, y, [0.0], v, v, vessel, vessel, rpm=1.0,
        attrs={"history": "earlier step", "steps": 10},
    )  # fmt: skip
    assert ds.attrs["steps"] == 10
    assert ds.attrs["history"].splitlines()[0] == "earlier step"
    assert len(ds.attrs["history"].splitlines()) == 2
    with pytest.raises(ValueError, match="blendxr_schema"):
        flow_dataset(x, y, [0.0], v, v, vessel, vessel, rpm=1.0, attrs={"blendxr_schema": "x"})
    with pytest.raises(ValueError, match="rpm"):
        flow_dataset(x, y, [0.0], v, v, vessel, vessel, rpm=1.0, attrs={"rpm": 2.0})


def test_flow_dataset_scene_as_mapping():
    x, y, v, vessel = _grid2()
    ds = flow_dataset(x, y, [0.0], v, v, vessel, vessel, rpm=1.0, scene={"vessel": {"r": 0.1}})
    assert "[vessel]" in ds.attrs["scene"]


def test_mixing_dataset_bad_lengths(make_mixing):
    ds = make_mixing(2)
    kwargs = dict(
        time=ds.time.values,
        revolution=ds.revolution.values[:-1],
        rsd=ds.rsd.values,
        intensity=ds.intensity.values,
        mass_a=ds.mass_a.values,
        snapshot_time=ds.snapshot_time.values,
        snapshot_revolution=ds.snapshot_revolution.values,
        c=ds.c.values,
    )
    with pytest.raises(ValueError, match="revolution"):
        mixing_dataset(ds.x.values, ds.y.values, **kwargs)
    kwargs["revolution"] = ds.revolution.values
    kwargs["c"] = ds.c.values[:, :-1]
    with pytest.raises(ValueError, match="c has shape"):
        mixing_dataset(ds.x.values, ds.y.values, **kwargs)


# ---------------------------------------------------------------------------------------
# Writing and opening
# ---------------------------------------------------------------------------------------


def _assert_same_values(written, read):
    for name, var in written.data_vars.items():
        expected = var.values.astype(np.float64)
        got = read[name].values.astype(np.float64)
        scale = max(np.nanmax(np.abs(expected)), 1e-30) if expected.size else 1.0
        np.testing.assert_allclose(got, expected, rtol=0, atol=2e-7 * scale, equal_nan=True)
    for name in written.coords:
        np.testing.assert_array_equal(read[name].values, written[name].values)


@pytest.mark.parametrize("recipe", ["swirl-2d", "rotation-3d-bed", "uniform-3d"])
def test_flow_round_trip(tmp_path, recipe, make_flow):
    ds = make_flow(recipe)
    path = bio.write_dataset(ds, tmp_path / "flow.nc", history="test write")
    assert path == tmp_path / "flow.nc"
    back = bio.open_flow(path)
    _assert_same_values(ds, back)
    # lazy: one dask chunk per phase, the grid whole
    n = ds.sizes["rev_phase"]
    for name in ("vx", "vy", "fill"):
        assert isinstance(back[name].data, dask.array.Array)
        assert back[name].chunks[0] == (1,) * n
        assert all(len(c) == 1 for c in back[name].chunks[1:])
    assert back.vessel.dtype == np.int8
    for key in ("Conventions", "title", "source", "scene", "blendxr_schema", "frame", "analytic"):
        assert back.attrs[key] == ds.attrs[key]
    assert back.attrs["rpm"] == ds.attrs["rpm"] and back.attrs["gravity"] == ds.attrs["gravity"]
    lines = back.attrs["history"].splitlines()
    assert lines[:-1] == ds.attrs["history"].splitlines()
    assert lines[-1].endswith("test write")
    back.close()


def test_on_disk_encoding(tmp_path, flow_3d):
    path = bio.write_dataset(flow_3d, tmp_path / "flow.nc")
    with netCDF4.Dataset(path) as nc:
        for name in ("vx", "vy", "vz", "fill"):
            var = nc[name]
            assert var.dtype == np.float32
            assert var.filters()["zlib"]
            assert var.chunking()[0] == 1
        assert nc["vessel"].dtype == np.int8
        assert "_FillValue" not in nc["vessel"].ncattrs()
        for name in ("rev_phase", "x", "y", "z"):
            assert "_FillValue" not in nc[name].ncattrs()
        assert nc.getncattr("source").startswith("blendxr ")
        assert "scene" in nc.ncattrs()


def test_mixing_round_trip(tmp_path, mixing_3d, scene_toml):
    path = bio.write_dataset(mixing_3d, tmp_path / "mixing.nc")
    back = bio.open_mixing(path)
    _assert_same_values(mixing_3d, back)
    assert np.array_equal(np.isnan(back.c.values), np.isnan(mixing_3d.c.values))
    assert back.c.chunks[0] == (1,) * mixing_3d.sizes["snapshot"]
    assert back.attrs["scene"] == scene_toml
    assert back.revolution.dims == ("time",)
    back.close()


def test_mixing_without_snapshots_round_trip(tmp_path, make_mixing):
    ds = make_mixing(2, n_snapshots=0)
    back = bio.open_mixing(bio.write_dataset(ds, tmp_path / "m.nc"), chunks=None)
    assert back.sizes["snapshot"] == 0


def test_lazy_dataset_can_be_written(tmp_path, flow_2d):
    first = bio.write_dataset(flow_2d, tmp_path / "a.nc")
    lazy = bio.open_flow(first)
    second = bio.write_dataset(lazy, tmp_path / "b.nc")
    back = bio.open_flow(second, chunks=None)
    assert not isinstance(back.vx.data, dask.array.Array)
    _assert_same_values(flow_2d, back)
    assert len(back.attrs["history"].splitlines()) == 3
    lazy.close()


def test_open_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        bio.open_flow(tmp_path / "absent.nc")
    with pytest.raises(FileNotFoundError):
        bio.open_mixing(tmp_path / "absent.nc")


def test_open_not_netcdf(tmp_path):
    path = tmp_path / "flow.nc"
    path.write_text("not a netCDF file")
    with pytest.raises(SchemaError, match="flow.nc"):
        bio.open_flow(path)


def test_open_wrong_kind(tmp_path, mixing_2d):
    path = bio.write_dataset(mixing_2d, tmp_path / "mixing.nc")
    with pytest.raises(SchemaError, match="blendxr_schema"):
        bio.open_flow(path)


def test_open_invalid_file_names_path_and_variable(tmp_path, flow_2d):
    path = bio.write_dataset(flow_2d, tmp_path / "flow.nc")
    with netCDF4.Dataset(path, "a") as nc:
        nc["vy"][1, 2, 2] = np.nan
        nc["vx"].units = "km"
    with pytest.raises(SchemaError) as info:
        bio.open_flow(path)
    message = str(info.value)
    assert str(path) in message and "vy" in message and "vx" in message


def test_write_refuses_invalid_dataset(tmp_path, flow_2d):
    ds = flow_2d.copy(deep=True)
    ds.fill.values[:] = 2.0
    with pytest.raises(SchemaError, match="fill"):
        bio.write_dataset(ds, tmp_path / "flow.nc")
    assert list(tmp_path.iterdir()) == []


def test_write_into_missing_directory(tmp_path, flow_2d):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        bio.write_dataset(flow_2d, tmp_path / "nowhere" / "flow.nc")


def test_written_file_keeps_mode_of_replaced_file(tmp_path, flow_2d):
    path = bio.write_dataset(flow_2d, tmp_path / "flow.nc")
    assert (path.stat().st_mode & 0o777) == 0o644
    os.chmod(path, 0o640)
    bio.write_dataset(flow_2d, path)
    assert (path.stat().st_mode & 0o777) == 0o640


# ---------------------------------------------------------------------------------------
# Atomic writes
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("when", ["before", "after"])
def test_failed_write_leaves_target_untouched(tmp_path, flow_2d, mixing_2d, monkeypatch, when):
    target = bio.write_dataset(mixing_2d, tmp_path / "out.nc")
    before = target.read_bytes()
    original = xr.Dataset.to_netcdf

    def failing(self, path=None, *args, **kwargs):
        if when == "after":
            original(self, path, *args, **kwargs)  # the temporary file is complete...
        raise OSError("disk full")  # ...and then the write fails anyway

    monkeypatch.setattr(xr.Dataset, "to_netcdf", failing)
    with pytest.raises(OSError, match="disk full"):
        bio.write_dataset(flow_2d, target)
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["out.nc"]


def test_a_full_disk_is_named_as_such(tmp_path, flow_2d, monkeypatch):
    """The netCDF library reports a full disk as "NetCDF: HDF error"."""
    import collections
    import shutil

    def failing(self, path=None, *args, **kwargs):
        raise OSError("NetCDF: HDF error")

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(xr.Dataset, "to_netcdf", failing)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10**9, 10**9, 1024))
    with pytest.raises(OSError, match="no space left on the device") as err:
        bio.write_dataset(flow_2d, tmp_path / "flow.nc")
    assert err.value.errno == errno.ENOSPC
    assert list(tmp_path.iterdir()) == []


def test_interrupted_write_leaves_no_temporary(tmp_path, flow_2d, monkeypatch):
    def interrupted(self, path=None, *args, **kwargs):
        with open(path, "wb") as f:
            f.write(b"half a file")
        raise KeyboardInterrupt

    monkeypatch.setattr(xr.Dataset, "to_netcdf", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bio.write_dataset(flow_2d, tmp_path / "flow.nc")
    assert list(tmp_path.iterdir()) == []


def test_failed_checkpoint_leaves_target_untouched(tmp_path, monkeypatch):
    target = bio.write_checkpoint(tmp_path / "run.ckpt", {"a": np.arange(3.0)}, {"t": 1.0})
    before = target.read_bytes()
    with pytest.raises(TypeError, match="not JSON-encodable"):
        bio.write_checkpoint(target, {"a": np.arange(4.0)}, {"bad": object()})
    assert target.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["run.ckpt"]


# ---------------------------------------------------------------------------------------
# CF conformance
# ---------------------------------------------------------------------------------------

# cfchecks fetches the CF standard-name, area-type and region tables over the network
# unless given local copies. blendxr files use no standard_name, area type or region, so
# empty tables are exact for them (any standard_name would be reported as unknown).
_TABLES = {
    "standard_names.xml": "<standard_name_table><version_number>0</version_number>"
    "<last_modified>none</last_modified></standard_name_table>",
    "area_types.xml": "<area_type_table><version_number>0</version_number>"
    "<date>none</date></area_type_table>",
    "regions.xml": "<standardized_region_list><version_number>0</version_number>"
    "<date>none</date></standardized_region_list>",
}


def _cf_errors(path, tmp_path) -> tuple[int, str]:
    for name, text in _TABLES.items():
        (tmp_path / name).write_text(f'<?xml version="1.0"?>\n{text}\n')
    command = [
        shutil.which("cfchecks"),
        "-v", "1.8",
        "-s", str(tmp_path / "standard_names.xml"),
        "-a", str(tmp_path / "area_types.xml"),
        "-r", str(tmp_path / "regions.xml"),
        str(path),
    ]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    if "requires UNIDATA UDUNITS-2" in output:  # a system library, installed by .ci/run
        pytest.skip("the CF checker cannot run: the UDUNITS-2 library is missing")
    match = re.search(r"ERRORS detected:\s*(\d+)", output)
    assert match, output
    return int(match.group(1)), output


@pytest.mark.skipif(shutil.which("cfchecks") is None, reason="the cfchecks command is absent")
@pytest.mark.parametrize("kind", ["flow-3d", "flow-2d", "mixing-3d"])
def test_written_files_pass_the_cf_checker(tmp_path, kind, make_flow, make_mixing):
    ds = {
        "flow-3d": lambda: make_flow("rotation-3d-bed"),
        "flow-2d": lambda: make_flow("swirl-2d"),
        "mixing-3d": lambda: make_mixing(3),
    }[kind]()
    path = bio.write_dataset(ds, tmp_path / "out.nc")
    # The checker knows CF up to 1.8 and rejects the newer version name blendxr declares
    # (CF-1.11) as "not CF data"; check a copy that declares the version checked against.
    copy = tmp_path / "as_cf18.nc"
    shutil.copyfile(path, copy)
    with netCDF4.Dataset(copy, "a") as nc:
        nc.Conventions = "CF-1.8"
    errors, output = _cf_errors(copy, tmp_path)
    assert errors == 0, output
    # The original differs only in the declared version.
    errors, output = _cf_errors(path, tmp_path)
    error_lines = [line for line in output.splitlines() if line.startswith("ERROR:")]
    assert errors <= 1 and all("2.6.1" in line for line in error_lines), output


# ---------------------------------------------------------------------------------------
# Checkpoints
# ---------------------------------------------------------------------------------------


def test_checkpoint_round_trip_is_bit_exact(tmp_path):
    rng = np.random.default_rng(3)
    special = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 5e-324, 1e308, np.pi])
    arrays = {
        "c": rng.standard_normal((5, 4, 3)),
        "special": special,
        "snapshot_0.5": rng.random((2, 3)),
        "count": np.arange(12, dtype=np.int64).reshape(3, 4),
        "small": np.arange(4, dtype=np.int16),
        "mask": rng.random((3, 3)) > 0.5,
        "scalar": np.array(2.5),
        "empty": np.zeros((0,)),
        "single": rng.random(6).astype(np.float32),
    }
    meta = {
        "t": 0.1 + 0.2,
        "steps": 12345678901,
        "name": "run",
        "reverse": True,
        "none": None,
        "dt_min": float("inf"),
        "grid": [64, 48],
        "settings": {"k1": 0.01, "scheme": "finite-volume"},
        "fingerprint": "abc123",
        "np_float": np.float64(1 / 3),
    }
    path = bio.write_checkpoint(tmp_path / "run.ckpt", arrays, meta)
    got, got_meta = bio.read_checkpoint(path)
    assert set(got) == set(arrays)
    for name, arr in arrays.items():
        assert got[name].dtype == arr.dtype, name
        assert got[name].shape == arr.shape, name
        if arr.dtype.kind == "f":
            bits = {4: np.uint32, 8: np.uint64}[arr.itemsize]
            assert np.array_equal(got[name].view(bits), arr.view(bits)), name
        else:
            assert np.array_equal(got[name], arr), name
    expected = dict(meta, np_float=1 / 3)
    assert got_meta == expected
    assert type(got_meta["steps"]) is int and type(got_meta["reverse"]) is bool


def test_checkpoint_rejects_bad_input(tmp_path):
    with pytest.raises(TypeError, match="dtype"):
        bio.write_checkpoint(tmp_path / "a", {"s": np.array(["a"])}, {})
    with pytest.raises(ValueError, match="reserved"):
        bio.write_checkpoint(tmp_path / "a", {}, {"source": "x"})
    assert list(tmp_path.iterdir()) == []


def test_read_checkpoint_errors(tmp_path, flow_2d):
    with pytest.raises(FileNotFoundError):
        bio.read_checkpoint(tmp_path / "absent")
    path = bio.write_dataset(flow_2d, tmp_path / "flow.nc")
    with pytest.raises(ValueError, match="not a blendxr checkpoint"):
        bio.read_checkpoint(path)


def test_analytic_recipe_is_json(flow_3d):
    recipe = json.loads(flow_3d.attrs["analytic"])
    assert recipe["flow"] == "solid_body_rotation"
    rebuilt = getattr(analytic, recipe.pop("flow"))(**recipe)
    xr.testing.assert_identical(rebuilt.drop_attrs(), flow_3d.drop_attrs())


# ---------------------------------------------------------------------------------------
# Flows from other codes: strict on writing, lenient on reading
# ---------------------------------------------------------------------------------------


def _third_party_flow(n=20, phases=12):
    """The minimum of docs/architecture.md ("Flows from other codes")."""
    x = y = np.linspace(0.005, 0.195, n)
    v = np.zeros((phases, n, n))
    return xr.Dataset(
        {
            "vx": (("rev_phase", "x", "y"), v + 0.01, {"units": "m s-1"}),
            "vy": (("rev_phase", "x", "y"), v, {"units": "m s-1"}),
            "fill": (("rev_phase", "x", "y"), v + 1.0, {"units": "1"}),
            "vessel": (("x", "y"), np.ones((n, n)), {"units": "1"}),
        },
        coords={
            "rev_phase": ("rev_phase", np.arange(phases) / phases, {"units": "1"}),
            "x": ("x", x, {"units": "m"}),
            "y": ("y", y, {"units": "m"}),
        },
        attrs={"frame": "vessel", "rpm": 10.0, "gravity": 9.81},
    )


def test_a_flow_with_complete_physics_from_another_code_mixes(tmp_path):
    path = tmp_path / "flow.nc"
    _third_party_flow().to_netcdf(path)  # xarray's defaults: _FillValue on coordinates
    flow = bx.open_flow(path)
    for lacked in ("blendxr_schema", "source", "history", "scene", "_FillValue", "vessel"):
        assert lacked in flow.attrs["conformed"]
    mixed = bx.mix(path, revolutions=0.25, cells=20, progress=False)
    assert "it lacked" in mixed.attrs["history"] and mixed.attrs["flow_conformed"]
    assert np.isfinite(mixed["rsd"].values).all()


def test_a_blendxr_flow_written_by_plain_xarray_is_read_as_written(tmp_path, make_flow):
    flow = make_flow("swirl-2d")
    flow.attrs["source"] = "othercode 2.1"
    del flow.attrs["history"]
    path = tmp_path / "plain.nc"
    flow.to_netcdf(path)
    read = bx.open_flow(path, chunks=None)
    assert "othercode 2.1" in read.attrs["source"] and read.attrs["source"].startswith("blendxr ")
    np.testing.assert_array_equal(read["vx"].values, flow["vx"].values)


@pytest.mark.parametrize(
    "spoil, word",
    [
        (lambda ds: ds.drop_vars("fill"), "fill"),
        (lambda ds: ds["vx"].attrs.pop("units") and ds, "vx"),
        (lambda ds: ds.attrs.pop("rpm") and ds, "rpm"),
        (lambda ds: ds.attrs.pop("frame") and ds, "frame"),
        (lambda ds: ds.assign_coords(x=ds.x.assign_attrs(units="mm")), "x"),
    ],
)
def test_a_flow_lacking_physics_is_refused_by_name(tmp_path, spoil, word):
    path = tmp_path / "flow.nc"
    spoil(_third_party_flow()).to_netcdf(path)
    with pytest.raises(SchemaError, match=word):
        bx.open_flow(path)


def test_a_complete_blendxr_flow_is_not_touched(flow_2d):
    from blendxr.schema import conform_flow

    assert conform_flow(flow_2d) is flow_2d


def test_the_canned_scene_is_a_valid_scene():
    """The scene the canned datasets carry is refused nowhere (an unknown key would be)."""
    from conftest import SCENE_TOML

    assert bx.load_scene(SCENE_TOML)["vessel"]["kind"] == "drum"
