"""The advection schemes of the mixing model, one module each behind :class:`Scheme`.

``SCHEMES`` maps the name a scene gives (``numerics.scheme``) to the class; the driver
makes the scheme through :func:`make` and never asks which one it has.
"""

from __future__ import annotations

from .base import BOUND_TOLERANCE, Scheme
from .finite_volume import FiniteVolume
from .lax_wendroff import LaxWendroff
from .semi_lagrangian import SemiLagrangian

__all__ = ["BOUND_TOLERANCE", "SCHEMES", "Scheme", "make"]

SCHEMES: dict[str, type[Scheme]] = {
    cls.name: cls for cls in (FiniteVolume, LaxWendroff, SemiLagrangian)
}


def make(name: str, grid, vessel, with_diffusion: bool) -> Scheme:
    """The scheme called ``name`` on ``grid``; ValueError naming the schemes if unknown."""
    try:
        cls = SCHEMES[name]
    except KeyError:
        raise ValueError(f"unknown scheme {name!r}; allowed: {', '.join(SCHEMES)}") from None
    return cls(grid, vessel, with_diffusion)
