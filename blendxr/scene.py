"""Scenes: everything a run needs to know, as TOML in and validated dictionaries out.

A scene has the sections ``vessel``, ``operation``, ``material``, ``fill``, ``flow``,
``mixing`` and ``numerics`` (see ``data_schemas/scene.schema.json``, the single source
of truth for keys, ranges and defaults). Scenes travel in every output file's attributes
as TOML text, so any result can be re-run from its own file.
"""

from __future__ import annotations

import copy
import difflib
import json
import math
import tomllib
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import tomli_w

__all__ = [
    "Scene",
    "SceneError",
    "builtin_scenes",
    "check_values",
    "default_of",
    "fit_snapshots",
    "load_scene",
    "parse_assignment",
    "scene_keys",
]


class SceneError(ValueError):
    """A scene is not valid; the message names every faulty key and what is allowed."""

    def __init__(self, faults: list[str]):
        self.faults = list(faults)
        super().__init__("invalid scene: " + "; ".join(self.faults))


def _scene_schema() -> dict:
    text = resources.files("blendxr.data_schemas").joinpath("scene.schema.json").read_text()
    return json.loads(text)


def _describe(error: jsonschema.ValidationError) -> str:
    key = ".".join(str(p) for p in error.absolute_path) or "scene"
    schema = error.schema if isinstance(error.schema, dict) else {}
    bounds = []
    for word, sign in (
        ("minimum", ">="),
        ("exclusiveMinimum", ">"),
        ("maximum", "<="),
        ("exclusiveMaximum", "<"),
    ):
        if word in schema:
            bounds.append(f"{sign} {schema[word]}")
    if error.validator in {"minimum", "exclusiveMinimum", "maximum", "exclusiveMaximum"}:
        return f"{key} = {error.instance!r} is out of range; allowed: {' and '.join(bounds)}"
    if error.validator == "enum":
        return f"{key} = {error.instance!r} is not one of {schema['enum']}"
    if error.validator == "additionalProperties":
        return _unknown_keys(key, error)
    if error.validator == "oneOf":
        choices = " or ".join(_allowed(option) for option in schema["oneOf"])
        return f"{key} = {error.instance!r} is not allowed; allowed: {choices}"
    return f"{key}: {error.message}"


def _non_finite(value, key: str = "") -> list[str]:
    """'operation.rpm = nan is not a finite number' for every NaN or infinity inside."""
    if isinstance(value, float) and not math.isfinite(value):
        return [f"{key or 'scene'} = {value!r} is not a finite number"]
    if isinstance(value, dict):
        return [f for k, v in value.items() for f in _non_finite(v, f"{key}.{k}" if key else k)]
    if isinstance(value, list):
        return [f for i, v in enumerate(value) for f in _non_finite(v, f"{key}.{i}")]
    return []


def _allowed(schema: dict) -> str:
    """What one alternative of a ``oneOf`` admits, in words: "a number > 0", "'floor'"."""
    if "const" in schema:
        return repr(schema["const"])
    bounds = [
        f"{sign} {schema[word]}"
        for word, sign in (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="))
        if word in schema
    ]
    kind = {"number": "a number", "integer": "an integer", "string": "a string"}
    what = kind.get(schema.get("type"), str(schema.get("type", "a value")))
    return " ".join([what, " and ".join(bounds)]) if bounds else what


def _unknown_keys(section: str, error: jsonschema.ValidationError) -> str:
    """'vessel.hopper_angel_deg is not a scene key; did you mean vessel.hopper_angle_deg?'"""
    known = sorted(error.schema.get("properties", {}))
    unknown = sorted(set(error.instance) - set(known))
    prefix = "" if section == "scene" else f"{section}."
    parts = []
    for name in unknown:
        close = difflib.get_close_matches(name, known, n=1)
        hint = f"; did you mean {prefix}{close[0]}?" if close else f"; allowed: {', '.join(known)}"
        parts.append(f"{prefix}{name} is not a scene key{hint}")
    return "; ".join(parts)


def scene_keys() -> list[str]:
    """Every dotted key a scene may set (``"mixing.k1"``, ``"solver.cell"``, ...)."""
    keys = []
    for section, sub in _scene_schema()["properties"].items():
        props = sub.get("properties")
        if props is None:
            keys.append(section)
        else:
            keys.extend(f"{section}.{k}" for k in props)
    return keys


def parse_assignment(text: str) -> tuple[str, Any]:
    """``"mixing.k1=0.02"`` -> ``("mixing.k1", 0.02)``: the value is read as TOML.

    A value that is not valid TOML (``top-bottom``) is taken as a string, so quotes are
    needed only where TOML would read another type.
    """
    key, sep, value = text.partition("=")
    key, value = key.strip(), value.strip()
    if not sep or not key or not value:
        raise SceneError([f"--set {text!r}: give key=value, for example mixing.k1=0.02"])
    try:
        parsed = tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        parsed = value
    return key, parsed


def _key_schema(key: str) -> dict:
    """The schema of one dotted key (``"mixing.stop_rsd"``)."""
    section, _, name = key.partition(".")
    try:
        return _scene_schema()["properties"][section]["properties"][name]
    except KeyError:
        raise KeyError(f"{key} is not a scene key") from None


def check_values(values: Mapping[str, Any]) -> None:
    """Validate values given outside a scene (keyword arguments) against the scene schema.

    The schema stays the one home of ranges: a function that takes a scene value as a
    keyword checks it here instead of repeating the range.

    Parameters
    ----------
    values : mapping
        ``{"mixing.stop_rsd": 0.05}``; None values are skipped (absent).

    Raises
    ------
    SceneError
        Naming every key whose value is out of its range.
    """
    faults = []
    for key, value in values.items():
        if value is None:
            continue
        faults.extend(_non_finite(value, key))
        validator = jsonschema.Draft202012Validator(_key_schema(key))
        for error in validator.iter_errors(value):
            error.path.extendleft(reversed(key.split(".")))
            faults.append(_describe(error))
    if faults:
        raise SceneError(sorted(faults))


def default_of(key: str) -> Any:
    """The schema default of a dotted key (None where the schema gives none)."""
    return copy.deepcopy(_key_schema(key).get("default"))


def fit_snapshots(snapshots, revolutions) -> list | None:
    """The snapshot revolutions that fit a run of ``revolutions``, and its end.

    A scene's snapshots are planned for its own length; a run made shorter keeps those
    that fit and ends with a snapshot of its last state.
    """
    if not snapshots or not isinstance(revolutions, int | float):
        return None if not snapshots else list(snapshots)
    kept = {r for r in snapshots if isinstance(r, int | float) and r <= revolutions}
    return sorted(kept | {revolutions})


def _set_dotted(data: dict, values: Mapping[str, Any]) -> dict:
    """A copy of ``data`` with dotted keys set; unknown keys refused with a did-you-mean."""
    out = copy.deepcopy(data)
    schema = _scene_schema()["properties"]
    known = scene_keys()
    faults = []
    for key, value in values.items():
        parts = key.split(".")
        head = parts[0]
        props = schema.get(head, {}).get("properties")
        free = head in schema and (props is None or (len(parts) > 2 and parts[1] == "parameters"))
        if key not in known and not free:
            close = difflib.get_close_matches(key, known, n=1)
            hint = f"did you mean {close[0]}?" if close else "see `blendxr scene NAME`"
            faults.append(f"{key} is not a scene key; {hint}")
            continue
        target = out
        for part in parts[:-1]:
            target = target.setdefault(part, {})
            if not isinstance(target, dict):
                faults.append(f"{key}: {part} is not a section")
                break
        else:
            target[parts[-1]] = value
    if faults:
        raise SceneError(faults)
    return out


def _apply_defaults(data: dict, schema: dict) -> dict:
    """Fill every missing key that has a schema default, section by section."""
    out = copy.deepcopy(data)
    for section, sub in schema.get("properties", {}).items():
        props = sub.get("properties")
        if props is None:
            continue
        target = out.setdefault(section, {})
        for key, spec in props.items():
            if "default" in spec and key not in target:
                target[key] = copy.deepcopy(spec["default"])
    return out


class Scene(Mapping):
    """A validated scene.

    Behaves as a read-only mapping of sections (``scene["mixing"]["k1"]``). Missing keys
    carry the schema's defaults. ``to_toml()`` gives the text stored in output files.

    Parameters
    ----------
    data : mapping
        The scene as nested dictionaries (for example parsed TOML).
    """

    def __init__(self, data: Mapping[str, Any]):
        schema = _scene_schema()
        raw = json.loads(json.dumps(dict(data)))  # plain, JSON-like copy
        validator = jsonschema.Draft202012Validator(schema)
        # NaN compares false with every bound, so the schema's ranges cannot catch it
        faults = sorted([*_non_finite(raw), *(_describe(e) for e in validator.iter_errors(raw))])
        if faults:
            raise SceneError(faults)
        self._raw = raw  # as given: overrides are applied to it, then defaults again
        self._data = _apply_defaults(raw, schema)
        self._check_relations()

    def _check_relations(self) -> None:
        faults = []
        mixing = self._data["mixing"]
        for r in mixing.get("snapshots", []):
            if r > mixing["revolutions"]:
                faults.append(
                    f"mixing.snapshots: {r} is beyond mixing.revolutions = {mixing['revolutions']}"
                )
        flow = self._data.get("flow", {})
        if flow.get("source") == "analytic" and "analytic" not in flow:
            faults.append("flow.analytic: required when flow.source = 'analytic'")
        if flow.get("source") == "file" and "path" not in flow:
            faults.append("flow.path: required when flow.source = 'file'")
        if faults:
            raise SceneError(faults)

    # Mapping interface
    def __getitem__(self, key: str) -> Any:
        return self._data[key]

    def __iter__(self):
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    @property
    def name(self) -> str:
        """The scene's name."""
        return self._data["name"]

    def given(self, key: str) -> Any:
        """The value a dotted key (``"flow.cell"``) or section (``"solver"``) was given,
        before defaults: None where the scene left it to its default."""
        value: Any = self._raw
        for part in key.split("."):
            if not isinstance(value, dict) or part not in value:
                return None
            value = value[part]
        return copy.deepcopy(value)

    def to_dict(self) -> dict:
        """A deep copy of the scene as plain dictionaries (defaults filled in)."""
        return copy.deepcopy(self._data)

    def to_toml(self) -> str:
        """The scene as TOML text (the form stored in output files)."""
        return tomli_w.dumps(self._data)

    def replace(self, **sections: Mapping[str, Any]) -> Scene:
        """A new scene with the given sections updated key by key.

        Examples
        --------
        >>> scene.replace(mixing={"k1": 0.02})  # doctest: +SKIP
        """
        data = self.to_dict()
        for section, values in sections.items():
            if isinstance(values, Mapping):
                data.setdefault(section, {}).update(values)
            else:
                data[section] = values
        return Scene(data)

    def with_values(self, values: Mapping[str, Any] | None = None, **dotted: Any) -> Scene:
        """A new scene with values set by dotted key, validated as a whole.

        Parameters
        ----------
        values : mapping, optional
            ``{"mixing.k1": 0.02, "flow.cell": 0.01}``.
        **dotted
            The same as keywords: ``scene.with_values(**{"mixing.k1": 0.02})``.

        Raises
        ------
        SceneError
            An unknown key (with the nearest known one) or a value out of its range.
        """
        merged = {**(values or {}), **dotted}
        if not merged:
            return self
        raw = _set_dotted(self._raw, merged)
        mixing = raw.get("mixing", {})
        if "mixing.revolutions" in merged and "mixing.snapshots" not in merged:
            fitted = fit_snapshots(mixing.get("snapshots"), mixing["revolutions"])
            if fitted is not None:
                mixing["snapshots"] = fitted
        return Scene(raw)

    def __repr__(self) -> str:
        return f"Scene({self.name!r})"


def builtin_scenes() -> list[str]:
    """Names of the scenes that ship with blendxr."""
    folder = resources.files("blendxr.scenes")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scene(scene: str | Path | Mapping | Scene, values=None, **dotted: Any) -> Scene:
    """Load a scene by built-in name, from a TOML file, or from a mapping.

    Parameters
    ----------
    scene : str, path, mapping or Scene
        A built-in name (see :func:`builtin_scenes`), a path to a ``.toml`` file, TOML text
        taken from a dataset's ``scene`` attribute, or nested dictionaries.
    values : mapping, optional
        Values to set by dotted key (``{"mixing.k1": 0.02}``), as ``--set`` does.
    **dotted
        The same as keywords: ``load_scene("tote-small", **{"mixing.k1": 0.02})``.

    Returns
    -------
    Scene

    Raises
    ------
    SceneError
        If the scene is invalid or cannot be found; the message names the key.
    """
    if isinstance(scene, Scene):
        return scene.with_values(values, **dotted)
    if isinstance(scene, Mapping):
        return Scene(scene).with_values(values, **dotted)
    text = None
    if isinstance(scene, str) and "\n" in scene:
        text = scene
    else:
        path = Path(scene)
        builtin = resources.files("blendxr.scenes").joinpath(f"{scene}.toml")
        if path.suffix == ".toml" and path.is_file():
            text = path.read_text()
        elif builtin.is_file():
            text = builtin.read_text()
        else:
            raise SceneError(
                [
                    f"scene {str(scene)!r}: no such file or built-in scene; built-in: "
                    f"{', '.join(builtin_scenes())}"
                ]
            )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise SceneError([f"scene TOML: {err}"]) from None
    return Scene(data).with_values(values, **dotted)
