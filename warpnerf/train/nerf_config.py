"""NeRF's run settings (``NeRFConfig``): defaults, the data-dependent resolution (near/far, box,
the capture's scene transform and NDC camera), validation, and the dict saved in a run's
config.json."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import torch

from ..errors import UserError

__all__ = ["NeRFConfig"]


@dataclass
class NeRFConfig:
    data: str = "builtin"  # a dataset folder, or "builtin" for the small synthetic scene
    data_format: str = "auto"  # auto (detect), blender, nerfstudio, colmap or llff
    holdout: int = 8  # COLMAP/LLFF: every holdout-th image is val/test (0: none)
    ndc: str = "auto"  # COLMAP/LLFF: NDC rays on/off; auto: on for forward-facing captures
    scene: dict | None = None  # COLMAP/LLFF, resolved at the start: format, transform (world ->
    # normalised [4][4]), ndc camera (fx, fy, W, H) or None, near, far, aabb
    iters: int = 2000
    batch: int = 1024  # rays per step, uniform across all training images
    field: str = "mlp"  # "mlp": NeRF's MLP; "hash": hash-grid encoding + small MLPs (fast);
    # "volsdf": a neural SDF rendered through VolSDF's Laplace density
    lr: float | None = None  # None: 5e-4 (mlp) or 1e-2 (hash)
    lr_final: float | None = None  # lr decays exponentially to this at lr_decay_steps;
    # None: lr / 10 (mlp) or lr / 20 (hash)
    lr_decay_steps: int = 0  # 0: the run's first `iters` (resolved and saved at the start)
    n_coarse: int = 64
    n_fine: int = 0  # > 0 turns on the fine network (coarse/fine hierarchical sampling)
    view_dependence: bool = True
    n_layers: int = 8
    width: int = 256
    skip: int = 4
    pos_freqs: int = 10
    dir_freqs: int = 4
    density_activation: str = "softplus"
    hash_levels: int = 16  # hash field: grid levels, table rows per level (log2), resolutions
    hash_log2_size: int = 19
    hash_base_res: int = 16
    hash_max_res: int = 2048
    hidden: int = 64  # hash field: width of its MLPs
    beta: float = 0.1  # volsdf: initial Laplace scale (world units), its floor, learned or fixed
    beta_min: float = 1e-4
    learn_beta: bool = True
    eikonal_weight: float = 0.1  # volsdf: weight of (|grad d| - 1)^2 (samples + random points)
    grid_res: int | None = None  # occupancy grid cells per axis (even; 0 = no grid, dense
    # stratified/hierarchical samples); None: 128 for the hash field, 0 otherwise
    grid_every: int = 16  # steps between grid updates
    grid_warmup: int = 256  # steps during which every update evaluates all cells
    occ_threshold: float = 0.01  # a cell is empty when one step through it has opacity below this
    march_step: float = 0.0  # marching step with a grid; 0: the box diagonal / 1024
    max_samples: int = 1024  # samples per ray at most with a grid
    round_samples: int = 0  # with a grid, rendering (no gradients) marches in rounds of this
    # many samples per live ray; 0: one round over all marched samples
    render_half: bool = False  # with a grid on CUDA, rendering runs the MLPs in float16
    target_samples: int = 0  # > 0: rays per step adapt so each step composites ~this many
    # samples (starting from --batch); 0: fixed --batch
    aabb: float = 0.0  # hash field: half-size of the scene cube at the origin (samples are
    # restricted to it); 0: 1.5 for datasets (lego), the built-in scene's own for builtin
    near: float | None = None  # None: 2 for datasets (lego), the built-in scene's own for builtin
    far: float | None = None  # None: 6 for datasets, the built-in scene's own for builtin
    background: float = 1.0  # white, as the NeRF-synthetic evaluation
    downscale: int = 1
    max_images: int = 0  # 0 = all
    builtin_size: int = 48
    t_threshold: float = 1e-4  # early termination (training and rendering)
    val_every: int = 500
    val_images: int = 2
    ckpt_every: int = 500
    chunk: int = 8192  # rays per chunk when rendering whole images
    max_seconds: float = 0.0  # stop (and checkpoint) after this much training time in this
    # invocation (a resume gets a fresh budget); 0 = no limit
    tf32: bool = False  # TF32 matrix products for the MLPs on CUDA (kernels stay float32)
    seed: int = 0
    device: str = "cpu"

    def to_dict(self):
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "config"):
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise UserError(f"{where}: unknown field(s) {sorted(unknown)}")
        return cls(**d)

    def resolve(self):
        """Fills in defaults that depend on the data and the field (near/far, lr, aabb)."""
        if self.lr is None:
            self.lr = 1e-2 if self.field == "hash" else 5e-4
        if self.lr_final is None:
            self.lr_final = self.lr / (20.0 if self.field == "hash" else 10.0)
        self._resolve_scene()
        if self.aabb <= 0 and self.scene is not None:
            self.aabb = self.scene["aabb"]
        if self.aabb <= 0 and self.field in ("hash", "volsdf"):
            if self.data == "builtin":
                from ..data.synthetic import BOUND

                self.aabb = BOUND
            else:
                self.aabb = 1.5
        if self.grid_res is None:
            self.grid_res = 128 if self.field == "hash" else 0
        if self.grid_res and self.march_step <= 0:
            self.march_step = 2.0 * self.aabb * math.sqrt(3.0) / 1024
        self._resolve_scene()
        if self.near is None or self.far is None:
            if self.scene is not None:
                NEAR, FAR = self.scene["near"], self.scene["far"]
            elif self.data == "builtin":
                from ..data.synthetic import FAR, NEAR
            else:
                NEAR, FAR = 2.0, 6.0
            self.near = NEAR if self.near is None else self.near
            self.far = FAR if self.far is None else self.far
        return self

    def _resolve_scene(self):
        """Reads a COLMAP/LLFF folder's poses once (no pixels) into ``scene``."""
        if self.scene is not None or self.data == "builtin" or not Path(self.data).is_dir():
            return  # (a missing folder is reported by the loader)
        from ..data.capture import capture_info
        from ..data.datasets import FORMATS, detect_format

        if self.data_format not in FORMATS or self.ndc not in ("auto", "on", "off"):
            raise UserError(
                f"--format must be one of {', '.join(FORMATS)} and --ndc auto, on or off; "
                f"got {self.data_format!r}, {self.ndc!r}"
            )
        fmt = self.data_format if self.data_format != "auto" else detect_format(self.data)
        if fmt not in ("colmap", "llff"):
            if self.ndc == "on":
                raise UserError("--ndc on needs a forward-facing COLMAP or LLFF capture")
            return
        info = capture_info(self.data, fmt, self.downscale, self.holdout)
        ndc = info["forward_facing"] if self.ndc == "auto" else self.ndc == "on"
        if ndc and not info["forward_facing"]:  # NDC needs the forward-facing normalisation
            raise UserError(
                f"{self.data}: --ndc on needs a forward-facing capture (every viewing axis within "
                "45 degrees of their mean); this one is not"
            )
        self.scene = {
            "format": fmt,
            "transform": info["transform"],
            "ndc": info["ndc_camera"] if ndc else None,
            "near": 0.0 if ndc else info["near"],
            "far": 4.0 if ndc else info["far"],
            "aabb": 1.5 if ndc else info["aabb"],
        }

    def ndc_camera(self):
        """(fx, fy, W, H) of the NDC camera, or None when rays stay in world space."""
        return self.scene["ndc"] if self.scene else None

    def validate(self):
        for name in (
            "iters",
            "batch",
            "n_coarse",
            "n_layers",
            "width",
            "val_every",
            "ckpt_every",
            "chunk",
            "builtin_size",
            "downscale",
        ):
            value = getattr(self, name)
            if value < 1:
                raise UserError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
        if self.n_fine < 0 or self.pos_freqs < 0 or self.dir_freqs < 0:
            raise UserError("--n-fine, --pos-freqs and --dir-freqs must be >= 0")
        if self.field not in ("mlp", "hash", "volsdf"):
            raise UserError(f"--field must be mlp, hash or volsdf, got {self.field!r}")
        if self.field == "volsdf":
            if not (self.beta > 0 and 0 < self.beta_min <= self.beta):
                raise UserError(f"need 0 < --beta-min <= --beta, got {self.beta_min}, {self.beta}")
            ew = self.eikonal_weight
            if self.width <= 3 * (1 + 2 * self.pos_freqs) or not (math.isfinite(ew) and ew >= 0):
                raise UserError("volsdf: --width must exceed the encoded position size and "
                                "--eikonal-weight must be >= 0")  # fmt: skip
        if self.field == "hash":
            from ..ops.encoding import HashGrid

            try:
                HashGrid(**self._grid_kwargs())
            except ValueError as e:
                raise UserError(f"hash grid: {e}") from None
            if self.hidden < 1:
                raise UserError(f"--hidden must be >= 1, got {self.hidden}")
        self.resolve()
        if self.grid_res:
            if self.field != "hash":
                raise UserError("--grid-res needs --field hash (set --grid-res 0 otherwise)")
            if self.grid_res < 2 or self.grid_res % 2 or self.grid_res > 1024:
                raise UserError(f"--grid-res must be even, in [2, 1024], got {self.grid_res}")
            for name in ("grid_every", "max_samples"):
                if getattr(self, name) < 1:
                    raise UserError(f"--{name.replace('_', '-')} must be >= 1")
            if not (0 < self.occ_threshold < 1 and math.isfinite(self.march_step)):
                raise UserError("--occ-threshold must be in (0, 1) and --march-step finite")
            # lattice intervals across the diagonal (the default step gives exactly 1024)
            need = math.ceil(2 * math.sqrt(3) * self.aabb / self.march_step * (1 - 1e-6))
            if self.max_samples < need:  # training would cut rays off where rendering does not
                raise UserError(
                    f"--max-samples {self.max_samples} is below the {need} steps of "
                    f"--march-step {self.march_step:g} across the box diagonal"
                )
            if min(self.grid_warmup, self.target_samples, self.round_samples) < 0:
                raise UserError("--grid-warmup, --target-samples, --round-samples must be >= 0")
        if not 0.0 <= self.t_threshold < 1.0:
            raise UserError(f"--t-threshold must be in [0, 1), got {self.t_threshold}")
        if self.max_seconds < 0 or self.val_images < 0 or self.max_images < 0:
            raise UserError("--max-seconds, --val-images and --max-images must be >= 0")
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            raise UserError(
                f"device {self.device!r}: no CUDA device available here (pass --device cpu)"
            )
        if not self.far > self.near >= 0:
            raise UserError(f"need 0 <= --near < --far, got near={self.near}, far={self.far}")
        if not (self.lr > 0 and self.lr_final > 0):
            raise UserError("--lr and --lr-final must be positive")
        return self

    def _grid_kwargs(self) -> dict:
        return dict(
            n_levels=self.hash_levels,
            log2_size=self.hash_log2_size,
            base_res=self.hash_base_res,
            max_res=self.hash_max_res,
        )

    def aabb_box(self):
        """The scene box [6]: with NDC rays [-a, a]^2 x [-1, 1] (z = 1 is infinity), for the
        hash/VolSDF field [-a, a]^3, else None (the MLP field samples near..far)."""
        a = float(self.aabb)
        if self.ndc_camera() is not None:
            return [-a, -a, -1.0, a, a, 1.0]
        if self.field not in ("hash", "volsdf"):
            return None
        return [-a, -a, -a, a, a, a]
