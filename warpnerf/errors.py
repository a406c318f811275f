"""User-facing errors: the CLI prints their message (no traceback) and exits with status 2."""


class UserError(Exception):
    """A mistake in the user's input (file, field, flag); the message says what and where."""


class Interrupted(Exception):
    """Training stopped by SIGINT/SIGTERM after saving a checkpoint at ``step``; the CLI exits
    with 128 + signum."""

    def __init__(self, signum: int, step: int, run):
        import signal

        self.signum, self.step, self.run = signum, step, run
        name = signal.Signals(signum).name
        super().__init__(
            f"{name} at step {step}: checkpoint saved in {run}; continue with "
            f"`warpnerf train ... --out {run} --resume --iters N`"
        )
