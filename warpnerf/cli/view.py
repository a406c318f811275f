"""`warpnerf view RUN`: the web viewer on a local port; and the flags that watch a training
(`--viewer`, `--no-tensorboard`)."""

from __future__ import annotations

import argparse
import contextlib
import os
import sys

from ..errors import UserError
from ..options import number_type
from ._common import check_existing, parse_device, positive_arg


def _host_port_flags(p, port_flag: str) -> None:
    p.add_argument("--host", default="127.0.0.1", help="address the viewer listens on "
                   "(default 127.0.0.1: this machine only; 0.0.0.0 lets other machines "
                   "connect, with a warning: whoever reaches the port and has the printed "
                   "URL's token can use the viewer)")  # fmt: skip
    p.add_argument(port_flag, type=int, default=7007, dest="port",
                   help="the viewer's port (default 7007; the next free one if taken)")  # fmt: skip


def view_flags(v) -> None:
    v.add_argument("run", help="a run folder (train nerf, volsdf, sdf or box)")
    _host_port_flags(v, "--port")
    v.add_argument("--device", default=None, help="cpu or cuda (default: the run's device)")
    v.add_argument("--mesh", default=None, help="a PLY to overlay (default RUN/mesh.ply if any)")
    v.add_argument("--max-resolution", default=800,
                   type=number_type(int, lambda n: 64 <= n <= 4096, "in 64..4096"),
                   help="longest side of the finest still frame, pixels (default 800; "
                   "where that would take long, still frames start smaller, ~2 s each, and "
                   "refine up to it)")  # fmt: skip
    v.add_argument("--frame-ms", type=positive_arg(float), default=100.0,
                   help="render time aimed at while the camera moves (default 100 ms)")  # fmt: skip
    v.add_argument("--exit-after", type=positive_arg(float), default=None, metavar="S",
                   help="stop the server after S seconds (scripts, tests)")  # fmt: skip


def watch_flags(p) -> None:
    """`train ...`: --no-tensorboard, --log-every, --viewer, --host, --viewer-port."""
    p.add_argument(
        "--no-tensorboard",
        dest="tensorboard",
        action="store_false",
        help="no TensorBoard event files in RUN/tensorboard (default: written)",
    )
    p.add_argument(
        "--log-every",
        type=positive_arg(int),
        default=10,
        metavar="N",
        help="TensorBoard: scalars every N steps (default 10; history.json has all)",
    )
    p.add_argument("--viewer", action="store_true", help="serve the web viewer during "
                   "training (frames render between steps; Ctrl-C still stops the training "
                   "after its step, checkpointed; see `warpnerf view`), and after it: the "
                   "finished run until Ctrl-C (see --viewer-wait)")  # fmt: skip
    p.add_argument("--viewer-wait", action=argparse.BooleanOptionalAction, default=None,
                   help="with --viewer: once training ends, keep serving the finished run until "
                   "Ctrl-C (--viewer-wait) or close the viewer and exit (--no-viewer-wait); "
                   "default: wait when stdin is a terminal (someone can press Ctrl-C), exit "
                   "otherwise (scripts, pipes, CI, tests)")  # fmt: skip
    _host_port_flags(p, "--viewer-port")


def tensorboard_every(args) -> int:
    """The `tensorboard` argument of the trainers: a record every N steps, 0 for none."""
    return args.log_every if args.tensorboard else 0


def check_port(port: int) -> None:
    if not 0 < port < 65536:
        raise UserError(f"--port must be in 1..65535, got {port}")


def viewer_waits(args) -> bool:
    """Whether `train ... --viewer` keeps serving the finished run until Ctrl-C:
    --viewer-wait / --no-viewer-wait, else when stdin is a terminal. (nerfstudio waits
    always; here a command whose stdin is no terminal (a script, a pipe, CI, a test) has nobody
    to press Ctrl-C and must not hang.)"""
    wait = getattr(args, "viewer_wait", None)
    if wait is not None:
        return bool(wait)
    try:
        return sys.stdin is not None and sys.stdin.isatty()
    except (AttributeError, ValueError, OSError):  # (closed, or a replaced stdin)
        return False


def live_hooks(args, log=print) -> list:
    """The hooks of `train ... --viewer` (none without it); the viewer's hook is also kept as
    ``args.live_viewer`` for :func:`viewer_after_training`."""
    if not getattr(args, "viewer", False):
        return []
    from ..viewer import LiveViewer

    check_port(args.port)
    hook = LiveViewer(args.out, host=args.host, port=args.port, log=log, keep=viewer_waits(args))
    args.live_viewer = hook
    return [hook]


@contextlib.contextmanager
def viewer_after_training(args, exit_after: float | None = None):
    """Around a `train` command: once it has succeeded (its result printed), a --viewer that
    waits (:func:`viewer_waits`) keeps serving the finished run until Ctrl-C or SIGTERM, then
    the command exits 0; a failed or stopped training closes the viewer at once. A viewer that
    does not wait says so (stderr: stdout's last line stays the command's JSON)."""
    try:
        yield
    except BaseException:
        hook = getattr(args, "live_viewer", None)
        if hook is not None:
            hook.shutdown()
        raise
    hook = getattr(args, "live_viewer", None)
    if hook is None or hook.url is None:  # no --viewer, or a run that never started
        return
    if hook.viewer is None:
        if getattr(args, "viewer_wait", None) is None:  # (the default chose not to wait)
            print("training finished; the viewer closed (stdin is not a terminal; "
                  "--viewer-wait keeps it serving the finished run)", file=sys.stderr)  # fmt: skip
        return
    print(f"training finished; the viewer keeps serving {args.out} at {hook.url} "
          "\N{EM DASH} Ctrl-C to exit", file=sys.stderr, flush=True)  # fmt: skip
    viewer = hook.viewer
    hook.serve_finished(exit_after)
    print(f"viewer: stopped after {viewer.frames} frames", file=sys.stderr, flush=True)
    _leave_if_stuck(viewer)


def _leave_if_stuck(viewer) -> None:
    """After closing: a frame stuck in one native call (e.g. a kernel compiling) would make the
    interpreter's teardown wait for it or abort under it; leave at once (exit 0)."""
    if viewer.rendering():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)


def cmd_view(args) -> int:
    from ..viewer import Viewer, load_scene

    check_port(args.port)
    check_existing(args.run)
    scene = load_scene(args.run, parse_device(args.device) if args.device else None, args.mesh)
    viewer = Viewer(
        scene, host=args.host, port=args.port, run=args.run,
        max_resolution=args.max_resolution, frame_seconds=args.frame_ms / 1e3,
    )  # fmt: skip
    try:
        print(f"warpnerf view: {viewer.url} (Ctrl-C stops)", flush=True)
    except BaseException:
        viewer.close()
        raise
    viewer.serve_until_stopped(args.exit_after)  # Ctrl-C, SIGTERM: stop in order (closes it)
    print(f"warpnerf view: stopped after {viewer.frames} frames", flush=True)
    _leave_if_stuck(viewer)
    return 0
