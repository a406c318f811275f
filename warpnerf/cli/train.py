"""`warpnerf train box|nerf|volsdf|sdf`: the built-in methods' front ends (presets, resume
checks, data parallel), registered at the end of this module as an outside method's would be
(:mod:`warpnerf.cli.train_commands` makes every `train` command by one path)."""

from __future__ import annotations

import dataclasses
import os
import sys
from functools import partial

from ..errors import UserError
from ..fields.model import field_traits, fields_with
from ..fields.settings import VOLSDF
from ..options import CHECKS, add_flags, apply_preset, flag_of, from_flags
from ..outputs import json_dumps
from ..train.box_fit import MODEL as BOX_MODEL
from ..train.box_fit import BoxFitConfig
from ..train.nerf_config import BEFORE_DEFAULT_CHANGED, FINE_SAMPLES, GRID, NeRFConfig, VolSDFConfig
from ..train.nerf_config import MODEL as NERF_MODEL
from ..train.presets import (
    NERF_PRESETS,
    SDF_PRESETS,
    checkpoint_bytes,
    cpu_hint,
    default_field,
    preset_fields,
    preset_help,
    preset_values,
    resolved_preset,
)
from ..train.sdf import MODEL as SDF_MODEL
from ..train.sdf import SDFConfig
from ._common import check_existing, check_out, parse_device, saved_config
from .train_commands import TrainCommand, register_train_command, resume_hint
from .view import live_hooks, tensorboard_every, watch_flags

__all__ = ["nerf_config_from_args"]  # (the helpers scripts/ may use)

DEVICE = "cpu"  # a new box fit's device (the box config holds none)


def _train_command(args, cls, new_config, train, report=lambda res: res) -> int:
    """The front end `train box` and `train sdf` share: the run folder checked, the config
    (``new_config(args) -> (config, device)`` for a new run; on --resume :func:`_resumed`),
    ``train(config, device, resume=..., progress=..., tensorboard=..., hooks=...)``, and
    ``report(result)`` printed as JSON."""
    check_out(args.out)
    cfg, device = _resumed(args, cls) if args.resume else new_config(args)
    with resume_hint(args, cfg.iters):
        res = train(cfg, device, resume=args.resume, progress=not args.quiet,
                    tensorboard=tensorboard_every(args), hooks=live_hooks(args))  # fmt: skip
    print(json_dumps(report(res)))
    return 0


def cmd_train_box(args) -> int:
    from ..train.box_fit import run_box_fit_on_folder

    def new_config(args):
        if args.data is None:
            raise UserError("--data DIR is required (a Blender-format folder)")
        cfg = BoxFitConfig(**from_flags(BoxFitConfig, args))
        if not cfg.far > cfg.near >= 0:
            raise UserError(f"need 0 <= --near < --far, got --near {cfg.near} and --far {cfg.far}")
        return cfg, parse_device(args.device or DEVICE)

    def train(cfg, device, **kw):  # (a resumed fit reads its data folder from the run)
        data = None if args.resume else args.data
        return run_box_fit_on_folder(data, args.out, cfg, device=device, frames=args.frames, **kw)

    return _train_command(args, BoxFitConfig, new_config, train)


# Flags a resume may change; every other train flag is fixed by the run's config.json (given
# again, it must equal the saved value: _resume_device).
_RESUME_FLAGS = {
    "out",
    "resume",
    "iters",
    "device",
    "max_seconds",
    "quiet",
    "func",
    "command",
    "model",
    "frames",  # train box: the spiral video written at the end, not part of the fit
    "tensorboard",  # watching a training changes nothing in it
    "log_every",
    "viewer",
    "viewer_wait",
    "host",
    "port",
}


def _resume_device(args, cls):
    """Checks a --resume command line; returns the --device override (None: the run's own).

    Only --iters, --device and --max-seconds (and the watching flags) may change; any other flag
    given must equal the run's saved config (``cls``'s defaults for keys an older run lacks):
    repeating the command that started the run, --preset included, is accepted, and a flag whose
    value differs is refused by name, with the saved value and the one given."""
    if args.iters is None:
        raise UserError("--resume needs --iters (the total number of steps to reach)")
    given = [k for k in _given_dests(args) if k not in _RESUME_FLAGS]
    if given:
        saved = saved_config(args.out)  # ({}: no run there, or no readable config: "drop")
        changed = [(k, _saved_value(k, saved, cls) if saved else _UNKNOWN) for k in given]
        changed = [(k, s) for k, s in changed if not _same(k, getattr(args, k), s)]
        if changed:
            flags = {a.dest: a.option_strings[0] for a in args.subparser._actions
                     if a.option_strings}  # fmt: skip
            names = ", ".join(
                flags.get(k, "--" + k.replace("_", "-"))
                + ("" if s is _UNKNOWN else f" (saved {_show(s)}, given {_show(getattr(args, k))})")
                for k, s in sorted(changed, key=lambda ks: flags.get(ks[0], ks[0]))
            )
            raise UserError(
                f"with --resume the run's saved config is used; drop {names} "
                "(only --iters, --device and --max-seconds may change; flags equal to the saved "
                "ones may stay)"
            )
    check_existing(args.out, "training run to continue (--out RUN --resume)")
    return parse_device(args.device) if args.device else None


_UNKNOWN = object()  # a saved value that cannot be known (no readable config.json)
_PATHS = ("data", "points")  # flags naming a file or folder: equal when they name the same one


def _given_dests(args) -> list:
    """The flags (their dests) given on a `train` command line: those whose value differs from
    the subcommand's default, and those written out on the command line being run (a flag given
    at its default value; read from the recorded command when it is this `train` command)."""
    # the subcommand's own parser (set as a default by cli.parser): its defaults, unparsed
    defaults = args.subparser.parse_args(["--out", "x"])
    given = {k for k, v in vars(args).items() if v != getattr(defaults, k, v)}
    from ..train.provenance import current_command

    argv = current_command()[1:]
    at = [i for i in range(len(argv) - 1) if argv[i : i + 2] == ["train", args.model]]
    if at:
        opts = {s: a.dest for a in args.subparser._actions for s in a.option_strings}
        for tok in argv[at[0] + 2 :]:
            if tok == "--":
                break
            if tok.split("=", 1)[0] in opts:
                given.add(opts[tok.split("=", 1)[0]])
    return [k for k in vars(args) if k in given]


def _saved_value(dest: str, saved: dict, cls):
    """What the run's saved config (a dict) holds for the flag ``dest`` of a `train` command,
    in the flag's terms; ``cls``'s default for a key an older run lacks."""
    defaults = _defaults(cls)
    if dest == "coarse_fine":  # (train nerf|volsdf: the fine network, n_fine > 0)
        return (saved.get("n_fine", defaults.get("n_fine")) or 0) > 0
    if dest == "fine_samples":
        return saved.get("n_fine", defaults.get("n_fine"))
    if dest in defaults or dest in saved:  # (a key whose default changed: its value before)
        return saved.get(dest, BEFORE_DEFAULT_CHANGED.get(dest, defaults.get(dest)))
    opts = saved.get("field_options")  # a field's own flags (train nerf|volsdf)
    if isinstance(opts, dict) and dest in opts:
        return opts[dest]
    for o in _field_option_classes():
        if dest in _defaults(o):
            return _defaults(o)[dest]
    return _UNKNOWN


def _defaults(cls) -> dict:
    """{field: default} of a config dataclass (its factories called)."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            out[f.name] = f.default
        elif f.default_factory is not dataclasses.MISSING:
            out[f.name] = f.default_factory()
    return out


def _same(dest: str, given, saved) -> bool:
    """Whether a flag's value given on --resume equals the saved one: numbers by value (1 and
    1.0), lists and tuples by items, paths (--data, --points) when they name the same file."""
    import math
    from pathlib import Path

    if saved is _UNKNOWN:
        return False
    if dest == "preset":  # (gpu is another name of default)
        given, saved = ("default" if v == "gpu" else v for v in (given, saved))
    if dest == "fine_samples" and saved == 0:
        return True  # (no fine network: the flag changes nothing)
    if isinstance(given, (list, tuple)) and isinstance(saved, (list, tuple)):
        return len(given) == len(saved) and all(_same("", a, b) for a, b in zip(given, saved))
    if isinstance(given, bool) or isinstance(saved, bool):
        return isinstance(given, bool) and isinstance(saved, bool) and given == saved
    if isinstance(given, (int, float)) and isinstance(saved, (int, float)):
        return math.isclose(given, saved, rel_tol=1e-9, abs_tol=0.0) or given == saved
    if given == saved:
        return True
    if dest in _PATHS and isinstance(given, str) and isinstance(saved, str):
        if "builtin" in (given, saved):  # (the built-in scene: a name, not a path)
            return False
        try:
            return Path(given).expanduser().resolve() == Path(saved).expanduser().resolve()
        except (OSError, RuntimeError, ValueError):
            return False
    return False


def _show(value) -> str:
    """A value as the command line writes it."""
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def _resumed(args, cls) -> tuple:
    """(config, device) of `train ... --resume`: the class's defaults with the loop's --iters
    and --max-seconds from the command line (the trainer reads the rest from the run's saved
    config), and the --device override (None: the run's own)."""
    device = _resume_device(args, cls)
    return cls(iters=args.iters, max_seconds=args.max_seconds), device


def nerf_config_from_args(args):
    """The NeRFConfig / VolSDFConfig of parsed `train nerf|volsdf` flags (a new run)."""
    if args.data is None:
        raise UserError("--data DIR is required (or --data builtin for the built-in scene)")
    cls = VolSDFConfig if args.model == "volsdf" else NeRFConfig
    kw = from_flags(cls, args, groups=_GROUPS[args.model])
    kw["n_fine"] = args.fine_samples  # (None: not given, the preset's or FINE_SAMPLES)
    kw["device"] = parse_device(args.device or cls.device)
    # --field auto: the hash field on CUDA, the paper's MLP on a CPU; --preset default on CUDA:
    # the measured GPU recipe (presets.NERF_PRESETS["gpu"]), saved as "gpu"
    auto = "auto" if cls is NeRFConfig else cls.field
    kw["field"] = default_field(kw.get("field") or auto, kw["device"])
    if cls is NeRFConfig and field_traits(kw["field"]).geometry == "sdf":
        # `train nerf` shows no SDF flags (beta, its schedule, --sdf-gradient) and lacks
        # VolSDF's defaults (the opacity loss, 6 frequencies): a run here would train a recipe
        # nobody measured, with no way to set its beta
        raise UserError(f"--field {kw['field']} is a surface field: train it with `warpnerf "
                        f"train volsdf --field {kw['field']}` (VolSDF's defaults and its flags: "
                        "--beta, --beta-final, --sdf-gradient, ...)")  # fmt: skip
    kw["preset"] = resolved_preset(kw["preset"], kw["device"])
    # the preset's sizes for the flags not given (explicit flags win)
    kw = apply_preset(kw, preset_values(NERF_PRESETS, kw["preset"], kw["field"]))
    kw["n_fine"] = (kw["n_fine"] or FINE_SAMPLES) if args.coarse_fine else 0
    opts = field_traits(kw["field"]).options  # the chosen field's own flags
    if opts is not None:
        kw["field_options"] = from_flags(opts, args)
    _refuse_other_fields_flags(args, cls, kw["field"])
    return cls(**kw)


def _refuse_other_fields_flags(args, cls, field: str) -> None:
    """A UserError for flags given that ``field`` does not read: another field's own options
    (its traits' ``options``) or a built-in field section (fields/settings.py) outside its
    traits' ``config``, e.g. --hash-levels with --field mlp: they would be saved and silently
    ignored. Given: not None and not the default."""
    from ..fields.model import FIELD_TRAITS

    def readers(part) -> list:
        return [n for n, t in FIELD_TRAITS.items() if part in (t.options, *t.config)]

    mine = field_traits(field)
    defaults = {f.name: f.default for f in dataclasses.fields(cls)}
    parts = [*(t.options for t in FIELD_TRAITS.values() if t.options),
             *(s for t in FIELD_TRAITS.values() for s in t.config)]  # fmt: skip
    for part in dict.fromkeys(parts):
        if part in (mine.options, *mine.config):
            continue
        given = [
            f.metadata["negate"] or flag_of(f)
            for f in dataclasses.fields(part)
            if f.metadata.get("flag") is not None
            and getattr(args, f.name, None) not in (None, defaults.get(f.name, f.default))
        ]
        if not given:
            continue
        flags, by = ", ".join(given), ", ".join(readers(part))
        if getattr(part, "TITLE", None):
            raise UserError(f"{flags}: {part.TITLE} settings, read by --field {by}, not by "
                            f"--field {field}")  # fmt: skip
        raise UserError(f"{flags}: options of another field (--field {by}), not of --field "
                        f"{field}")  # fmt: skip


def _field_option_classes() -> list:
    """The ``options`` classes of the registered fields (each field's own flags)."""
    from ..fields.model import FIELD_TRAITS

    return list(dict.fromkeys(t.options for t in FIELD_TRAITS.values() if t.options))


class _CpuNote:
    """A loop hook printing one line on stderr when a CPU run meets GPU-sized settings
    (train/presets.py: cpu_hint). It speaks after the first step, with that step's measured
    time and the checkpoint's size (counted at the loop's start, once the config and the data
    have been checked: a user mistake stays a one-line error with no note before it)."""

    def __init__(self, cfg, command: str):
        self.cfg, self.command = cfg, command
        self.start, self.bytes = None, None

    def on_start(self, task, step: int) -> None:
        if cpu_hint(self.cfg, self.command) is None:
            return  # (no note: nothing to measure)
        self.start = step
        self.bytes = checkpoint_bytes(task) if task is not None else None

    def on_step(self, step: int, history: dict, lr: float) -> None:
        if self.start is None or step != self.start + 1:
            return
        secs = history.get("seconds") or []
        first = secs[-1] - (secs[-2] if len(secs) > 1 else 0.0) if secs else None
        line = cpu_hint(self.cfg, self.command, first_step=first, checkpoint=self.bytes)
        if line:
            print(line, file=sys.stderr, flush=True)

    def on_validation(self, step: int, figures: dict, task) -> None:
        pass

    def close(self) -> None:
        pass


def _silent(*args, **kw) -> None:
    """The log of a data-parallel run's ranks other than 0."""


def cmd_train_nerf(args) -> int:
    from ..train.nerf import train_nerf

    sdf = fields_with(geometry="sdf")
    if args.model == "volsdf" and field_traits(args.field).geometry != "sdf":
        raise UserError(
            f"train volsdf trains an SDF field ({', '.join(sdf)}); use train nerf for --field "
            f"{'|'.join(fields_with(geometry='density'))}"
        )
    check_out(args.out)
    if args.resume:
        cfg, device = _resumed(args, NeRFConfig)
        field = saved_config(args.out).get("field", "volsdf")
        if args.model == "volsdf" and field_traits(field).geometry != "sdf":
            raise UserError(
                f"{args.out}: a NeRF run with --field {field}, not a VolSDF run; continue it with "
                f"`warpnerf train nerf --out {args.out} --resume --iters N`"
            )
    else:
        cfg, device = nerf_config_from_args(args), None
    # started by torchrun (WORLD_SIZE > 1): one rank of a data-parallel run (train/distributed.py)
    from ..train.distributed import from_env

    want = cfg.device if not args.resume else device or saved_config(args.out).get("device")
    dist, rank_device = from_env(str(want or "cpu"))
    if dist is not None:  # (each rank's own device: a new run's config built with it)
        device = rank_device if args.resume else device
        cfg = cfg if args.resume else dataclasses.replace(cfg, device=rank_device)
    main = dist is None or dist.main
    # (only rank 0 prints: the other ranks' lines would repeat its own)
    notes = [] if args.resume else [_CpuNote(cfg, f"warpnerf train {args.model}")]
    with resume_hint(args, cfg.iters):
        hist = train_nerf(cfg, args.out, resume=args.resume, progress=not args.quiet and main,
                          device=device, hooks=(live_hooks(args) + notes) if main else [],
                          tensorboard=tensorboard_every(args), dist=dist,
                          log=print if main else _silent)  # fmt: skip
    if dist is not None:  # (every rank finished: they leave the group together)
        dist.close()
    if not main:
        # A rank other than 0 has written nothing and has nothing left to do: it leaves at once,
        # without the interpreter's teardown, in which gloo's threads were seen to abort a rank
        # after a finished run (SIGABRT, "terminate called without an active exception": 2 of 5
        # CI runs on 2026-12-03, both times rank 1, after destroy_process_group).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    last = {
        "step": hist["step"][-1] if hist["step"] else 0,
        "train_psnr": hist["psnr"][-1] if hist["psnr"] else None,
        "val_psnr": hist["val_psnr"][-1] if hist["val_psnr"] else None,
        "seconds": hist["seconds"][-1] if hist["seconds"] else 0.0,
    }
    print(json_dumps(last))
    return 0


def cmd_train_sdf(args) -> int:
    from ..train.sdf import train_sdf

    def new_config(args):
        if args.points is None:
            raise UserError("--points FILE.npz|FILE.ply (or 'builtin') is required")
        kw = from_flags(SDFConfig, args)
        # the preset's sizes for the flags not given (explicit flags win), then the defaults
        kw = apply_preset(kw, preset_values(SDF_PRESETS, kw["preset"], kw["field"]))
        batch, layers = kw.get("batch", SDFConfig.batch), kw.get("n_layers", SDFConfig.n_layers)
        kw.update(n_random=batch, skip=max(1, layers // 2))
        kw["device"] = parse_device(args.device or SDFConfig.device)
        return SDFConfig(**kw), None  # (the device is the config's)

    def report(m):
        out = {k: m[k] for k in ("step", "seconds", "chamfer", "vertices", "faces")}
        out["eikonal_residual_box_mean"] = m["eikonal_residual_box"]["mean"]
        if "mesh_clean" in m:  # mesh.ply's cleaning: the components dropped
            out["mesh_clean"] = m["mesh_clean"]
        return out

    def train(cfg, device, **kw):
        return train_sdf(cfg, args.out, device=device, **kw)

    return _train_command(args, SDFConfig, new_config, train, report)


def add_box_flags(tb) -> None:
    """`train box`: BoxFitConfig's flags (warpnerf.options) and the command's own."""
    tb.add_argument("--data", help="folder with transforms*.json and PNG images")
    tb.add_argument("--out", required=True, help="run folder (config, checkpoint, result)")
    tb.add_argument("--resume", action="store_true", help="continue the fit in --out exactly")
    tb.add_argument(
        "--device",
        default=None,
        help=f"cpu or cuda (default {DEVICE}; on --resume, default the run's own)",
    )
    tb.add_argument("--frames", type=CHECKS[("int", "nonnegative")], default=40,
                    help="spiral video frames (0: none)")  # fmt: skip
    tb.add_argument("--quiet", action="store_true", help="no progress bar")
    watch_flags(tb)
    add_flags(tb, BoxFitConfig, unset=("iters",))


def add_sdf_flags(ts) -> None:
    """`train sdf`: SDFConfig's flags (warpnerf.options) and the command's own."""
    ts.add_argument("--points", help=SDFConfig.__dataclass_fields__["points"].metadata["help"])
    ts.add_argument("--out", required=True, help="run folder")
    ts.add_argument("--resume", action="store_true", help="continue the fit in --out exactly")
    ts.add_argument("--quiet", action="store_true", help="no progress bar")
    watch_flags(ts)
    add_flags(ts, SDFConfig, exclude=("points",), unset=("iters", "device", *_SDF_PRESET),
              notes=preset_help(SDF_PRESETS))  # fmt: skip


_GROUPS = {"nerf": GRID, "volsdf": VOLSDF + GRID}  # the config fields each command shows
# the flags a preset sets: default None ("not given"), so that the preset fills them in
_NERF_PRESET, _SDF_PRESET = preset_fields(NERF_PRESETS), preset_fields(SDF_PRESETS)


def _section_title(section) -> str:
    """A config section's title in --help; a field's section names the fields that read it
    (their traits' ``config``)."""
    from ..fields.model import FIELD_TRAITS

    readers = [n for n, t in FIELD_TRAITS.items() if section in t.config]
    return f"{section.TITLE} (--field {', '.join(readers)})" if readers else section.TITLE


def add_nerf_flags(tn, model: str) -> None:
    """The flags of `train nerf` and `train volsdf`: built from NeRFConfig / VolSDFConfig
    (warpnerf.options; defaults and help are the config's), plus the command's own."""
    cls = VolSDFConfig if model == "volsdf" else NeRFConfig
    tn.add_argument("--data", help=cls.__dataclass_fields__["data"].metadata["help"])
    tn.add_argument("--out", required=True, help="run folder (config, checkpoint, history)")
    tn.add_argument("--resume", action="store_true", help="continue the run in --out exactly")
    tn.add_argument("--coarse-fine", action="store_true", default=cls.n_fine > 0,
                    help="add the fine network")  # fmt: skip
    fine = preset_help(NERF_PRESETS).get("n_fine")
    tn.add_argument("--fine-samples", type=CHECKS[("int", "positive")], default=None,
                    help=f"fine samples per ray (default {FINE_SAMPLES}; {fine})")  # fmt: skip
    tn.add_argument("--quiet", action="store_true", help="no progress bar")
    watch_flags(tn)
    # `train nerf --field` not given: auto (nerf_config_from_args: hash on CUDA, mlp on a CPU)
    auto = ("field",) if model == "nerf" else ()
    unset = ("iters", "device", *_NERF_PRESET, *auto)
    add_flags(tn, cls, groups=_GROUPS[model], exclude=("data",), unset=unset,
              defaults={k: "auto" for k in auto}, notes=preset_help(NERF_PRESETS),
              titles=_section_title)  # fmt: skip
    from ..fields.model import FIELD_TRAITS

    if model == "nerf":  # the surface fields are refused here (they train with `train volsdf`):
        # the help lists the fields this command trains
        act = tn._option_string_actions["--field"]
        mine = [n for n in act.choices if FIELD_TRAITS[n].geometry != "sdf"]
        surface = [n for n in act.choices if n not in mine]
        act.metavar = "{" + ",".join(mine) + "}"
        act.help = ("mlp: NeRF's MLP; hash: hash-grid encoding + small MLPs (trains in "
                    "minutes); not given: hash on CUDA, mlp on a CPU (the surface fields, "
                    f"{', '.join(surface)}, train with `train volsdf`)")  # fmt: skip

    taken = {a.dest for a in tn._actions}
    for opts in _field_option_classes():  # each registered field's own flags ("not given": None)
        fields = [n for n, t in FIELD_TRAITS.items() if t.options is opts]
        clash = sorted(taken & {f.name for f in dataclasses.fields(opts)})
        if clash:  # (a developer's mistake: say which, rather than argparse's conflict)
            raise ValueError(
                f"the options of --field {' or '.join(fields)} ({opts.__name__}) "
                f"reuse the names of other train flags: {', '.join(clash)}"
            )
        taken |= {f.name for f in dataclasses.fields(opts)}
        group = tn.add_argument_group(f"--field {' or '.join(fields)}")
        add_flags(group, opts, unset=[f.name for f in dataclasses.fields(opts)])


# the built-in methods' front ends, registered as an outside method's would be (in the order
# `train --help` lists them)
register_train_command(BOX_MODEL, "box", TrainCommand(
    "fit the rainbow SDF box to a Blender-format folder", add_box_flags,
    cmd_train_box))  # fmt: skip
register_train_command(NERF_MODEL, "nerf", TrainCommand(
    "train a NeRF (coarse, or coarse/fine) on a dataset", partial(add_nerf_flags, model="nerf"),
    cmd_train_nerf))  # fmt: skip
register_train_command(NERF_MODEL, "volsdf", TrainCommand(
    "train VolSDF (neural SDF + Laplace density) on a dataset: the surface fields (--field "
    "volsdf, hash_sdf) with VolSDF's defaults and flags", partial(add_nerf_flags,
    model="volsdf"), cmd_train_nerf))  # fmt: skip
register_train_command(SDF_MODEL, "sdf", TrainCommand(
    "fit a neural SDF to a point cloud (eikonal loss) + mesh", add_sdf_flags,
    cmd_train_sdf))  # fmt: skip
