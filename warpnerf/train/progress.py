"""The progress of the commands that take a while (render, eval, mesh, export): the training
loop's tqdm bar, one updating line on stderr, when stderr is a terminal; otherwise (a log file, a
pipe, a CI job) a line every ``every`` seconds in the same format, so that a long command is
seen to move without filling a log with redraws. Nothing on stdout: the commands' JSON result
stays the last line there. ``enabled=False`` (``--quiet``) shows nothing.

    with Progress(40, "render", unit="frame", enabled=not quiet) as bar:
        for f in range(40):
            ...
            bar.update()
"""

from __future__ import annotations

import sys
import time

__all__ = ["Progress", "PERIODIC_SECONDS"]

PERIODIC_SECONDS = 10.0  # not a terminal: a line at most this often


class Progress:
    """A progress display of ``total`` units of work (see the module's text); a context manager,
    closed on leaving (a periodic display then prints its last line, if it printed any).
    ``stream``: default stderr; ``terminal``: default whether ``stream`` is a terminal;
    ``every``: the periodic lines' spacing in seconds (default :data:`PERIODIC_SECONDS`)."""

    def __init__(self, total: int, desc: str, unit: str = "it", enabled: bool = True,
                 stream=None, every: float | None = None, terminal: bool | None = None,
                 unit_scale: bool = False):  # fmt: skip
        self.total, self.desc, self.unit, self.unit_scale = int(total), desc, unit, unit_scale
        self.stream = sys.stderr if stream is None else stream
        self.every = PERIODIC_SECONDS if every is None else float(every)
        self.n, self.lines = 0, 0
        self.t0 = self._last = time.perf_counter()
        self._bar = None
        self.enabled = bool(enabled) and self.total > 0
        if not self.enabled:
            return
        if terminal is None:
            try:
                terminal = self.stream.isatty()
            except (AttributeError, ValueError, OSError):
                terminal = False
        if terminal:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=desc, unit=unit, file=self.stream,
                             unit_scale=unit_scale)  # fmt: skip

    def update(self, n: int = 1) -> None:
        if not self.enabled:
            return
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
            return
        now = time.perf_counter()
        if now - self._last >= self.every and self.n < self.total:
            self._last = now
            self._line(now)

    def text(self, now: float | None = None) -> str:
        """The periodic line: tqdm's own meter (desc, percentage, n/total, elapsed<left, rate)."""
        from tqdm import tqdm

        now = time.perf_counter() if now is None else now
        return tqdm.format_meter(self.n, self.total, now - self.t0, prefix=self.desc,
                                 unit=self.unit, ncols=0, unit_scale=self.unit_scale)  # fmt: skip

    def counting(self, fn):
        """``fn`` (one argument, a tensor or array of rows: points, rays) that also counts its
        argument's rows as done (marching cubes' grid evaluated in chunks, say)."""

        def counted(x, *args, **kw):
            out = fn(x, *args, **kw)
            self.update(len(x))
            return out

        return counted

    def _line(self, now: float) -> None:
        self.lines += 1
        print(self.text(now), file=self.stream, flush=True)

    def close(self) -> None:
        if not self.enabled:
            return
        self.enabled = False
        if self._bar is not None:
            self._bar.close()
        elif self.lines:  # the periodic display's last line: where it stopped, and in how long
            self._line(time.perf_counter())

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
