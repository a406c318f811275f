"""Renamed :mod:`warpnerf.sphere_tracing` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.sphere_tracing`."""

from .sphere_tracing import *  # noqa: F403
from .sphere_tracing import __all__  # noqa: F401
