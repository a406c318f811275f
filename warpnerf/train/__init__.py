"""Training loops: box fit, NeRF (coarse/fine) with evaluation and camera-path renders."""

# The built-in methods (train/methods.py's registry) register themselves in their own modules,
# as an added method does (docs/ARCHITECTURE.md), in this order; methods of outside packages come
# through the "warpnerf.methods" entry points.
from . import nerf_method  # noqa: F401, I001  (nerf: train nerf, train volsdf)
from . import sdf  # noqa: F401  (neural_sdf: train sdf)
from . import box_fit  # noqa: F401  (box: train box)
from .box_fit import BoxFitConfig, fit_box, render_box_views
from .nerf import NeRFConfig, load_run, train_nerf
from .nerf_eval import evaluate_run, render_run

__all__ = [
    "BoxFitConfig",
    "fit_box",
    "render_box_views",
    "NeRFConfig",
    "train_nerf",
    "load_run",
    "evaluate_run",
    "render_run",
]
