"""The sections of NeRF's run settings (:class:`~warpnerf.train.nerf_config.NeRFConfig` is made
of them): the data and its scene transform, sampling, capture-only settings and validation, each
a small dataclass whose fields carry their flags, help and checks."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..data.cameras import MAX_CENTRE, MAX_DEPTH, MIN_EXTENT, scene_bounds_problem
from ..data.dataset import capture_formats, carries_scene
from ..data.loading import FORMATS
from ..options import check_at_least, option

__all__ = [
    "DataConfig",
    "SceneConfig",
    "SamplingConfig",
    "ProposalConfig",
    "CaptureConfig",
    "ValidationConfig",
    "GRID",
    "MAX_DEPTH_RAYS",
    "MAX_BUILTIN_SIZE",
]


GRID = ("grid",)  # flag group: `train nerf` only (VOLSDF: `train volsdf` only)


MAX_DEPTH_RAYS = 1 << 20  # --depth-rays: observation rays a step, at most
DISTORTION_SPACES = ("scene", "mipnerf360")  # --distortion-space: the loss's ray coordinate


# --builtin-size at most: the built-in scene renders its 64 training views in one call, and the
# kernels index rays with int32 (64 x 4096^2 = 2^30 rays)
MAX_BUILTIN_SIZE = 4096


@dataclass
class DataConfig:
    """Where the images come from and how they are read."""

    TITLE = "data"

    data: str = option(
        "builtin", "Blender, nerfstudio, COLMAP or LLFF folder, or 'builtin' (the built-in scene)"
    )
    data_format: str = option(
        "auto", "data format (auto: detect)", flag="--format", choices=FORMATS
    )
    holdout: int = option(
        8, "COLMAP/LLFF: every Nth image (sorted names) is val/test; 0 = none",
        check="nonnegative",
    )  # fmt: skip
    ndc: str = option(
        "auto", "COLMAP/LLFF: NDC rays (auto: on for forward-facing captures)",
        choices=("auto", "on", "off"),
    )  # fmt: skip
    # COLMAP/LLFF, resolved at the start: format, transform (world -> normalised [4][4]), ndc
    # camera (fx, fy, W, H) or None, near, far, aabb
    scene: dict | None = option(None, flag=None)
    downscale: int = option(1, "image downscale factor", check="positive")
    max_images: int = option(0, "training images used (0 = all)", check="nonnegative")
    allow_outside_paths: bool = option(
        False, "let the dataset's files name images outside its folder (absolute paths, '..', "
        "symlinks out of it); refused by default",
    )  # fmt: skip
    images_on: str = option(
        "auto", "where the training images live on a GPU run: device (gathered on the GPU), "
        "host (host memory; each batch's pixels gathered there into pinned memory and copied: "
        "GPU memory independent of the number of images) or auto (device while they take at most a "
        "quarter of the free GPU memory)",
    )  # fmt: skip
    builtin_size: int = option(48, "image size of the built-in scene", check="positive")

    def check_section(self, fail) -> None:
        check_at_least(self, fail, 1, "downscale", "builtin_size")
        if self.builtin_size > MAX_BUILTIN_SIZE:
            raise fail("builtin_size", f"must be in [1, {MAX_BUILTIN_SIZE}] (the built-in scene's "
                       f"rays index in int32), got {self.builtin_size}")  # fmt: skip
        if self.holdout < 0 or self.holdout == 1:
            raise fail("holdout", f"must be 0 (none) or >= 2, got {self.holdout}")
        check_at_least(self, fail, 0, "max_images")
        for name, allowed in (("ndc", ("auto", "on", "off")), ("data_format", FORMATS),
                              ("images_on", ("auto", "device", "host"))):  # fmt: skip
            if (v := getattr(self, name)) not in allowed:
                raise fail(name, f"must be one of {', '.join(allowed)}, got {v!r}")
        if self.scene is not None:
            _check_scene(self.scene, lambda rule: fail("scene", rule))


@dataclass
class SceneConfig:
    """The part of space a run models: near/far, the scene box, contraction, the background."""

    TITLE = "scene bounds"

    aabb: float = option(
        0.0, "hash/volsdf field: half-size of the scene cube (0: 1.5 for datasets, larger "
        "where an RGBA Blender-format split's opaque pixels show something past it; the "
        "built-in scene's own for builtin; with --contract on: of the inner cube, default the "
        "camera centres' extent)", check="nonnegative",
    )  # fmt: skip
    contract: str = option(
        "auto", "unbounded scene (hash field with a grid): space beyond the inner cube (--aabb) "
        "is contracted into a shell around it (mip-NeRF 360), the grid lives in contracted "
        "space, marching steps grow with distance and training composites onto random "
        "backgrounds (auto: on for COLMAP/LLFF captures that are not forward-facing)",
        choices=("auto", "on", "off"),
    )  # fmt: skip
    near: float | None = option(None, "default 2 (the built-in scene's own for builtin)",
                                check="finite")  # fmt: skip
    far: float | None = option(None, "default 6 (the built-in scene's own for builtin)",
                               check="finite")  # fmt: skip
    background: float = option(1.0, flag=None)  # white, as the NeRF-synthetic evaluation

    def check_section(self, fail) -> None:
        if self.contract not in ("auto", "on", "off"):
            raise fail("contract", f"must be one of auto, on, off, got {self.contract!r}")
        if not (math.isfinite(self.background) and 0 <= self.background <= 1):
            raise fail("background", f"must be in [0, 1], got {self.background}")
        # distances the kernels take in float32 (data/cameras.py: MAX_DEPTH, MIN_EXTENT)
        if not (self.aabb == 0 or MIN_EXTENT <= self.aabb <= MAX_CENTRE):
            raise fail("aabb", f"must be 0 (automatic) or in [{MIN_EXTENT:g}, {MAX_CENTRE:g}], "
                       f"got {self.aabb}")  # fmt: skip
        for name in ("near", "far"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and (v > 0 or (name == "near" and v == 0))):
                rule = ">= 0" if name == "near" else "positive"
                raise fail(name, f"must be finite and {rule}, got {v}")
            if v is not None and v > MAX_DEPTH:
                raise fail(name, f"must be at most {MAX_DEPTH:g} (a distance in float32), got {v}")
        if self.near is not None and self.far is not None and not self.far > self.near:
            raise fail("near", f"must be below far: need 0 <= near < far, got near={self.near}, "
                       f"far={self.far}")  # fmt: skip


@dataclass
class SamplingConfig:
    """Where along a ray the field is evaluated: stratified (and fine) samples, or marching the
    occupancy grid; early termination."""

    TITLE = "sampling and the occupancy grid"

    n_coarse: int = option(64, "coarse samples per ray", flag="--samples", check="positive")
    n_fine: int = option(0, flag=None)  # > 0: the fine network (--coarse-fine --fine-samples N)
    t_threshold: float = option(
        1e-4, "early ray termination below this transmittance (0: off)", check="finite"
    )
    grid_res: int | None = option(
        None, "occupancy grid cells per axis, even (default 128 with --field hash; 0: no grid, "
        "stratified/hierarchical samples instead)", check="nonnegative", groups=GRID,
    )  # fmt: skip
    grid_every: int = option(16, "steps between grid updates", check="positive", groups=GRID)
    grid_warmup: int = option(
        256, "steps during which every update evaluates all cells", check="nonnegative",
        groups=GRID,
    )  # fmt: skip
    occ_threshold: float = option(
        0.01, "a cell is empty when one step through it has opacity below this",
        check="positive", groups=GRID,
    )  # fmt: skip
    march_step: float = option(
        0.0, "marching step with a grid (0: the box diagonal / 1024)", check="nonnegative",
        groups=GRID,
    )  # fmt: skip
    max_samples: int = option(1024, "samples per ray at most, with a grid", check="positive",
                              groups=GRID)  # fmt: skip
    round_samples: int = option(
        0, "with a grid, renders march in rounds of this many samples per live ray (0: one "
        "round)", check="nonnegative", groups=GRID,
    )  # fmt: skip
    render_half: bool = option(False, flag=None)  # grid on CUDA: rendering MLPs in float16
    # grid: how renders march without gradients (render_marched's tracer: auto, traced, rounds)
    render_tracer: str = option("auto", flag=None)
    target_samples: int = option(
        0, "with a grid: adapt rays per step to composite about this many samples (0: fixed "
        "--batch)", check="nonnegative", groups=GRID,
    )  # fmt: skip
    cuda_graph: str = option(
        "auto", "with a grid on CUDA: run each training step with static shapes, captured once "
        "in a CUDA graph and replayed (auto: when the run allows it; off: the eager step, "
        "for debugging; on: refuse a run that does not allow it)",
        choices=("auto", "on", "off"), groups=GRID,
    )  # fmt: skip
    march_cone: float = option(
        0.0, "with --contract on: marching steps grow as this x the distance, beyond "
        "march-step / cone (0: 1/256)", check="nonnegative", groups=GRID,
    )  # fmt: skip

    def check_section(self, fail) -> None:
        check_at_least(self, fail, 1, "n_coarse")
        check_at_least(self, fail, 0, "n_fine")
        if not 0.0 <= self.t_threshold < 1.0:
            raise fail("t_threshold", f"must be in [0, 1), got {self.t_threshold}")
        if not (math.isfinite(self.march_cone) and 0 <= self.march_cone <= 1):
            raise fail("march_cone", f"must be in [0, 1], got {self.march_cone}")
        if self.render_tracer not in ("auto", "traced", "rounds"):
            raise fail("render_tracer", f"must be auto, traced or rounds, got "
                       f"{self.render_tracer!r}")  # fmt: skip
        if self.cuda_graph not in ("auto", "on", "off"):
            raise fail("cuda_graph", f"must be one of auto, on, off, got {self.cuda_graph!r}")
        if not self.grid_res:
            return
        if self.grid_res < 2 or self.grid_res % 2 or self.grid_res > 1024:
            raise fail("grid_res", f"must be even, in [2, 1024], got {self.grid_res}")
        check_at_least(self, fail, 1, "grid_every", "max_samples")
        if not 0 < self.occ_threshold < 1:
            raise fail("occ_threshold", f"must be in (0, 1), got {self.occ_threshold}")
        if not (math.isfinite(self.march_step) and 0 <= self.march_step <= MAX_DEPTH):
            raise fail("march_step", f"must be in [0, {MAX_DEPTH:g}], got {self.march_step}")
        check_at_least(self, fail, 0, "grid_warmup", "target_samples", "round_samples")


@dataclass
class ProposalConfig:
    """nerfacto's proposal sampling, side by side with the occupancy grid (issue 48)."""

    TITLE = "proposal sampling (contracted scenes)"

    sampler: str = option(
        "grid", "how a contracted scene (--contract on, --field hash) places samples: grid "
        "(march the occupancy grid) or proposal (nerfacto: small hash-grid density networks "
        "resample each ray, --proposal-samples per level, into --proposal-final samples of the "
        "field, trained by the interlevel loss; fixed samples per ray, so --batch rays a step "
        "whatever --target-samples says)",
        choices=("grid", "proposal"), groups=GRID,
    )  # fmt: skip
    proposal_samples: str = option(
        "256,96", "with --sampler proposal: samples per ray of each proposal level, one "
        "network per level (nerfacto's)", groups=GRID,
    )  # fmt: skip
    proposal_final: int = option(
        48, "with --sampler proposal: the field's samples per ray", check="positive", groups=GRID
    )
    interlevel_loss: float = option(
        1.0, "with --sampler proposal: weight of mip-NeRF 360's interlevel loss (each proposal "
        "histogram bounding the field's weights from above; the mean over rays and the field's "
        "samples, nerfacto's weight)", check="nonnegative", groups=GRID,
    )  # fmt: skip
    proposal_anneal: int = option(
        1000, "with --sampler proposal: steps over which the exponent of the proposal weights "
        "rises from 0 to 1 (nerfacto's anneal, slope 10; 0: none)", check="nonnegative",
        groups=GRID,
    )  # fmt: skip

    def check_section(self, fail) -> None:
        from ..fields.proposal import MAX_SAMPLES, parse_levels

        if self.sampler not in ("grid", "proposal"):
            raise fail("sampler", f"must be grid or proposal, got {self.sampler!r}")
        try:
            parse_levels(self.proposal_samples)
        except ValueError as e:
            raise fail("proposal_samples", str(e)) from None
        if not 1 <= self.proposal_final <= MAX_SAMPLES:
            raise fail("proposal_final", f"must be in [1, {MAX_SAMPLES}], got "
                       f"{self.proposal_final}")  # fmt: skip
        if not (math.isfinite(self.interlevel_loss) and self.interlevel_loss >= 0):
            raise fail("interlevel_loss", f"must be finite and >= 0, got {self.interlevel_loss}")
        if not 0 <= self.proposal_anneal <= 10**9:
            raise fail("proposal_anneal", f"must be in [0, 10^9], got {self.proposal_anneal}")
        if self.sampler != "proposal":
            return
        traits = getattr(self, "traits", None)
        field = getattr(self, "field", "?")
        if traits is None or traits.geometry != "density" or not traits.captures:
            raise fail("sampler", f"proposal needs a NeRF field with the capture features "
                       f"(--field hash), not --field {field}")  # fmt: skip
        contract = getattr(self, "contract", "auto")
        if contract == "off" or getattr(self, "grid_res", None) == 0:
            raise fail("sampler", "proposal is for contracted scenes (--contract on; a "
                       "COLMAP/LLFF capture that is not forward-facing has it by default; "
                       f"--grid-res > 0), not --contract {contract} --grid-res "
                       f"{getattr(self, 'grid_res', None)}")  # fmt: skip
        # (--target-samples, which --preset gpu sets, is left unused: the batch stays --batch)
        if getattr(self, "view_cull", False):
            raise fail("view_cull", "culls the occupancy grid's cells; --sampler proposal has "
                       "no grid")  # fmt: skip


@dataclass
class CaptureConfig:
    """What photos need beyond renders: appearance codes, pose refinement, the distortion loss
    and the depth prior."""

    TITLE = "captures (appearance codes, pose refinement, extra losses)"

    appearance_dim: int | None = option(
        None, "hash field with a grid: a learned appearance code of this size per training "
        "image, fed to the colour MLP (exposure / white balance changing between photos); "
        "held-out views use the codes' mean; 0: none (default 16 on a COLMAP/LLFF capture: "
        "measured +0.5 dB on beer, docs/design/data.md; else 0)", check="nonnegative",
    )  # fmt: skip
    appearance_images: int = option(0, flag=None)  # codes: the training split's size, when set
    pose_refine: bool = option(
        False, "learn a small rotation and translation correction per training camera (poses "
        "that are slightly off, e.g. COLMAP's); held-out cameras keep their given poses",
    )  # fmt: skip
    pose_lr: float = option(1e-3, "with --pose-refine: the corrections' learning rate (it "
                            "decays with --lr's schedule)", check="positive")  # fmt: skip
    pose_images: int = option(0, flag=None)  # pose refinement: the training split's size
    distortion_loss: float = option(
        0.0, "hash field with a grid: weight of mip-NeRF 360's distortion loss on each training "
        "ray's compositing weights, which pulls a ray's weight into one short stretch (fewer "
        "floaters in real captures; ray positions are normalised to s = t / (t + a) in "
        "contracted scenes, a the inner half-size, else to (t - near) / (far - near); see "
        "--distortion-space); 0: off", check="nonnegative",
    )  # fmt: skip
    distortion_space: str = option(
        "scene", "with --distortion-loss: the ray coordinate the loss measures in: scene (as "
        "above) or mipnerf360 (mip-NeRF 360's s = (1/near - 1/t) / (1/near - 1/far): t from "
        "near to 2 near spans half of [0, 1], distant space is packed near 1; on beer the "
        "stretch in front of the nearest surfaces spans about 4 times more s than in scene's)",
        choices=DISTORTION_SPACES,
    )  # fmt: skip
    near_loss: float = option(
        0.0, "hash field with a grid or --sampler proposal, world-space rays (not NDC): "
        "weight of a penalty on each training ray's compositing weight at samples nearer "
        "than --near-loss-frac x its camera's distance to the scene centre (the rays' mean; "
        "against fog in front of the cameras); 0: off", check="nonnegative",
    )  # fmt: skip
    near_loss_frac: float = option(
        0.6, "with --near-loss: the penalised stretch of each ray, a fraction of its camera's "
        "distance to the scene centre (the normalised scene's origin; beer's near plane lies "
        "at 0.5 of it, all but 0.03 percent of the COLMAP points it sees beyond 0.75)",
        check="positive",
    )  # fmt: skip
    depth_loss: float = option(
        0.0, "COLMAP captures with sparse points (world-space rays, not NDC): weight of a depth "
        "prior at the points, a Huber loss (delta 0.1) on each observation ray's rendered depth "
        "relative to the point's distance along it, over --depth-rays observations drawn per "
        "step from the training images (geometry where the photos alone leave it open, e.g. an "
        "untextured floor); 0: off", check="nonnegative",
    )  # fmt: skip
    depth_rays: int = option(
        256, "with --depth-loss: observation rays rendered per step", check="positive"
    )

    def check_section(self, fail) -> None:
        if self.appearance_dim is not None and self.appearance_dim > 256:
            raise fail("appearance_dim", f"must be at most 256, got {self.appearance_dim}")
        for name in ("distortion_loss", "depth_loss", "near_loss"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise fail(name, f"must be finite and >= 0, got {v}")
        if self.distortion_space not in DISTORTION_SPACES:
            raise fail("distortion_space", f"must be one of {', '.join(DISTORTION_SPACES)}, "
                       f"got {self.distortion_space!r}")  # fmt: skip
        if not (math.isfinite(self.near_loss_frac) and 0 < self.near_loss_frac <= 1):
            raise fail("near_loss_frac", f"must be in (0, 1], got {self.near_loss_frac}")
        if not 1 <= self.depth_rays <= MAX_DEPTH_RAYS:
            raise fail("depth_rays", f"must be in [1, {MAX_DEPTH_RAYS}], got {self.depth_rays}")
        for name in ("appearance_images", "pose_images"):
            if not 0 <= getattr(self, name) <= 10**6:
                raise fail(name, f"must be in [0, 10^6], got {getattr(self, name)}")
        if not (math.isfinite(self.pose_lr) and self.pose_lr > 0):
            raise fail("pose_lr", f"must be finite and positive, got {self.pose_lr}")


@dataclass
class ValidationConfig:
    """What a run scores and keeps while it trains."""

    TITLE = "validation and snapshots"

    val_every: int = option(1000, "steps between validations", check="positive")
    val_images: int = option(2, "validation images scored", check="nonnegative")
    chunk: int = option(8192, flag=None)  # rays per chunk when rendering whole images
    snapshots: str = option(
        "", "keep a copy of the checkpoint when the training time reaches each of these seconds "
        "(e.g. 15,60,300; RUN/snapshots/t60s.pt) for time-to-quality curves",
    )  # fmt: skip

    def check_section(self, fail) -> None:
        check_at_least(self, fail, 1, "val_every", "chunk")
        check_at_least(self, fail, 0, "val_images")
        if self.snapshots:
            from .loop import parse_snapshots

            try:
                parse_snapshots(self.snapshots)
            except ValueError as e:
                raise fail("snapshots", str(e)) from None


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _check_scene(scene, fail) -> None:
    """A saved ``scene`` (made by :func:`scene_settings`, kept by :meth:`NeRFConfig.resolve`): the
    capture's format, its world -> normalised similarity transform [4][4], the NDC camera or
    null, near, far, aabb."""
    keys = ("format", "transform", "ndc", "near", "far", "aabb")
    # "inner" (the contracted scene's inner cube) came later: older runs' scenes lack it
    if not isinstance(scene, dict) or set(scene) - {"inner"} != set(keys):
        raise fail(f"must be null or an object with exactly the keys {', '.join(keys)} "
                   "(and optionally inner)")  # fmt: skip
    if not isinstance(scene["format"], str) or not carries_scene(scene["format"]):
        raise fail(f"format must be a capture format ({', '.join(capture_formats())}) or an "
                   f"exported one (nerfstudio), got {scene['format']!r}"[:200])  # fmt: skip
    t = scene["transform"]
    rows_ok = isinstance(t, list) and len(t) == 4
    rows_ok = rows_ok and all(isinstance(r, list) and len(r) == 4 for r in t)
    rows_ok = rows_ok and all(_number(v) for r in t for v in r)
    if not rows_ok or t[3] != [0, 0, 0, 1] or not abs(_det3([r[:3] for r in t[:3]])) > 1e-300:
        raise fail("transform must be a 4x4 list of finite numbers (a similarity, last row "
                   "[0, 0, 0, 1])")  # fmt: skip
    ndc = scene["ndc"]
    if ndc is not None and not (
        isinstance(ndc, list) and len(ndc) == 4 and all(_number(v) and v > 0 for v in ndc)
    ):
        raise fail("ndc must be null or 4 positive finite numbers (fx, fy, W, H)")
    problem = scene_bounds_problem(scene["near"], scene["far"], scene["aabb"], scene.get("inner"))
    if problem is not None:  # (the rule of an exported capture's warpnerf_scene)
        raise fail(" ".join(problem))


def _det3(m) -> float:
    (a, b, c), (d, e, f), (g, h, i) = m
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
