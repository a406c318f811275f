"""Size presets of the `train` commands (``--preset cpu``) and the one-line hint printed when a
CPU run meets GPU-sized settings.

A preset is a table of config values per field (``PRESETS[name][field] -> {config field:
value}``); ``default`` (= ``gpu``) is the configs' own defaults. The command line leaves every
flag a preset sets at None ("not given", :func:`warpnerf.options.add_flags`'s ``unset``), so
:func:`warpnerf.options.apply_preset` fills in only what the user did not give: explicit flags
win. The preset's name is saved in the run's config.json (``preset``).

The ``cpu`` sizes train the built-in scene (``--data builtin`` / ``--points builtin``) to a
recognisable result in under a minute on 2 CPU cores once Warp's kernels are compiled (the first
run compiles them, a few minutes once). Measured on the project's 2-core CPU, idle, whole command
(wall): train nerf mlp 11 s, 20.7 dB val (the mean colour scores 9.6 dB); hash 22 s, 21.3 dB;
train volsdf 20 s, 21.1 dB; hash_sdf 38 s, 23.2 dB (43.5 s, 23.0 dB on 2026-12-03 with
forward differences, after the mask loss and the weight cull); train sdf mlp 9 s, Chamfer 0.020;
hash 14 s, Chamfer 0.0046. Under heavy sharing (load 15) the same runs took 15-30 minutes.
"""

from __future__ import annotations

import math

__all__ = ["PRESET_NAMES", "NERF_PRESETS", "SDF_PRESETS", "preset_values", "preset_fields",
           "default_field", "resolved_preset", "preset_help", "cpu_hint", "checkpoint_bytes",
           "preset_option"]  # fmt: skip

PRESET_NAMES = ("default", "gpu", "cpu")  # default: gpu on CUDA, the configs' own on a CPU


def preset_option(scene: str):
    """The ``preset`` field of a config whose cpu preset trains ``scene`` quickly."""
    from ..options import option

    return option(
        "default", f"sizes: cpu ({scene} in under a minute on 2 CPU cores; sets the flags "
        "marked --preset cpu, flags given explicitly win), gpu (the measured GPU recipe, marked "
        "--preset gpu) or default (gpu on CUDA, the plain defaults on a CPU)",
        choices=PRESET_NAMES,
    )  # fmt: skip


_NERF_CPU = dict(iters=300, batch=512, builtin_size=32, val_images=2)
_GRID_CPU = dict(grid_res=32, march_step=2 * math.sqrt(3) / 256, grid_warmup=64, grid_every=8)

# `train nerf` / `train volsdf`: NeRFConfig values per --field
NERF_PRESETS = {
    "cpu": {
        "mlp": {
            **_NERF_CPU,
            "n_coarse": 32,
            "n_layers": 4,
            "width": 64,
            "pos_freqs": 4,
            "lr": 5e-3,
            "lr_final": 5e-4,
        },
        "hash": {
            **_NERF_CPU,
            **_GRID_CPU,
            "hash_levels": 8,
            "hash_log2_size": 14,
            "hash_max_res": 128,
            "hidden": 32,
        },
        # (the eikonal term's double backward: about 2 s of CPU a step at batch 512 and 32 + 16
        # samples, measured; hence fewer rays, samples and steps)
        "volsdf": {
            **_NERF_CPU,
            "iters": 200,
            "batch": 256,
            "n_coarse": 24,
            "n_fine": 16,
            "n_layers": 4,
            "width": 64,
            "pos_freqs": 4,
            "lr": 5e-3,
            "lr_final": 5e-4,
        },
        # (300 steps: 28.0 dB but 2.5x the time of the others; 150: 23.2 dB.) hash_sdf's default
        # forward differences: 4 SDF evaluations a coloured sample instead of 7, the same
        # delivered mesh (Chamfer 0.0117) and val (23.00 against 22.94 dB) in 0.58x the training
        # time (50.8 s against 87.2 s on 2 cores, one run each, 2026-12-03, docs/design/
        # training.md "Issue 47, fifth round"; the field's default since the GPU's val agreed)
        "hash_sdf": {
            **_NERF_CPU,
            "iters": 150,
            **_GRID_CPU,
            "hash_levels": 8,
            "hash_log2_size": 14,
            "hash_max_res": 128,
            "hidden": 32,
        },
    },
}

# The GPU recipe of the hash field (issue 44, measured on lego 400x400, all 100 val images, one
# H200, 2026-11-27, docs/FIGURES.md): 2^19 composited samples a step (about 4,096 rays at first,
# the batch adapting to the samples) and tiny-cuda-nn's weight average (--ema 0.95: 36.21 and
# 36.11 dB at 60 s over two seeds against 35.83 without); TF32 is the config's default on CUDA.
# 40,000 steps (the lr decays to lr/20 over them; 20,000 before): 36.04 / 36.13 / 36.02 dB at
# 60 / 120 / 300 s against the 20,000-step schedule's 35.91 at 60 s and at its end (2 x H200,
# 2026-11-28, docs/design/nerf.md "Issue 44, third round"; 100,000 steps scored 0.1 dB more
# at each budget but makes the plain run 17 minutes long).
# Rendering (eval, render, validation, viewer) in chunks of 2^19 rays, a 400x400 frame in one:
# 97 ms a lego frame in the configs' 8,192-ray chunks (H200, 2026-11-28, docs/design/
# rendering.md "Issue 47") against 9.1-11.0 ms with `eval --chunk 400000` (H100/H200, 2026-11-26).
NERF_PRESETS["gpu"] = {
    "hash": {
        "batch": 4096,
        "target_samples": 1 << 19,
        "ema": 0.95,
        "iters": 40000,
        "chunk": 1 << 19,
    },
    # The surface field: the batch and samples of every hash_sdf measurement (--batch 4096
    # --target-samples 262144) and the weight average, which lifted lego from 31.33 to 33.13 dB
    # at 300 s and materials from 30.25 to 31.25 dB at 60 s with a finer mesh (Chamfer 0.0288
    # against 0.0314) (one H200, 2026-12-03, docs/design/surfaces.md "Issue 49, sixth round");
    # its frames in large chunks: 48 ms a 400x400 lego frame with `eval --chunk 400000` (H100,
    # 2026-11-25, surfaces.md "Issue 17, second round"), 155-176 ms in the configs' chunks (H200,
    # 2026-12-02, surfaces.md "Issue 49, fourth round")
    "hash_sdf": {"batch": 4096, "target_samples": 1 << 18, "ema": 0.95, "chunk": 400_000},
}


def default_field(field: str, device: str) -> str:
    """``--field auto``: the hash field on CUDA, the paper's MLP on a CPU (where the hash field
    at GPU sizes takes seconds a step; ``--preset cpu`` sizes either for the CPU)."""
    if field != "auto":
        return field
    return "hash" if str(device).startswith("cuda") else "mlp"


def resolved_preset(preset: str, device: str) -> str:
    """``--preset default`` on CUDA is the GPU recipe (``gpu``); elsewhere the name given."""
    return "gpu" if preset == "default" and str(device).startswith("cuda") else preset


# `train sdf`: SDFConfig values per --field
SDF_PRESETS = {
    "cpu": {
        "mlp": dict(iters=300, batch=1024, n_layers=4, width=64, resolution=64),
        "hash": dict(
            iters=300,
            batch=1024,
            hash_levels=8,
            hash_log2_size=14,
            hash_max_res=128,
            hash_width=32,
            resolution=64,
        ),  # fmt: skip
    },
}


def preset_values(table: dict, preset: str, field: str) -> dict:
    """The config values preset ``preset`` sets for ``field`` ({} for default/gpu)."""
    return dict(table.get(preset, {}).get(field, {}))


def preset_fields(table: dict) -> tuple:
    """Every config field some preset of ``table`` sets (their flags default to "not given")."""
    names = {k for fields in table.values() for values in fields.values() for k in values}
    return tuple(sorted(names))


def preset_help(table: dict) -> dict:
    """{config field: "--preset cpu: 300 (mlp), 200 (hash)"}: what each preset sets, for the
    flags' help."""
    out: dict = {}
    for name, fields in table.items():
        for field_name in preset_fields({name: fields}):
            vals = {}
            for field, values in fields.items():
                if field_name in values:
                    vals.setdefault(f"{values[field_name]:.4g}", []).append(field)
            text = ", ".join(
                v if len(vals) == 1 and len(fs) == len(fields) else f"{v} ({'/'.join(fs)})"
                for v, fs in vals.items()
            )
            out.setdefault(field_name, []).append(f"--preset {name}: {text}")
    return {k: "; ".join(v) for k, v in out.items()}


# seconds (CPU time) per unit of work on the project's 2-core CPU, fitted to steps 2-3 of
# today's defaults on the built-in scene (mlp 4.2 s, hash 4.4 s, hash_sdf 10.2 s a step); a rule
# of thumb telling a CPU user the order of magnitude before the first step, not a benchmark
SEC_PER_MLP_FLOP = 2e-11  # a sample through an MLP layer of width w: 6 w^2 flops (fwd + bwd)
SEC_PER_HASH_LOOKUP = 4e-7  # a sample through one hash level (8 corners, fwd + bwd)
HINT_STEP_SECONDS = 1.0  # an estimated step above this on a CPU is "GPU-sized"


def step_seconds(cfg) -> float:
    """A rough estimate of one training step's seconds of a NeRF/VolSDF config on a 2-core CPU:
    rays x samples per ray x the work per sample (MLP flops or hash lookups). With an occupancy
    grid the early steps march the whole box (every cell occupied), half its diagonal a ray."""
    cfg = cfg.resolve()  # (a resolved copy)
    if cfg.grid_res:
        steps = 2 * math.sqrt(3) * cfg.aabb / cfg.march_step
        samples = min(cfg.max_samples, steps / 2)
    else:
        samples = cfg.n_coarse + (cfg.n_coarse + cfg.n_fine if cfg.n_fine else 0)
    if cfg.traits.hash:
        mlp = 6 * 4 * cfg.hidden**2  # the density and colour MLPs, about 4 layers of width hidden
        per_sample = mlp * SEC_PER_MLP_FLOP + cfg.hash_levels * SEC_PER_HASH_LOOKUP
    else:
        per_sample = 6 * cfg.n_layers * cfg.width**2 * SEC_PER_MLP_FLOP
    # the field's own factor (its traits': a number, or a function of the config): hash_sdf's
    # finite differences (2.3 central, measured; forward 0.58x that), volsdf's eikonal double
    # backward (3)
    cost = cfg.traits.cpu_cost
    return cfg.batch * samples * per_sample * (cost(cfg) if callable(cost) else cost)


def cpu_hint(
    cfg, command: str = "train nerf", first_step: float | None = None, checkpoint: int | None = None
) -> str | None:
    """The one line a CPU run with GPU-sized settings prints (None: no line): the time a step
    and for all ``iters`` (``first_step``: the measured seconds of the run's first step, else the
    rule-of-thumb :func:`step_seconds`), the size of each checkpoint (``checkpoint`` bytes, see
    :func:`checkpoint_bytes`) and the suggestion of ``--preset cpu``. None on CUDA, with
    ``--preset cpu``, and when a step is estimated under :data:`HINT_STEP_SECONDS` (the rule of
    thumb decides, so that a small run whose first step compiles kernels says nothing)."""
    if not str(cfg.device).startswith("cpu") or cfg.preset == "cpu":
        return None
    sec = step_seconds(cfg)
    if sec < HINT_STEP_SECONDS:
        return None
    if first_step is None:
        took = f"about {_duration(sec)} a step on 2 CPU cores, {_duration(sec * cfg.iters)}"
    else:
        took = (f"the first step took {_duration(first_step)}, so about "
                f"{_duration(first_step * cfg.iters)}")  # fmt: skip
    size = "" if checkpoint is None else f"; each checkpoint is about {_size(checkpoint)}"
    return (
        f"warpnerf: note: --device cpu with GPU-sized settings (--batch {cfg.batch}, "
        f"--field {cfg.field}): {took} for --iters {cfg.iters}{size}; `{command} --preset cpu` "
        "sizes the run for a CPU (the built-in scene in under a minute)"
    )


def _duration(seconds: float) -> str:
    """``0.4 s``, ``52 s``, ``14 min``, ``35 h``: a duration to the unit that reads best."""
    if seconds < 10:
        return f"{seconds:.1f} s"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 2 * 3600:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.0f} h"


def _size(nbytes: float) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if nbytes < 1000 or unit == "GB":
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.3g} {unit}"
        nbytes /= 1000
    return f"{nbytes:.3g} GB"


def checkpoint_bytes(task) -> int:
    """About the bytes of a task's checkpoint: its model's state (parameters and buffers: the
    occupancy grid, poses) and Adam's two moments of every parameter (the optimiser's state once
    it has stepped). Tensors shared between parts count once; histories and generators (small)
    are left out."""
    import torch

    model = getattr(task, "model", None)
    params = list(task.parameters())
    state = list(model.state_dict().values()) if isinstance(model, torch.nn.Module) else params
    seen, total = set(), 0
    for t in state:
        if isinstance(t, torch.Tensor) and (t.data_ptr(), t.numel()) not in seen:
            seen.add((t.data_ptr(), t.numel()))
            total += t.numel() * t.element_size()
    return total + 2 * sum(p.numel() * p.element_size() for p in params)
