"""Renamed :mod:`warpnerf.box_demo` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.box_demo`."""

from .box_demo import *  # noqa: F403
from .box_demo import __all__  # noqa: F401
