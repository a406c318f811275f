"""Shared fixtures: a ``device`` fixture over cpu and cuda, fixed seeds for every test, ``fifo``
(a FIFO that fails the test instead of hanging it) and ``cli_launches`` (Warp's CPU launches as
the command makes them); the session runs torch on one CPU thread (see ``pytest_configure``)."""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import threading
import time

import pytest
import torch
import warp as wp

from ._launches import cli_cpu_launches

# CPU launches honour the block width, so the cooperative (tiled) kernels run their real multi-lane
# code on the CPU too, not the one-lane degenerate walk Warp uses on CPUs by default.
wp.config.enable_cpu_blocks = True

_NO_CUDA = "CUDA not available (torch.cuda.is_available() is False): cuda variant skipped"


@pytest.fixture(params=["cpu", "cuda"])
def device(request) -> torch.device:
    """Every kernel test runs on the CPU and, when there is one, on a CUDA GPU."""
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip(_NO_CUDA)
    return torch.device(request.param)


def pytest_configure(config) -> None:
    """The session's disk cache (the built-in scene's images) is a temporary folder, never the
    user's ~/.cache; subprocesses of tests inherit it through the environment. Set before
    collection, so even a test module's import-time use of the built-in scene goes there.

    torch runs on one CPU thread, here and (through OMP_NUM_THREADS) in the tests' subprocesses,
    unless OMP_NUM_THREADS is set already: the tests' tensors are tiny, and on a 2-core machine
    torch's second intra-op thread made each small op wait for it, most of all after Warp's
    single-threaded CPU kernels and whenever anything else ran (tests/test_nerf.py: 576 s with
    the default 2 threads against 102 s with one, load about 3, 2026-12-02). One thread also
    keeps the suite's floats independent of the machine's core count (docs/DETERMINISM.md:
    torch's CPU sums depend on the thread count)."""
    folder = tempfile.mkdtemp(prefix="wn-cache-")
    config._warpnerf_cache = (os.environ.get("WARPNERF_CACHE"), folder)
    os.environ["WARPNERF_CACHE"] = folder
    if "OMP_NUM_THREADS" not in os.environ:
        config._warpnerf_threads = torch.get_num_threads()
        os.environ["OMP_NUM_THREADS"] = "1"
        torch.set_num_threads(1)


def pytest_unconfigure(config) -> None:
    threads = getattr(config, "_warpnerf_threads", None)
    if threads is not None:
        os.environ.pop("OMP_NUM_THREADS", None)
        torch.set_num_threads(threads)
    old, folder = getattr(config, "_warpnerf_cache", (None, None))
    if folder is None:
        return
    if old is None:
        os.environ.pop("WARPNERF_CACHE", None)
    else:
        os.environ["WARPNERF_CACHE"] = old
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def cli_launches():
    """Warp's CPU launches as ``warpnerf`` makes them outside the tests (one lane per block) for
    the test: the long convergence and end-to-end runs (tests/_launches.py says why)."""
    with cli_cpu_launches():
        yield


@pytest.fixture
def fifo():
    """``fifo(path)`` makes a FIFO at ``path`` (replacing a file there) and watches it: a command
    that blocks opening it (the open waits for a writer forever, and no signal reaches a blocked
    open in a worker thread) is released after 30 s by opening the other end, and the test
    fails."""
    paths, stop, hung = [], threading.Event(), []

    def watch():
        t0 = time.monotonic()
        while not stop.wait(0.2):
            if time.monotonic() - t0 < 30:
                continue
            for p in paths:
                with contextlib.suppress(OSError):  # ENXIO: nobody is reading it
                    os.close(os.open(p, os.O_WRONLY | os.O_NONBLOCK))
                    hung.append(p)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()

    def make(path):
        if os.path.lexists(path):
            os.unlink(path)
        os.mkfifo(path)
        paths.append(path)
        return path

    yield make
    stop.set()
    thread.join()
    assert not hung, f"the command hung opening the FIFO {hung[0]}"


@pytest.fixture(autouse=True)
def _fixed_seed():
    """Each test starts from the same torch RNG state, whatever ran before it."""
    torch.manual_seed(0)
    yield


def pytest_report_header(config) -> str:
    if torch.cuda.is_available():
        return f"warpnerf kernels: testing on cpu and {torch.cuda.get_device_name(0)}"
    return f"warpnerf kernels: testing on cpu only; {_NO_CUDA}"
