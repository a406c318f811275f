"""Renamed :mod:`warpnerf.json_input` (issue 46): this alias of the old import path goes in the
next release; import from :mod:`warpnerf.json_input`."""

from .json_input import *  # noqa: F403
from .json_input import __all__  # noqa: F401
