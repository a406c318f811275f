"""Training loops (box fit now; NeRF, neural SDF and VolSDF trainers follow)."""

from .box_fit import BoxFitConfig, fit_box, psnr, render_box_views

__all__ = ["BoxFitConfig", "fit_box", "render_box_views", "psnr"]
