"""blendxr: how many revolutions until this blend is uniform?

The public face of the package. Everything a user or a test relies on is named here.
"""

from ._version import __version__

__all__ = ["__version__"]
