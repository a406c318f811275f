"""Renamed :mod:`warpnerf.outputs` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.outputs`."""

from .outputs import *  # noqa: F403
from .outputs import __all__  # noqa: F401
