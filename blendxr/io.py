"""netCDF in (lazy, validated) and out (atomic), and checkpoints.

Every dataset leaves through `write_dataset` and enters through `open_flow` or
`open_mixing`, so that files always carry the contract of ``blendxr.schema``: CF
attributes, the scene as TOML text, the blendxr version, a timestamped history.

Writes are atomic: the file is written under a temporary name in the target's directory,
flushed to disk, then renamed over the target. A run killed mid-write leaves the previous
file intact, never a truncated one.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
import uuid
from collections.abc import Iterator, Mapping
from pathlib import Path

import netCDF4
import numpy as np
import xarray as xr

from ._version import __version__
from .schema import SchemaError, _append_history, conform_flow, validate

__all__ = [
    "open_flow",
    "open_mixing",
    "read_checkpoint",
    "write_checkpoint",
    "write_dataset",
]

# Leading dimension along which lazily read data is split: one chunk per phase / snapshot,
# the unit the advection-diffusion stepper reads.
_LEAD = {"flow/1": "rev_phase", "mixing/1": "snapshot"}

_COMPRESSION = {"zlib": True, "complevel": 4, "shuffle": True}


# --------------------------------------------------------------------------------------
# Atomic replacement
# --------------------------------------------------------------------------------------


def _fsync_path(path: Path, *, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        if directory:
            return  # some platforms cannot open directories; the rename is still atomic
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


def _new_file_mode(path: Path) -> int:
    if path.exists():
        return path.stat().st_mode & 0o7777
    return 0o644


#: free space below which a failed write is reported as a full disk
_LOW_SPACE = 16 * 2**20


@contextlib.contextmanager
def _atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; on success it replaces `path`, else vanishes."""
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if not parent.is_dir():
        raise FileNotFoundError(
            errno.ENOENT, f"cannot write {target}: directory {parent} does not exist", str(parent)
        )
    fd, name = tempfile.mkstemp(dir=parent, prefix=f".{target.name}.", suffix=".tmp")
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        _fsync_path(tmp)
        os.chmod(tmp, _new_file_mode(target))
        os.replace(tmp, target)
    except OSError as exc:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        # the netCDF library reports a full disk as "NetCDF: HDF error": say what it is
        free = shutil.disk_usage(parent).free
        if exc.errno == errno.ENOSPC or free < _LOW_SPACE:
            raise OSError(
                errno.ENOSPC,
                f"cannot write {target}: no space left on the device ({free / 2**20:.0f} MiB "
                f"free in {parent}); the previous file, if any, is untouched",
                str(target),
            ) from exc
        raise
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise
    _fsync_path(parent, directory=True)


#: temporary files of a write killed midway are removed once they are this old (s): a
#: younger one may belong to a write still running in the same folder
STALE_TEMPORARY_S = 600.0


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files that killed writes left in ``folder`` (the hidden
    ``.NAME.*.tmp`` and ``.NAME.*.staged.*`` files of :func:`_atomic_path` and
    :func:`staged_outputs`) when older than :data:`STALE_TEMPORARY_S`. Returns them."""
    import time

    removed = []
    now = time.time()
    for pattern in (".*.tmp", ".*.staged.*"):
        for path in Path(folder).glob(pattern):
            with contextlib.suppress(FileNotFoundError):
                if path.is_file() and now - path.stat().st_mtime > STALE_TEMPORARY_S:
                    path.unlink()
                    removed.append(path)
    return removed


@contextlib.contextmanager
def staged_outputs(folder: str | os.PathLike) -> Iterator:
    """Write a run's outputs so that they are all new or all old.

    Yields ``stage(name) -> Path``: a hidden path in ``folder`` to write ``name`` to
    (with the atomic writers). When the block ends without error every staged file is
    renamed onto its name, one rename each after all are written; on an error the
    staged files are removed and the folder keeps its previous outputs.
    """
    folder = Path(folder)
    token = uuid.uuid4().hex[:12]  # unique per batch
    staged: dict[str, Path] = {}

    def stage(name: str) -> Path:
        # the name's own suffix last: writers that choose a format by it still can
        staged[name] = folder / f".{name}.{token}.staged{Path(name).suffix}"
        return staged[name]

    try:
        yield stage
        for name, path in staged.items():
            os.replace(path, folder / name)
    except BaseException:
        for path in staged.values():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
        raise
    _fsync_path(folder, directory=True)


# --------------------------------------------------------------------------------------
# Datasets
# --------------------------------------------------------------------------------------


def _encoding(ds: xr.Dataset) -> dict[str, dict]:
    lead = _LEAD.get(ds.attrs.get("blendxr_schema"))
    encoding: dict[str, dict] = {}
    for name in ds.coords:
        # CF: coordinates never have missing values.
        encoding[name] = {"_FillValue": None}
    for name, var in ds.data_vars.items():
        if name == "vessel":
            encoding[name] = {"dtype": "int8", "_FillValue": None, **_COMPRESSION}
            continue
        enc = dict(_COMPRESSION)
        if var.dtype.kind == "f":
            enc["dtype"] = "float32"
        if var.dtype.kind == "b":
            enc.update(dtype="int8", _FillValue=None)
        if lead is not None and var.ndim > 1 and var.dims[0] == lead and 0 not in var.shape:
            # One on-disk chunk per phase/snapshot matches the lazy reader's chunks.
            enc["chunksizes"] = (1,) + var.shape[1:]
        encoding[name] = enc
    return encoding


def write_dataset(ds: xr.Dataset, path: str | os.PathLike, *, history: str | None = None) -> Path:
    """Validate a flow or mixing dataset and write it to netCDF, atomically.

    Data variables are stored as compressed (zlib) float32, the vessel mask as int8,
    coordinates without ``_FillValue``; arrays with a phase or snapshot axis are chunked
    one phase/snapshot per chunk. A history line (UTC timestamp, blendxr version, `history`
    or the file name) is appended. The ``scene`` and ``source`` attributes travel along.

    Parameters
    ----------
    ds : xarray.Dataset
        A ``flow/1`` or ``mixing/1`` dataset; may be lazy (dask), it is written chunk by chunk.
    path : str or path-like
        Target file. Its directory must exist. An existing file is replaced only once the
        new one is complete on disk.
    history : str, optional
        What to record in the history line; default ``"written to <file name>"``.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    SchemaError
        If `ds` does not follow its schema; nothing is written.
    FileNotFoundError
        If the target directory does not exist.
    """
    validate(ds)
    target = Path(path)
    out = ds.copy(deep=False)
    for var in out.variables.values():
        var.encoding = {}
    out.encoding = {}
    out.attrs = dict(out.attrs)
    out.attrs["history"] = _append_history(
        out.attrs.get("history"), history or f"written to {target.name}"
    )
    encoding = _encoding(out)
    with _atomic_path(target) as tmp:
        out.to_netcdf(tmp, mode="w", format="NETCDF4", engine="netcdf4", encoding=encoding)
    return target


def write_result(ds: xr.Dataset, path: str | os.PathLike, *, scene=None, title: str) -> Path:
    """Write a study's result (no flow/mixing schema) to netCDF atomically, with the CF
    global attributes, the blendxr version and the scene.

    Parameters
    ----------
    ds : xarray.Dataset
        Every variable should carry ``units`` and ``long_name``.
    path : str or path-like
    scene : Scene, optional
        Stored as TOML text in the ``scene`` attribute.
    title : str
        The ``title`` attribute.
    """
    from ._version import __version__

    target = Path(path)
    out = ds.copy(deep=False)
    out.attrs = {
        **{k: (int(v) if isinstance(v, bool) else v) for k, v in out.attrs.items()},
        "Conventions": "CF-1.11",
        "title": title,
        "source": f"blendxr {__version__}",
        "scene": scene.to_toml() if scene is not None else str(out.attrs.get("scene", "")),
    }
    out.attrs["history"] = _append_history(out.attrs.get("history"), f"written to {target.name}")
    for name in out.coords:
        out[name].encoding = {"_FillValue": None}
    with _atomic_path(target) as tmp:
        out.to_netcdf(tmp, mode="w", format="NETCDF4", engine="netcdf4")
    return target


def _chunks_for(ds_dims: Mapping[str, int], lead: str, chunks):
    if chunks in ("phase", "snapshot"):
        return {dim: (1 if dim == lead else -1) for dim in ds_dims}
    return chunks


def _existing_file(path) -> Path:
    path = Path(path)
    if not path.is_file():
        if path.is_dir():
            raise IsADirectoryError(errno.EISDIR, f"{path} is a directory, not a file", str(path))
        if path.exists():
            raise OSError(errno.EINVAL, f"{path} is not a regular file", str(path))
        raise FileNotFoundError(errno.ENOENT, f"no such file: {path}", str(path))
    return path


def open_dataset(path: str | os.PathLike) -> xr.Dataset:
    """Open any netCDF file lazily, with a clear error when it is not one.

    Raises
    ------
    FileNotFoundError, IsADirectoryError
        No such file, or a directory.
    SchemaError
        The file is not readable netCDF (named, with the reason).
    """
    path = _existing_file(path)
    try:
        return xr.open_dataset(path, engine="netcdf4", chunks={})
    except (OSError, ValueError) as exc:
        raise SchemaError(
            [f"not a readable netCDF file ({type(exc).__name__}: {exc})"], source=str(path)
        ) from exc


def _open(path, schema: str, chunks) -> xr.Dataset:
    path = _existing_file(path)
    try:
        # Open once without dask to learn the dims; the cost is the header only.
        with xr.open_dataset(path, engine="netcdf4") as probe:
            dims = dict(probe.sizes)
        if chunks is None:
            with xr.open_dataset(path, engine="netcdf4") as eager:
                ds = eager.load()
        else:
            ds = xr.open_dataset(
                path, engine="netcdf4", chunks=_chunks_for(dims, _LEAD[schema], chunks)
            )
    except (OSError, ValueError) as exc:
        raise SchemaError(
            [f"not a readable netCDF file ({type(exc).__name__}: {exc})"],
            schema=schema,
            source=str(path),
        ) from exc
    if schema == "flow/1":
        ds = conform_flow(ds, origin=path.name)  # other codes' flows: form filled in
    try:
        validate(ds, schema=schema)
    except SchemaError as exc:
        ds.close()
        raise SchemaError(exc.faults, schema=schema, source=str(path)) from None
    return ds


def open_flow(path: str | os.PathLike, *, chunks="phase") -> xr.Dataset:
    """Open a flow file lazily and validate it.

    Parameters
    ----------
    path : str or path-like
        A netCDF file written by `write_dataset` (or any file following ``flow/1``).
    chunks : "phase", dict, "auto" or None
        ``"phase"`` (default): dask arrays with one chunk per ``rev_phase``, so the stepper
        reads only the phases it needs. A dict or ``"auto"`` is passed to xarray. None loads
        everything into memory.

    Returns
    -------
    xarray.Dataset
        The validated flow dataset.

    Raises
    ------
    FileNotFoundError
        If `path` does not exist.
    SchemaError
        If the file is not readable netCDF or does not follow ``flow/1``; lists every fault.
    """
    return _open(path, "flow/1", chunks)


def open_mixing(path: str | os.PathLike, *, chunks="snapshot") -> xr.Dataset:
    """Open a mixing file lazily and validate it.

    Parameters
    ----------
    path : str or path-like
        A netCDF file following ``mixing/1``.
    chunks : "snapshot", dict, "auto" or None
        ``"snapshot"`` (default): one dask chunk per concentration snapshot. None loads
        everything into memory.

    Returns
    -------
    xarray.Dataset
        The validated mixing dataset.

    Raises
    ------
    FileNotFoundError
        If `path` does not exist.
    SchemaError
        If the file is not readable netCDF or does not follow ``mixing/1``.
    """
    return _open(path, "mixing/1", chunks)


# --------------------------------------------------------------------------------------
# Checkpoints
# --------------------------------------------------------------------------------------

_CHECKPOINT_MARK = "blendxr_checkpoint"
_JSON_KEYS = "blendxr_json_meta"
_RESERVED = (_CHECKPOINT_MARK, _JSON_KEYS, "source")
_BOOL_MARK = "blendxr_bool"


def _meta_value(value):
    """Value to store as a netCDF attribute, and whether it went through JSON."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, str):
        return value, False
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return value, False
    # bool, None, lists, dicts: netCDF has no type for them, JSON keeps them exact.
    return json.dumps(value, default=_json_default), True


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"a value of type {type(value).__name__} is not JSON-encodable")


def write_json(data: Mapping, path: str | os.PathLike) -> Path:
    """Write ``data`` as indented JSON atomically (NumPy values and paths as plain ones)."""
    target = Path(path)
    with _atomic_path(target) as tmp:
        tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    return target


def write_checkpoint(
    path: str | os.PathLike, arrays: Mapping[str, np.ndarray], meta: Mapping[str, object]
) -> Path:
    """Save the state of a long run, atomically, so that it can resume.

    Parameters
    ----------
    path : str or path-like
        Target file (netCDF-4). Replaced only once the new one is complete on disk.
    arrays : mapping of str to array_like
        Named numeric or boolean arrays, stored bit for bit (float64 stays float64,
        losslessly compressed). Names must be valid netCDF names (no ``/``).
    meta : mapping of str to object
        Scalars (int, float, str) are stored as attributes as they are; anything else
        (bool, None, lists, dicts) as JSON text, decoded again by `read_checkpoint`.

    Returns
    -------
    pathlib.Path
        The path written.
    """
    clash = [key for key in meta if key in _RESERVED]
    if clash:
        raise ValueError(f"checkpoint meta may not use the reserved names {clash}")
    prepared = {}
    for name, values in arrays.items():
        arr = np.asarray(values)
        if arr.dtype.kind not in "biuf":
            raise TypeError(f"checkpoint array {name!r} has unsupported dtype {arr.dtype}")
        prepared[str(name)] = arr
    target = Path(path)
    with _atomic_path(target) as tmp, netCDF4.Dataset(tmp, "w", format="NETCDF4") as nc:
        nc.setncattr(_CHECKPOINT_MARK, 1)
        nc.setncattr("source", f"blendxr {__version__}")
        json_keys = []
        for key, value in meta.items():
            stored, encoded = _meta_value(value)
            nc.setncattr(str(key), stored)
            if encoded:
                json_keys.append(str(key))
        nc.setncattr(_JSON_KEYS, json.dumps(json_keys))
        for name, arr in prepared.items():
            dims = []
            for axis, size in enumerate(arr.shape):
                dim = f"{name}__{axis}"
                # Size 0 would make netCDF create an unlimited dimension; that is fine.
                nc.createDimension(dim, size)
                dims.append(dim)
            stored = arr.astype(np.int8) if arr.dtype.kind == "b" else arr
            var = nc.createVariable(name, stored.dtype, tuple(dims), zlib=True, fill_value=False)
            var.set_auto_maskandscale(False)
            if arr.dtype.kind == "b":
                var.setncattr(_BOOL_MARK, 1)
            if arr.size:
                var[...] = stored
    return target


def read_checkpoint(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Read a checkpoint written by `write_checkpoint`.

    Parameters
    ----------
    path : str or path-like
        The checkpoint file.

    Returns
    -------
    arrays : dict of str to numpy.ndarray
        The arrays, bit-identical to those written.
    meta : dict of str to object
        The metadata, with JSON-encoded values decoded and NumPy scalars made Python scalars.

    Raises
    ------
    FileNotFoundError
        If `path` does not exist.
    ValueError
        If the file is not a blendxr checkpoint.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, f"no such checkpoint: {path}", str(path))
    try:
        nc = netCDF4.Dataset(path, "r")
    except OSError as exc:
        raise ValueError(f"{path}: not a readable checkpoint ({exc})") from exc
    with nc:
        names = nc.ncattrs()
        if _CHECKPOINT_MARK not in names:
            raise ValueError(f"{path}: not a blendxr checkpoint")
        json_keys = set(json.loads(nc.getncattr(_JSON_KEYS))) if _JSON_KEYS in names else set()
        meta: dict[str, object] = {}
        for key in names:
            if key in _RESERVED:
                continue
            value = nc.getncattr(key)
            if key in json_keys:
                value = json.loads(value)
            elif isinstance(value, np.generic):
                value = value.item()
            elif isinstance(value, np.ndarray) and value.size == 1:
                value = value.item()
            meta[key] = value
        arrays: dict[str, np.ndarray] = {}
        for name, var in nc.variables.items():
            var.set_auto_maskandscale(False)
            arr = np.array(var[...]) if var.size else np.zeros(var.shape, dtype=var.dtype)
            if _BOOL_MARK in var.ncattrs():
                arr = arr.astype(bool)
            arrays[name] = arr
    return arrays, meta
