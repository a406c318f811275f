"""The web viewer (``warpnerf view RUN``, ``warpnerf train ... --viewer``): a viser page whose
background is the run rendered by the project's renderer from the browser's camera."""

from .live import LiveViewer
from .scene import RunScene, load_scene
from .server import Viewer

__all__ = ["Viewer", "RunScene", "load_scene", "LiveViewer"]
