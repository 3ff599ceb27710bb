"""Scenes: everything a run needs to know, as TOML in and validated dictionaries out.

A scene has the sections ``vessel``, ``operation``, ``material``, ``fill``, ``flow``,
``mixing`` and ``numerics`` (see ``data_schemas/scene.schema.json``, the single source
of truth for keys, ranges and defaults). Scenes travel in every output file's attributes
as TOML text, so any result can be re-run from its own file.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import jsonschema
import tomli_w
import tomllib

__all__ = ["Scene", "SceneError", "load_scene", "builtin_scenes"]


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
        return f"{key}: {error.message}"
    return f"{key}: {error.message}"


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
        faults = sorted(
            (_describe(e) for e in validator.iter_errors(raw)),
        )
        if faults:
            raise SceneError(faults)
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

    def __repr__(self) -> str:
        return f"Scene({self.name!r})"


def builtin_scenes() -> list[str]:
    """Names of the scenes that ship with blendxr."""
    folder = resources.files("blendxr.scenes")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def load_scene(scene: str | Path | Mapping | Scene) -> Scene:
    """Load a scene by built-in name, from a TOML file, or from a mapping.

    Parameters
    ----------
    scene : str, path, mapping or Scene
        A built-in name (see :func:`builtin_scenes`), a path to a ``.toml`` file, TOML text
        taken from a dataset's ``scene`` attribute, or nested dictionaries.

    Returns
    -------
    Scene

    Raises
    ------
    SceneError
        If the scene is invalid or cannot be found; the message names the key.
    """
    if isinstance(scene, Scene):
        return scene
    if isinstance(scene, Mapping):
        return Scene(scene)
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
    return Scene(data)
