"""Dataset contracts: build flow and mixing datasets, check them against the schema files.

The JSON Schema files in ``data_schemas/`` (shipped as ``blendxr.data_schemas``) are the
single source of truth. Each describes the structure that ``xarray.Dataset.to_dict(data=False)``
returns (dims, coords, data_vars, attrs), and carries extra keywords, all prefixed
``x-blendxr-``, for what JSON Schema cannot say about the values themselves:

``x-blendxr-attrs``
    exact attribute values of a variable (``units``, ``axis``); the builders write them.
``x-blendxr-long_name``
    the ``long_name`` the builders write (any non-empty ``long_name`` is accepted).
``x-blendxr-finite``
    no NaN or infinity anywhere.
``x-blendxr-minimum``, ``x-blendxr-maximum``, ``x-blendxr-exclusiveMaximum``
    range of the values that are not NaN; closed bounds allow ``x-blendxr-range-atol``
    of round-off (a bounded scheme may leave -1e-20 where it means 0).
``x-blendxr-enum``
    the only values allowed (the vessel mask).
``x-blendxr-equally-spaced``
    a strictly increasing coordinate with uniform spacing (relative tolerance
    ``x-blendxr-rtol`` of the step, plus the round-off of the stored dtype).
``x-blendxr-cyclic``
    the values are ``k * P / n`` for ``k = 0 .. n-1`` with period ``P``: equally spaced in
    ``[0, P)`` starting at 0, so that the last value wraps onto the first.
``x-blendxr-increasing``
    strictly increasing values.
``x-blendxr-global-attrs``
    exact global attribute values (``Conventions``, ``blendxr_schema``); the builders write them.

`validate` reads the structure without touching the data, then evaluates every value check
of every variable in a single ``dask.compute`` call, so a lazily opened file is streamed
through once, chunk by chunk, and never loaded whole.
"""

from __future__ import annotations

import copy
import datetime as _dt
import functools
import json
import math
import operator
import re
import warnings
from collections.abc import Mapping
from importlib.resources import files
from typing import Any

import dask
import dask.array as da
import jsonschema
import numpy as np
import xarray as xr

from ._version import __version__

try:
    import tomllib
except ImportError:  # Python 3.10 has no tomllib; the scene text is then not parsed here.
    tomllib = None

__all__ = [
    "SCHEMA_NAMES",
    "SchemaError",
    "flow_dataset",
    "load_schema",
    "mixing_dataset",
    "validate",
]

#: Names accepted by `load_schema`.
SCHEMA_NAMES = ("flow", "mixing", "scene")

# Attributes every dataset gets from its builder; users may not override these through
# ``attrs=`` because they identify the contract the dataset follows.
_PROTECTED_ATTRS = ("Conventions", "blendxr_schema", "source")


class SchemaError(ValueError):
    """A dataset (or file) does not follow its blendxr schema.

    Parameters
    ----------
    faults : list of str
        One line per fault, each starting with the variable, dimension or attribute at fault.
    schema : str, optional
        The schema checked against, e.g. ``"flow/1"``.
    source : str, optional
        Where the dataset came from (a file path), shown first in the message.

    Attributes
    ----------
    faults : list of str
        Every fault found, not just the first.
    """

    def __init__(self, faults, *, schema: str | None = None, source: str | None = None):
        if isinstance(faults, str):
            faults = [faults]
        self.faults = list(faults)
        self.schema = schema
        self.source = None if source is None else str(source)
        super().__init__(self._message())

    def _message(self) -> str:
        where = f"{self.source}: " if self.source else ""
        what = f"does not follow blendxr schema {self.schema}" if self.schema else "is not valid"
        n = len(self.faults)
        head = f"{where}dataset {what} ({n} fault{'s' if n != 1 else ''}):"
        return "\n".join([head] + [f"  - {fault}" for fault in self.faults])

    def __str__(self) -> str:
        return self._message()

    def __reduce__(self):
        # Keep the fault list intact when the error crosses process boundaries (dask workers).
        return (_rebuild_schema_error, (self.faults, self.schema, self.source))


def _rebuild_schema_error(faults, schema, source):
    return SchemaError(faults, schema=schema, source=source)


# --------------------------------------------------------------------------------------
# Schema files
# --------------------------------------------------------------------------------------


@functools.cache
def _schema_text(kind: str) -> str:
    resource = files("blendxr.data_schemas").joinpath(f"{kind}.schema.json")
    return resource.read_text(encoding="utf-8")


@functools.cache
def _schema(kind: str) -> dict:
    return json.loads(_schema_text(kind))


def _kind(name: str) -> str:
    kind = str(name).split("/", 1)[0]
    if kind not in SCHEMA_NAMES:
        raise ValueError(f"unknown schema {name!r}; expected one of {', '.join(SCHEMA_NAMES)}")
    return kind


def load_schema(name: str) -> dict:
    """Load one of the package's JSON Schema files.

    Parameters
    ----------
    name : {"flow", "mixing", "scene"}
        Which schema; a versioned name such as ``"flow/1"`` is accepted too.

    Returns
    -------
    dict
        The parsed schema (a fresh copy; changing it does not affect validation).

    Raises
    ------
    ValueError
        If `name` is not one of the known schemas.
    FileNotFoundError
        If the schema file is missing from the installation.
    """
    return copy.deepcopy(_schema(_kind(name)))


@functools.cache
def _validator(kind: str) -> jsonschema.Draft202012Validator:
    schema = _schema(kind)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _variable_specs(schema: Mapping) -> dict[str, dict]:
    """Per-variable schema entries (coords and data_vars) by variable name."""
    props = schema.get("properties", {})
    specs: dict[str, dict] = {}
    for group in ("coords", "data_vars"):
        specs.update(props.get(group, {}).get("properties", {}))
    return specs


def _cf_attrs(spec: Mapping) -> dict[str, str]:
    attrs = {}
    if "x-blendxr-long_name" in spec:
        attrs["long_name"] = spec["x-blendxr-long_name"]
    attrs.update(spec.get("x-blendxr-attrs", {}))
    return attrs


# --------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------


def _plain(value: Any) -> Any:
    """JSON-ready copy of a ``to_dict`` tree: lists, Python scalars, non-finite floats as text.

    Non-finite floats become strings so that a NaN ``rpm`` fails the ``number`` type instead
    of slipping through ``minimum`` (every comparison with NaN is false).
    """
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.item() if value.ndim == 0 or value.size == 1 else value.tolist())
    if isinstance(value, np.generic):
        return _plain(value.item())
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, float) and not math.isfinite(value):
        return repr(value)
    return value


_GROUP_WORD = {"dims": "dimension", "coords": "coordinate", "data_vars": "data variable"}


def _where(path: list) -> str:
    if not path:
        return "dataset"
    head, rest = path[0], [str(p) for p in path[1:]]
    if head == "attrs":
        return f"attribute {rest[0]}" if rest else "global attributes"
    if head == "dims":
        return f"dim {rest[0]}" if rest else "dims"
    if head in ("coords", "data_vars") and rest:
        return ".".join(rest)
    return ".".join([str(head)] + rest)


def _describe(error: jsonschema.ValidationError) -> str:
    path = list(error.absolute_path)
    where = _where(path)
    if error.validator == "required":
        match = re.match(r"^'(.*)' is a required property$", error.message)
        missing = match.group(1) if match else error.message
        if not path:
            return f"{missing}: missing from the dataset"
        if len(path) == 1 and path[0] in _GROUP_WORD:
            return f"{missing}: missing {_GROUP_WORD[path[0]]}"
        if path == ["attrs"]:
            return f"attribute {missing}: missing global attribute"
        if len(path) == 3 and path[0] in ("coords", "data_vars") and path[2] == "attrs":
            return f"{path[1]}: missing attribute {missing!r}"
        return f"{where}: missing {missing!r}"
    if error.validator == "not":
        return f"{where}: {error.schema.get('description', 'not allowed here')}"
    if error.validator == "const":
        return f"{where}: is {error.instance!r}, expected {error.validator_value!r}"
    if error.validator == "enum":
        return f"{where}: is {error.instance!r}, expected one of {error.validator_value!r}"
    return f"{where}: {error.message}"


def _structure_faults(kind: str, instance: dict) -> list[str]:
    errors = sorted(_validator(kind).iter_errors(instance), key=lambda e: list(e.absolute_path))
    return [_describe(e) for e in errors]


def _attribute_faults(ds: xr.Dataset, schema: Mapping) -> list[str]:
    faults = []
    for name, spec in _variable_specs(schema).items():
        if name not in ds.variables:
            continue
        attrs = ds.variables[name].attrs
        for key, wanted in spec.get("x-blendxr-attrs", {}).items():
            # Absence is already reported by the JSON Schema part ("required").
            if key in attrs and _plain(attrs[key]) != wanted:
                faults.append(f"{name}: {key} is {_plain(attrs[key])!r}, expected {wanted!r}")
    for key, wanted in schema.get("x-blendxr-global-attrs", {}).items():
        if key == "blendxr_schema":
            continue  # dispatched on, hence equal
        if key in ds.attrs and _plain(ds.attrs[key]) != wanted:
            faults.append(f"attribute {key}: is {_plain(ds.attrs[key])!r}, expected {wanted!r}")
    for name in ds.coords:
        var = ds.variables[name]
        if "_FillValue" in var.attrs or var.encoding.get("_FillValue") is not None:
            faults.append(f"{name}: coordinates must have no _FillValue")
    scene = ds.attrs.get("scene")
    if tomllib is not None and isinstance(scene, str) and scene.strip():
        try:
            tomllib.loads(scene)
        except tomllib.TOMLDecodeError as exc:
            faults.append(f"attribute scene: not valid TOML ({exc})")
    return faults


def _as_dask(var: xr.Variable) -> da.Array:
    if var.chunks is not None:
        return var.data
    if not getattr(var, "_in_memory", True) and var.ndim > 1:
        # A file opened without dask: read it one leading slice at a time, not whole.
        return var.chunk({var.dims[0]: 1}).data
    return da.from_array(np.asarray(var.values), chunks=-1)


def _lazy_checks(ds: xr.Dataset, schema: Mapping, xp) -> dict:
    """Every value check, keyed by (variable, check).

    With ``xp = dask.array`` the checks are lazy reductions, to be computed together; with
    ``xp = numpy`` (all data already in memory) they are evaluated on the spot, which spares
    building a task graph for small in-memory datasets.
    """
    checks: dict[tuple[str, str], Any] = {}
    for name, spec in _variable_specs(schema).items():
        if name not in ds.variables:
            continue
        var = ds.variables[name]
        if var.dtype.kind not in "biuf":
            continue  # a dtype fault is reported by the structure check
        arr = np.asarray(var.values) if xp is np else _as_dask(var)
        floating = var.dtype.kind == "f"
        if spec.get("x-blendxr-finite") and floating:
            checks[name, "nonfinite"] = (~xp.isfinite(arr)).sum()
        lo = spec.get("x-blendxr-minimum")
        hi = spec.get("x-blendxr-maximum")
        hi_open = spec.get("x-blendxr-exclusiveMaximum")
        if (lo is not None or hi is not None or hi_open is not None) and arr.size:
            atol = float(schema.get("x-blendxr-range-atol", 0.0))
            tests = []
            if lo is not None:
                tests.append(arr < lo - atol)
            if hi is not None:
                tests.append(arr > hi + atol)
            if hi_open is not None:
                tests.append(arr >= hi_open)
            outside = functools.reduce(operator.or_, tests)
            checks[name, "outside"] = outside.sum()
            if floating:
                checks[name, "min"] = xp.nanmin(arr)
                checks[name, "max"] = xp.nanmax(arr)
            else:
                checks[name, "min"] = arr.min()
                checks[name, "max"] = arr.max()
        if "x-blendxr-enum" in spec:
            checks[name, "not_in_enum"] = (~xp.isin(arr, spec["x-blendxr-enum"])).sum()
        needs_values = (
            spec.get("x-blendxr-equally-spaced")
            or spec.get("x-blendxr-increasing")
            or "x-blendxr-cyclic" in spec
        )
        if needs_values and var.ndim == 1:
            checks[name, "values"] = arr
    return checks


def _fmt(value: float) -> str:
    return f"{value:.9g}"


def _spacing_faults(name: str, values: np.ndarray, rtol: float) -> list[str]:
    n = values.size
    if n < 2 or not np.all(np.isfinite(values)):
        return []
    x = values.astype(np.float64)
    step = (x[-1] - x[0]) / (n - 1)
    if not step > 0:
        return [f"{name}: cell centres must increase (first {_fmt(x[0])}, last {_fmt(x[-1])})"]
    ideal = x[0] + step * np.arange(n)
    # Float32 coordinates carry round-off of their own magnitude, not of the step.
    tol = rtol * step + 4 * np.finfo(values.dtype).eps * np.max(np.abs(x))
    if np.max(np.abs(x - ideal)) > tol:
        steps = np.diff(x)
        return [
            f"{name}: not equally spaced (steps from {_fmt(steps.min())} to "
            f"{_fmt(steps.max())}; the grid must be uniform)"
        ]
    return []


def _cyclic_faults(name: str, values: np.ndarray, period: float, rtol: float) -> list[str]:
    n = values.size
    if n == 0:
        return []
    x = values.astype(np.float64)
    if not np.all(np.isfinite(x)):
        return [f"{name}: values must be finite"]
    faults = []
    eps = 4 * np.finfo(values.dtype).eps * period
    step = period / n
    if abs(x[0]) > rtol * step + eps:
        faults.append(f"{name}: must start at 0, starts at {_fmt(x[0])}")
    if x.min() < -eps or x.max() >= period - eps:
        faults.append(
            f"{name}: values must lie in [0, {_fmt(period)}), "
            f"found {_fmt(x.min())} .. {_fmt(x.max())}"
        )
    if np.max(np.abs(x - x[0] - step * np.arange(n))) > rtol * step + eps:
        steps = np.diff(x) if n > 1 else np.array([np.nan])
        faults.append(
            f"{name}: must be equally spaced by {_fmt(period)}/n = {_fmt(step)} for n = {n} "
            f"values (steps from {_fmt(steps.min())} to {_fmt(steps.max())})"
        )
    return faults


def _value_faults(ds: xr.Dataset, schema: Mapping) -> list[str]:
    in_memory = all(
        getattr(var, "_in_memory", False) and var.chunks is None for var in ds.variables.values()
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN slices in nanmin/nanmax
        if in_memory:
            result = _lazy_checks(ds, schema, np)
        else:
            # One pass over lazy data: every reduction of every variable in one graph.
            (result,) = dask.compute(_lazy_checks(ds, schema, da))
    rtol = float(schema.get("x-blendxr-rtol", 1e-6))
    faults = []
    for name, spec in _variable_specs(schema).items():
        if (name, "nonfinite") in result and result[name, "nonfinite"]:
            faults.append(f"{name}: {int(result[name, 'nonfinite'])} values are NaN or infinite")
        if (name, "outside") in result and result[name, "outside"]:
            lo = spec.get("x-blendxr-minimum")
            hi = spec.get("x-blendxr-maximum", spec.get("x-blendxr-exclusiveMaximum"))
            right = "]" if "x-blendxr-maximum" in spec else ")"
            span = f"[{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"
            faults.append(
                f"{name}: {int(result[name, 'outside'])} values outside {span} "
                f"(min {float(result[name, 'min'])!r}, max {float(result[name, 'max'])!r})"
            )
        if (name, "not_in_enum") in result and result[name, "not_in_enum"]:
            faults.append(
                f"{name}: {int(result[name, 'not_in_enum'])} values not in {spec['x-blendxr-enum']}"
            )
        if (name, "values") in result:
            values = np.asarray(result[name, "values"])
            if spec.get("x-blendxr-equally-spaced"):
                faults += _spacing_faults(name, values, rtol)
            if "x-blendxr-cyclic" in spec:
                faults += _cyclic_faults(name, values, float(spec["x-blendxr-cyclic"]), rtol)
            if spec.get("x-blendxr-increasing") and values.size > 1:
                if not np.all(np.diff(values) > 0):
                    faults.append(f"{name}: values must increase strictly")
    return faults


def validate(ds: xr.Dataset, *, schema: str | None = None) -> xr.Dataset:
    """Check a flow or mixing dataset against its schema and report every fault.

    The schema is chosen by the dataset's ``blendxr_schema`` attribute (``"flow/1"`` or
    ``"mixing/1"``). Structure (dims, coordinates, variables, dtypes, attributes) is checked
    by the JSON Schema file; the values (finite velocities, ``fill`` in [0, 1], the vessel
    mask in {0, 1}, uniform grids, ``rev_phase`` equally spaced in [0, 1) from 0, ...) by
    the file's ``x-blendxr-`` keywords. Lazy (dask) data is reduced in one pass.

    Parameters
    ----------
    ds : xarray.Dataset
        The dataset to check.
    schema : str, optional
        If given (e.g. ``"flow/1"``), the dataset must declare exactly this schema.

    Returns
    -------
    xarray.Dataset
        `ds` itself, unchanged, so that calls can be chained.

    Raises
    ------
    SchemaError
        Listing every fault found, each naming the variable, dimension or attribute.
    """
    if not isinstance(ds, xr.Dataset):
        raise TypeError(f"validate expects an xarray.Dataset, got {type(ds).__name__}")
    declared = ds.attrs.get("blendxr_schema")
    known = ("flow/1", "mixing/1")
    if not isinstance(declared, str):
        fault = (
            "attribute blendxr_schema: missing global attribute"
            if declared is None
            else f"attribute blendxr_schema: is {declared!r}, expected a string"
        )
        raise SchemaError([f"{fault}; expected one of {', '.join(known)}"], schema=schema)
    if schema is not None and declared != schema:
        raise SchemaError(
            [f"attribute blendxr_schema: is {declared!r}, expected {schema!r}"], schema=schema
        )
    kind = declared.split("/", 1)[0]
    if kind not in ("flow", "mixing"):
        raise SchemaError(
            [f"attribute blendxr_schema: is {declared!r}, expected one of {', '.join(known)}"]
        )
    spec = _schema(kind)
    if spec["x-blendxr-global-attrs"]["blendxr_schema"] != declared:
        raise SchemaError(
            [
                f"attribute blendxr_schema: is {declared!r}; this blendxr {__version__} "
                f"reads {spec['x-blendxr-global-attrs']['blendxr_schema']!r}"
            ]
        )
    instance = _plain(ds.to_dict(data=False))
    faults = _structure_faults(kind, instance)
    faults += _attribute_faults(ds, spec)
    faults += _value_faults(ds, spec)
    if faults:
        raise SchemaError(list(dict.fromkeys(faults)), schema=declared)
    return ds


#: global attributes a flow from another code may lack: blendxr fills them in when it
#: reads one (they record provenance, not physics)
_PROVENANCE_ATTRS = ("Conventions", "title", "source", "history", "scene")


def conform_flow(ds: xr.Dataset, *, origin: str | None = None) -> xr.Dataset:
    """A flow from another code made to follow ``flow/1`` where only form is missing.

    Strict on what blendxr writes, lenient on what it reads: a flow whose physics is
    complete (the velocities, fill and vessel with their units, ``rev_phase``, the
    coordinates in metres, and the ``frame``, ``rpm`` and ``gravity`` attributes) is
    accepted with what it lacked filled in -- the ``blendxr_schema`` attribute, the CF
    attributes ``Conventions``, ``title``, ``source``, ``history`` and ``scene``, a
    ``_FillValue`` on the coordinates (xarray's default), the ``long_name`` and ``axis``
    attributes, a float 0/1 vessel mask, the dimension order -- and each of them named
    in a line of the result's ``history`` (and in the ``conformed`` attribute). Missing
    or wrong physics is left for :func:`validate` to refuse. A dataset that needs
    nothing is returned unchanged.

    Parameters
    ----------
    ds : xarray.Dataset
    origin : str, optional
        Where it came from (a file), for the history line.
    """
    if ds.attrs.get("blendxr_schema") not in (None, "flow/1"):
        return ds  # another kind: validate says so
    spec = _schema("flow")
    notes: list[str] = []
    out = ds.copy()
    out.attrs = dict(ds.attrs)
    if "blendxr_schema" not in out.attrs:
        out.attrs["blendxr_schema"] = "flow/1"
        notes.append("the blendxr_schema attribute")
    for key in _PROVENANCE_ATTRS:
        if not isinstance(out.attrs.get(key), str) or (key == "title" and not out.attrs[key]):
            notes.append(f"the {key} attribute")
            out.attrs.pop(key, None)
    source = out.attrs.get("source")
    if source is not None and not source.startswith("blendxr "):
        out.attrs["source"] = f"blendxr {__version__} (read from: {source})"
        notes.append(f"a blendxr source (it had {source!r})")
    out.attrs.setdefault("source", f"blendxr {__version__} (read from another code)")
    out.attrs.setdefault("Conventions", spec["x-blendxr-global-attrs"]["Conventions"])
    out.attrs.setdefault("title", f"flow read from {origin or 'another code'}")
    out.attrs.setdefault("scene", "")
    specs = _variable_specs(spec)
    filled = set()
    for name in out.coords:
        var = out[name]
        if "_FillValue" in var.attrs or var.encoding.get("_FillValue") is not None:
            var.attrs.pop("_FillValue", None)
            var.encoding["_FillValue"] = None
            filled.add("coordinates free of _FillValue")
    for name, vspec in specs.items():
        if name not in out.variables:
            continue
        attrs = out[name].attrs
        if "long_name" not in attrs and "x-blendxr-long_name" in vspec:
            attrs["long_name"] = vspec["x-blendxr-long_name"]
            filled.add("long_name attributes")
        axis = vspec.get("x-blendxr-attrs", {}).get("axis")
        if axis is not None and "axis" not in attrs:
            attrs["axis"] = axis
            filled.add("axis attributes")
    notes.extend(sorted(filled))
    if "vessel" in out and out["vessel"].dtype.kind == "f":
        values = np.asarray(out["vessel"].values)
        if np.all(np.isin(values, (0.0, 1.0))):
            out["vessel"] = out["vessel"].astype(np.int8)
            notes.append("an integer vessel mask")
    order = [d for d in ("rev_phase", "x", "y", "z") if d in out.dims]
    for name in list(out.data_vars):
        dims = out[name].dims
        wanted = tuple(d for d in order if d in dims)
        if set(dims) == set(wanted) and dims != wanted:
            out[name] = out[name].transpose(*wanted)
            notes.append(f"{name} in the dimension order {wanted}")
    if not notes:
        return ds
    text = "; ".join(notes)
    out.attrs["conformed"] = text
    out.attrs["history"] = _append_history(
        out.attrs.get("history"), f"read a flow from {origin or 'another code'} that lacked: {text}"
    )
    return out


# --------------------------------------------------------------------------------------
# Builders
# --------------------------------------------------------------------------------------


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _append_history(history: str | None, what: str) -> str:
    """Return `history` with one more line: UTC timestamp, blendxr version, what was done."""
    line = f"{_utc_now()} blendxr {__version__}: {what}"
    history = (history or "").rstrip("\n")
    return f"{history}\n{line}" if history else line


def _scene_text(scene: Any) -> str:
    """The scene as TOML text: accepts text, a mapping, or an object that renders itself."""
    if scene is None:
        return ""
    if isinstance(scene, str):
        return scene
    for method in ("to_toml", "as_toml", "dumps"):
        if callable(getattr(scene, method, None)):
            text = getattr(scene, method)()
            if isinstance(text, str):
                return text
    if isinstance(scene, Mapping):
        import tomli_w

        return tomli_w.dumps(dict(scene))
    raise TypeError(
        "scene must be TOML text, a mapping or an object with to_toml(), "
        f"got {type(scene).__name__}"
    )


def _is_lazy(a: Any) -> bool:
    return isinstance(a, da.Array)


def _coordinate(name: str, values: Any) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {arr.shape}")
    return arr


def _field(name: str, values: Any, shape: tuple[int, ...], lead: str) -> Any:
    """A (lead, *grid) array: takes it as given, or repeats a grid-shaped array along lead."""
    arr = values if _is_lazy(values) else np.asarray(values)
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    if not _is_lazy(arr) and arr.dtype.kind != "f":
        arr = arr.astype(np.float64)
    if tuple(arr.shape) == shape:
        return arr
    if tuple(arr.shape) == shape[1:]:
        if _is_lazy(arr):
            return da.broadcast_to(arr[None], shape)
        return np.repeat(arr[None], shape[0], axis=0)
    raise ValueError(
        f"{name} has shape {tuple(arr.shape)}, expected {shape} ({lead}, grid) "
        f"or the grid shape {shape[1:]}"
    )


def _mask(name: str, values: Any, shape: tuple[int, ...]) -> Any:
    arr = values if _is_lazy(values) else np.asarray(values)
    if tuple(arr.shape) != shape:
        raise ValueError(f"{name} has shape {tuple(arr.shape)}, expected the grid shape {shape}")
    if _is_lazy(arr):
        return arr.astype(np.int8)
    # Cast only when lossless, so that a bad mask is reported by validate instead of hidden.
    as_int8 = arr.astype(np.int8)
    return as_int8 if np.array_equal(as_int8, arr) else arr


def _global_attrs(kind: str, title: str, scene: Any, what: str, attrs: Mapping | None) -> dict:
    extra = dict(attrs or {})
    clash = [k for k in _PROTECTED_ATTRS if k in extra]
    if clash:
        raise ValueError(f"attrs may not set {', '.join(clash)}: the builder owns them")
    history = extra.pop("history", None)
    out = {
        "Conventions": _schema(kind)["x-blendxr-global-attrs"]["Conventions"],
        "title": title,
        "source": f"blendxr {__version__}",
        "history": _append_history(history, what),
        "scene": _scene_text(scene),
    }
    out.update(_schema(kind)["x-blendxr-global-attrs"])
    out.update(extra)
    return out


def _assign_cf(ds: xr.Dataset, kind: str) -> None:
    for name, spec in _variable_specs(_schema(kind)).items():
        if name in ds.variables:
            ds[name].attrs.update(_cf_attrs(spec))


def flow_dataset(
    x,
    y,
    rev_phase,
    vx,
    vy,
    fill,
    vessel,
    *,
    z=None,
    vz=None,
    frame: str = "vessel",
    rpm: float,
    gravity: float = 9.81,
    scene=None,
    title: str = "blendxr flow",
    attrs: Mapping | None = None,
) -> xr.Dataset:
    """Build a validated flow dataset (schema ``flow/1``) from plain arrays.

    Parameters
    ----------
    x, y : array_like, shape (nx,), (ny,)
        Cell centres in metres, uniformly spaced.
    rev_phase : array_like, shape (n,)
        Fractions of a revolution, ``k / n`` for ``k = 0 .. n-1``.
    vx, vy : array_like, shape (n, nx, ny[, nz])
        Velocity of the material (m/s) relative to `frame`. An array of the grid shape
        is taken as steady and repeated for every phase. NumPy or dask arrays.
    fill : array_like, shape (n, nx, ny[, nz])
        Volume fraction of material in each cell, 0 to 1 (grid shape: steady).
    vessel : array_like, shape (nx, ny[, nz])
        1 inside the vessel, 0 outside; stored as int8.
    z : array_like, shape (nz,), optional
        Cell centres along the rotation axis; give it (with `vz`) for a 3-D dataset, leave
        it out for a 2-D dataset, which then has no z at all.
    vz : array_like, optional
        z velocity, 3-D only.
    frame : {"vessel", "lab"}
        Frame the velocities are given in.
    rpm : float
        Rotation speed in revolutions per minute (>= 0); the period is ``60 / rpm`` s.
    gravity : float
        Gravitational acceleration in m/s².
    scene : str, mapping or Scene, optional
        The scene, stored as TOML text in the ``scene`` attribute (empty when None).
    title : str
        The ``title`` attribute.
    attrs : mapping, optional
        More global attributes (solver diagnostics, ``analytic``, ...). A ``history``
        entry is kept as earlier history and the builder's line appended to it.

    Returns
    -------
    xarray.Dataset
        The flow dataset, with CF attributes taken from ``flow.schema.json``.

    Raises
    ------
    ValueError
        If shapes do not fit together.
    SchemaError
        If the values break the contract (NaN velocities, fill outside [0, 1], ...).
    """
    if (z is None) != (vz is None):
        raise ValueError("a 3-D flow needs both z and vz; a 2-D flow has neither")
    axes = {"x": _coordinate("x", x), "y": _coordinate("y", y)}
    if z is not None:
        axes["z"] = _coordinate("z", z)
    phases = _coordinate("rev_phase", rev_phase)
    grid = tuple(a.size for a in axes.values())
    shape = (phases.size,) + grid
    dims = ("rev_phase",) + tuple(axes)
    fields = {"vx": vx, "vy": vy}
    if vz is not None:
        fields["vz"] = vz
    fields["fill"] = fill
    data_vars = {name: (dims, _field(name, v, shape, "rev_phase")) for name, v in fields.items()}
    data_vars["vessel"] = (tuple(axes), _mask("vessel", vessel, grid))
    coords = {"rev_phase": ("rev_phase", phases)}
    coords.update({name: (name, a) for name, a in axes.items()})
    clash = [k for k in ("frame", "rpm", "gravity") if k in (attrs or {})]
    if clash:
        raise ValueError(f"give {', '.join(clash)} as arguments of flow_dataset, not in attrs")
    global_attrs = _global_attrs("flow", title, scene, "flow_dataset", attrs)
    global_attrs.update(frame=frame, rpm=float(rpm), gravity=float(gravity))
    ds = xr.Dataset(data_vars, coords=coords, attrs=global_attrs)
    _assign_cf(ds, "flow")
    return validate(ds)


def mixing_dataset(
    x,
    y,
    *,
    z=None,
    time,
    revolution,
    rsd,
    intensity,
    mass_a,
    snapshot_time,
    snapshot_revolution,
    c,
    scene=None,
    title: str = "blendxr mixing",
    attrs: Mapping | None = None,
) -> xr.Dataset:
    """Build a validated mixing dataset (schema ``mixing/1``) from plain arrays.

    Parameters
    ----------
    x, y : array_like, shape (nx,), (ny,)
        Cell centres in metres of the concentration grid, uniformly spaced.
    z : array_like, shape (nz,), optional
        Cell centres along the rotation axis; omit for a 2-D dataset (no z at all).
    time : array_like, shape (nt,)
        Times of the mixing curves in seconds, strictly increasing.
    revolution : array_like, shape (nt,)
        Revolutions completed at each time.
    rsd, intensity : array_like, shape (nt,)
        Relative standard deviation and segregation intensity of species A.
    mass_a : array_like, shape (nt,)
        Total volume of species A in m³ (per metre of depth in 2-D).
    snapshot_time, snapshot_revolution : array_like, shape (ns,)
        Time (s) and revolutions of each concentration snapshot.
    c : array_like, shape (ns, nx, ny[, nz])
        Fraction of species A in the solids, NaN where there is no material.
    scene : str, mapping or Scene, optional
        The scene, stored as TOML text in the ``scene`` attribute (empty when None).
    title : str
        The ``title`` attribute.
    attrs : mapping, optional
        More global attributes (scheme, dt, grid, k1, k2, d, wall time, ...).

    Returns
    -------
    xarray.Dataset
        The mixing dataset, with CF attributes taken from ``mixing.schema.json``.

    Raises
    ------
    ValueError
        If shapes do not fit together.
    SchemaError
        If the values break the contract.
    """
    axes = {"x": _coordinate("x", x), "y": _coordinate("y", y)}
    if z is not None:
        axes["z"] = _coordinate("z", z)
    grid = tuple(a.size for a in axes.values())
    t = _coordinate("time", time)
    snap_t = _coordinate("snapshot_time", snapshot_time)
    curves = {}
    for name, values in (
        ("revolution", revolution),
        ("rsd", rsd),
        ("intensity", intensity),
        ("mass_a", mass_a),
    ):
        curves[name] = _coordinate(name, values)
        if curves[name].size != t.size:
            raise ValueError(f"{name} has {curves[name].size} values, time has {t.size}")
    snap_rev = _coordinate("snapshot_revolution", snapshot_revolution)
    if snap_rev.size != snap_t.size:
        raise ValueError(
            f"snapshot_revolution has {snap_rev.size} values, snapshot_time has {snap_t.size}"
        )
    c_arr = c if _is_lazy(c) else np.asarray(c, dtype=np.float64)
    if tuple(c_arr.shape) == grid and snap_t.size == 1:
        c_arr = c_arr[None]
    if tuple(c_arr.shape) != (snap_t.size,) + grid:
        raise ValueError(
            f"c has shape {tuple(c_arr.shape)}, expected {(snap_t.size,) + grid} (snapshot, grid)"
        )
    data_vars = {
        "c": (("snapshot",) + tuple(axes), c_arr),
        "rsd": ("time", curves["rsd"]),
        "intensity": ("time", curves["intensity"]),
        "mass_a": ("time", curves["mass_a"]),
    }
    coords = {
        "time": ("time", t),
        "revolution": ("time", curves["revolution"]),
        "snapshot_time": ("snapshot", snap_t),
        "snapshot_revolution": ("snapshot", snap_rev),
    }
    coords.update({name: (name, a) for name, a in axes.items()})
    global_attrs = _global_attrs("mixing", title, scene, "mixing_dataset", attrs)
    ds = xr.Dataset(data_vars, coords=coords, attrs=global_attrs)
    _assign_cf(ds, "mixing")
    return validate(ds)
