"""`warpnerf view RUN`: the web viewer on a local port; and the flags that watch a training
(`--viewer`, `--no-tensorboard`)."""

from __future__ import annotations

import os
import sys
import threading
import time

from ..errors import UserError
from ..options import number_type
from ._common import _device, _existing, _positive


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
    v.add_argument("--frame-ms", type=_positive(float), default=100.0,
                   help="render time aimed at while the camera moves (default 100 ms)")  # fmt: skip
    v.add_argument("--exit-after", type=_positive(float), default=None, metavar="S",
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
        type=_positive(int),
        default=10,
        metavar="N",
        help="TensorBoard: scalars every N steps (default 10; history.json has all)",
    )
    p.add_argument("--viewer", action="store_true", help="serve the web viewer during "
                   "training (frames render between steps; Ctrl-C still stops the training "
                   "after its step, checkpointed; see `warpnerf view`)")  # fmt: skip
    _host_port_flags(p, "--viewer-port")


def tensorboard_every(args) -> int:
    """The `tensorboard` argument of the trainers: a record every N steps, 0 for none."""
    return args.log_every if args.tensorboard else 0


def check_port(port: int) -> None:
    if not 0 < port < 65536:
        raise UserError(f"--port must be in 1..65535, got {port}")


def live_hooks(args, log=print) -> list:
    """The hooks of `train ... --viewer` (none without it)."""
    if not getattr(args, "viewer", False):
        return []
    from ..viewer import LiveViewer

    check_port(args.port)
    return [LiveViewer(args.out, host=args.host, port=args.port, log=log)]


def cmd_view(args) -> int:
    from ..viewer import Viewer, load_scene
    from ..viewer.server import signals_to

    check_port(args.port)
    _existing(args.run)
    scene = load_scene(args.run, _device(args.device) if args.device else None, args.mesh)
    stop = threading.Event()
    viewer = Viewer(
        scene, host=args.host, port=args.port, run=args.run,
        max_resolution=args.max_resolution, frame_seconds=args.frame_ms / 1e3,
    )  # fmt: skip
    try:
        with signals_to(lambda *_: stop.set()):  # Ctrl-C, SIGTERM: stop in order
            print(f"warpnerf view: {viewer.url} (Ctrl-C stops)", flush=True)
            t0 = time.perf_counter()
            while not stop.wait(0.1):
                if args.exit_after is not None and time.perf_counter() - t0 >= args.exit_after:
                    break
    finally:
        viewer.close()
    print(f"warpnerf view: stopped after {viewer.frames} frames", flush=True)
    if viewer.rendering():  # a frame stuck in one native call (e.g. a kernel compiling): the
        sys.stdout.flush()  # interpreter's teardown would wait for it or abort under it
        sys.stderr.flush()
        os._exit(0)
    return 0
