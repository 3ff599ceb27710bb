"""blendxr: how many revolutions until this blend is uniform?

The public face of the package (DESIGN §6). Everything a user or a test relies on is
named here; everything else is an implementation detail.
"""

from . import images
from ._version import __version__
from .ade.stepper import SCHEMES, BlowUpError, mix
from .flow import analytic as flows
from .flow.solver import FlowBlowUpError, solve_flow
from .io import open_flow, open_mixing, write_dataset
from .metrics import (
    lacey_index,
    random_mixture_intensity,
    rsd,
    segregation_intensity,
    thief_rsd,
    thief_samples,
)
from .pipeline import flow_key, revolutions_to_level, run_scene, scene_flow
from .scene import Scene, SceneError, builtin_scenes, load_scene
from .schema import SchemaError, validate
from .studies import calibrate_k1, read_curve
from .sweep import sweep

__all__ = [
    "__version__",
    "SCHEMES",
    "BlowUpError",
    "FlowBlowUpError",
    "Scene",
    "SceneError",
    "SchemaError",
    "builtin_scenes",
    "calibrate_k1",
    "flow_key",
    "flows",
    "images",
    "lacey_index",
    "load_scene",
    "mix",
    "open_flow",
    "open_mixing",
    "random_mixture_intensity",
    "read_curve",
    "revolutions_to_level",
    "rsd",
    "run_scene",
    "scene_flow",
    "segregation_intensity",
    "solve_flow",
    "sweep",
    "thief_rsd",
    "thief_samples",
    "validate",
    "write_dataset",
]
