"""Old name of :mod:`warpnerf.ops.bridge`, kept for one release: the same module object, so
patches made through either name are seen by both."""

import sys

from warpnerf.ops import bridge

sys.modules[__name__] = bridge
