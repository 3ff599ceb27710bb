"""Shared fixtures: small canned flow and mixing datasets with full metadata.

Every dataset here is schema-valid and small enough that a test using it runs in
milliseconds. Fixtures return fresh objects, so a test may modify what it gets.
"""

from __future__ import annotations

import numpy as np
import pytest

from blendxr.flow import analytic
from blendxr.schema import mixing_dataset

#: A small scene as TOML text, carried by the canned mixing datasets.
SCENE_TOML = """\
name = "canned-drum"

[vessel]
kind = "drum"
ndim = 2
diameter = 0.15
width = 0.05

[operation]
rpm = 3.26
"""

#: Recipes for the canned flows: (id, analytic function, keyword arguments).
FLOW_RECIPES = [
    ("uniform-2d", analytic.uniform, {"velocity": (0.3, -0.1), "cells": (6, 5)}),
    ("uniform-3d", analytic.uniform, {"velocity": (0.1, 0.2, 0.3), "cells": 4, "n_phases": 2}),
    ("swirl-2d", analytic.swirl, {"ndim": 2, "cells": 8, "n_phases": 4}),
    ("swirl-3d", analytic.swirl, {"ndim": 3, "cells": (4, 5, 6), "n_phases": 4}),
    ("rotation-2d-full", analytic.solid_body_rotation, {"ndim": 2, "cells": 8}),
    (
        "rotation-3d-bed",
        analytic.solid_body_rotation,
        {"ndim": 3, "cells": 6, "fill_fraction": 0.4, "n_phases": 4},
    ),
]


@pytest.fixture(autouse=True, scope="session")
def _private_flow_cache(tmp_path_factory):
    """Tests cache their solved flows in a folder of their own, never the user's."""
    import os

    folder = tmp_path_factory.mktemp("flow-cache")
    before = os.environ.get("BLENDXR_CACHE")
    os.environ["BLENDXR_CACHE"] = str(folder)
    yield folder
    if before is None:
        os.environ.pop("BLENDXR_CACHE", None)
    else:
        os.environ["BLENDXR_CACHE"] = before


def make_flow(recipe_id: str):
    """Build one of the canned flows by its id in `FLOW_RECIPES`."""
    for name, function, kwargs in FLOW_RECIPES:
        if name == recipe_id:
            return function(**kwargs)
    raise KeyError(recipe_id)


def make_mixing(ndim: int = 2, *, n_time: int = 5, n_snapshots: int = 2, scene=SCENE_TOML):
    """A canned mixing dataset: a half-full circular section, top-bottom loading decaying.

    ``c`` is NaN outside the material, as the contract asks.
    """
    rng = np.random.default_rng(7)
    x = np.linspace(-0.045, 0.045, 7)
    y = np.linspace(-0.05, 0.05, 6)
    z = np.linspace(-0.02, 0.02, 3) if ndim == 3 else None
    grid = np.meshgrid(x, y, *([z] if ndim == 3 else []), indexing="ij")
    material = (np.hypot(grid[0], grid[1]) < 0.05) & (grid[1] < 0.01)
    period = 60.0 / 3.26
    time = np.linspace(0.0, 2.0 * period, n_time)
    decay = np.exp(-time / period)
    snap_rev = np.linspace(0.0, 2.0, n_snapshots)
    c = np.empty((n_snapshots,) + material.shape)
    for k, r in enumerate(snap_rev):
        mixed = 0.5 + (np.where(grid[1] < -0.02, 0.5, -0.5)) * np.exp(-r)
        c[k] = np.where(
            material, np.clip(mixed + 0.01 * rng.standard_normal(mixed.shape), 0, 1), np.nan
        )
    return mixing_dataset(
        x,
        y,
        z=z,
        time=time,
        revolution=time / period,
        rsd=0.9 * decay,
        intensity=decay**2,
        mass_a=np.full(n_time, 1.2e-4),
        snapshot_time=snap_rev * period,
        snapshot_revolution=snap_rev,
        c=c,
        scene=scene,
        attrs={"scheme": "finite-volume", "k1": 0.01, "k2": 0.019, "d": 0.001},
    )


@pytest.fixture(name="make_flow")
def make_flow_fixture():
    """Factory: ``make_flow(recipe_id)`` builds a canned flow (ids in `FLOW_RECIPES`)."""
    return make_flow


@pytest.fixture(name="make_mixing")
def make_mixing_fixture():
    """Factory: ``make_mixing(ndim, n_time=5, n_snapshots=2, scene=...)``."""
    return make_mixing


@pytest.fixture
def scene_toml() -> str:
    """The canned scene as TOML text."""
    return SCENE_TOML


@pytest.fixture
def flow_2d():
    """2-D periodic flow (LeVeque swirl, 8 x 8 cells, 4 phases)."""
    return make_flow("swirl-2d")


@pytest.fixture
def flow_3d():
    """3-D cylinder with a rotating bed (40 % fill, 4 phases), frame "lab"."""
    return make_flow("rotation-3d-bed")


@pytest.fixture(params=[recipe[0] for recipe in FLOW_RECIPES])
def any_flow(request):
    """Each canned flow in turn, 2-D and 3-D, steady and periodic."""
    return make_flow(request.param)


@pytest.fixture
def mixing_2d():
    """2-D mixing dataset: 5 curve times, 2 snapshots, NaN outside the material."""
    return make_mixing(2)


@pytest.fixture
def mixing_3d():
    """3-D mixing dataset: 5 curve times, 2 snapshots, NaN outside the material."""
    return make_mixing(3)


@pytest.fixture(params=[2, 3], ids=["2d", "3d"])
def any_mixing(request):
    """The canned mixing datasets, 2-D and 3-D."""
    return make_mixing(request.param)
