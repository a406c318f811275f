"""Renamed :mod:`warpnerf.data.loading` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.data.loading`."""

from .loading import *  # noqa: F403
from .loading import __all__  # noqa: F401
