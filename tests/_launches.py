"""How the tests launch Warp's cooperative kernels on the CPU.

tests/conftest.py turns ``wp.config.enable_cpu_blocks`` on, so the tiled kernels run their real
multi-lane code on the CPU (block scans, tile sums) in the tests. ``warpnerf`` itself, outside
the tests, leaves it off: a CPU launch runs each block with one lane. The long convergence and
end-to-end runs take :func:`cli_cpu_launches`: they check what a training reaches, which the
command runs with one lane, and real lanes cost 35-50 % of such a run's CPU time (the PSNR
floors of tests/test_nerf.py, the exposure run of tests/test_appearance.py; 2026-12-02), for
the same figures (the MLP's PSNR floor: 25.73 dB either way). The lanes' arithmetic stays
checked by the kernel tests (tests/test_composite_tiled.py: tiled against sequential and
float64 at block widths 4 and 32) and by every other training test."""

from __future__ import annotations

import contextlib

import warp as wp


@contextlib.contextmanager
def cli_cpu_launches():
    """CPU launches as ``warpnerf`` makes them (one lane per block) inside the block."""
    old = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = False
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = old
