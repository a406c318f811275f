"""The settings of the tools that take a run folder (`eval`, `render`, `mesh`, `export`) as
configs declared with :func:`~warpnerf.options.option`: their flags, defaults and help come from
here as the `train` commands' come from the training configs (tests/test_options.py checks that
every flag's default is its field's and that the library functions these tools call have the
same defaults)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from ..options import option
from ..train.nerf_eval import RENDERERS
from ..train.nerf_run import MAX_SPP
from ..train.surface_level import LEVEL_BOUND, parse_level

__all__ = ["EvalConfig", "RenderConfig", "MeshConfig", "ExportConfig", "RUN_DEVICE"]

RUN_DEVICE = "cpu or cuda (default: the run's device)"
QUIET = "no progress on stderr (default: a bar on a terminal, else a line every 10 s)"
SPLITS = ("train", "val", "test")
RENDERED_HELP = (f"'rendered': the median SDF at the rendered depths of opaque training rays "
                 f"(a seeded subset of the training pixels; clamped to +-{LEVEL_BOUND:g} beta), "
                 "where the renders put the surface")  # fmt: skip
CLEAN_HELP = ("drop floating pieces: connected components with less than MIN_FRACTION of the "
              "surface area (MIN_FRACTION default 0.01; give it after RUN)")  # fmt: skip


def _level_arg(text: str):
    """--level's argparse type: a finite number or 'rendered' (train/surface_level.py)."""
    try:
        return parse_level(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


@dataclass
class EvalConfig:
    """`warpnerf eval RUN`: images of a split scored, or with ``geometry`` an SDF run's surface
    against a reference."""

    split: str = option("val", "the data split to score", choices=SPLITS)
    device: str | None = option(None, RUN_DEVICE)
    max_images: int = option(0, "0 = all images of the split", check="nonnegative")
    chunk: int | None = option(None, "rays rendered at once (default: the run's)",
                               check="positive")  # fmt: skip
    march_step: float | None = option(None, "grid runs: another marching step (default: the "
                                      "run's)", check="positive")  # fmt: skip
    round_samples: int | None = option(
        None, "grid runs: another sample-count rounding (0 = none; default: the run's)",
        check="nonnegative",
    )  # fmt: skip
    half: bool = option(False, "grid runs on CUDA: float16 MLPs")
    tracer: str | None = option(
        None, "grid runs: how frames march (traced: instant-ngp's tracer, rounds of a few "
        "samples per live ray, 2x slower on an H200 today; rounds: --round-samples; auto: "
        "rounds; default: the run's, auto)", choices=("auto", "traced", "rounds"),
    )  # fmt: skip
    renderer: str = option("volume", "SDF runs: sphere (trace the surface, colour at the hit; "
                           "default folder RUN/eval_SPLIT_sphere) or volume",
                           choices=RENDERERS)  # fmt: skip
    spp: int | None = option(None, f"rays a pixel, averaged (1 = the pixels' centres; k^2: a "
                             f"k x k grid in each pixel, else R2 points; at most {MAX_SPP}): the "
                             "box-filtered image an area-averaged dataset holds; each is one "
                             "more render (default: the run's --train-spp)",
                             check="positive")  # fmt: skip
    out: str | None = option(None, "output folder (default: RUN/eval_SPLIT)")
    geometry: str | None = option(None, "SDF runs: instead of images, the surface's accuracy, "
                                  "completeness and Chamfer distance against REF: 'materials' "
                                  "(its analytic shapes; also the rendered depth's error) or a "
                                  "point cloud (.npz / .ply)", metavar="REF")  # fmt: skip
    mesh_resolution: int = option(256, "with --geometry: marching-cubes nodes per axis")
    geometry_points: int = option(50000, "with --geometry: points sampled on each surface")
    geometry_views: int = option(10, "with --geometry materials: the rendered depth's error "
                                 "against the analytic hits on this many val images (0 = all)",
                                 check="nonnegative")  # fmt: skip
    clean: float | None = option(None, "with --geometry: also the figures after cleaning; "
                                 + CLEAN_HELP, check="finite", const=0.01,
                                 metavar="MIN_FRACTION")  # fmt: skip
    level: float | str = option(0.0, "with --geometry: the SDF level meshed, a number or "
                                + RENDERED_HELP, check=_level_arg)  # fmt: skip
    quiet: bool = option(False, QUIET)


@dataclass
class RenderConfig:
    """`warpnerf render RUN`: colour and depth videos along a camera path."""

    path: str = option("spiral", "spiral, orbit, or a camera-path JSON file saved by `warpnerf "
                       "view`")  # fmt: skip
    frames: int | None = option(None, "frames (default 40; a path file: its own frame count)",
                                check="positive")  # fmt: skip
    size: tuple | None = option(None, "WxH (default: the training size)", check="size")
    device: str | None = option(None, RUN_DEVICE)
    renderer: str = option("volume", "SDF runs: sphere-trace the surface (into "
                           "RUN/render_PATH_sphere) or volume", choices=RENDERERS)  # fmt: skip
    spp: int | None = option(None, f"rays a pixel, averaged (at most {MAX_SPP}; default: the "
                             "run's --train-spp)", check="positive")  # fmt: skip
    quiet: bool = option(False, QUIET)


@dataclass
class MeshConfig:
    """`warpnerf mesh [RUN]`: marching cubes of a run's surface or of an SDF scene."""

    sdf: str | None = option(None, "SDF scene: a JSON file, or 'torus' / 'scene' (built-in)")
    resolution: int = option(256, "grid nodes per axis")
    level: float | str | None = option(
        None, "SDFs: 0, another number, or " + RENDERED_HELP + "; density for NeRF runs: "
        "default from the run, the median density where lines through the grid reach opacity "
        "0.5 as rays (the depth it renders), at most the peak density nine in ten of those "
        "lines reach (no holes)", check=_level_arg,
    )  # fmt: skip
    bounds: float | None = option(None, "half-size of the cube", check="positive")
    out: str = option("", "mesh.ply (a PNG screenshot goes beside it)", required=True)
    device: str | None = option(None, "where to evaluate and march (default: the run's device; "
                                "cpu for --sdf)")  # fmt: skip
    colors: bool = option(False, "runs: bake the radiance field's colour into the vertices "
                          "(seen along the normal, looking at the surface)")  # fmt: skip
    clean: float | None = option(None, CLEAN_HELP + "; a run's mesh is cleaned at 0.01 unless "
                                 "--keep-all", check="finite", const=0.01,
                                 metavar="MIN_FRACTION")  # fmt: skip
    keep_all: bool = option(False, "runs: the raw level set; by default faces no training "
                            "camera sees are culled (the inside of objects, space under a floor) "
                            "and floating pieces dropped (--clean)")  # fmt: skip
    no_weight_cull: bool = option(False, "runs: keep the faces where no training ray puts "
                                  "weight; by default a face is kept only in the cells of a "
                                  "grid (at most 128^3, dilated by one) holding a sample of a "
                                  "training ray whose compositing weight is >= 0.005 (the "
                                  "camera culling and --clean still apply)")  # fmt: skip
    decimate: float | None = option(None, "quadric decimation removing about R of the faces, "
                                    "0 < R < 1 (after --clean, before --colors)",
                                    check="finite", metavar="R")  # fmt: skip
    no_screenshot: bool = option(False, "no PNG screenshot beside the .ply")
    quiet: bool = option(False, QUIET)


@dataclass
class ExportConfig:
    """`warpnerf export RUN pointcloud|cameras`."""

    out: str = option("", "pointcloud: a .ply; cameras: a .json", required=True)
    views: int = option(0, "pointcloud: training views used, spread evenly (0: all)",
                        check="nonnegative")  # fmt: skip
    stride: int = option(2, "pointcloud: every Nth pixel", check="positive")
    min_opacity: float = option(0.5, "pointcloud: rays kept", check="finite")
    device: str | None = option(None, "pointcloud: " + RUN_DEVICE)
    quiet: bool = option(False, QUIET)
