"""Training loops: box fit, NeRF (coarse/fine) with evaluation and camera-path renders."""

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
