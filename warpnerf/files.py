"""Renamed :mod:`warpnerf.safe_writes` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.safe_writes`."""

from .safe_writes import *  # noqa: F403
from .safe_writes import __all__  # noqa: F401
