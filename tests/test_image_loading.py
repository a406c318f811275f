"""Parallel image reading (data/_images.py): order, errors in order, one array."""

import threading
import time

import numpy as np
import pytest

from warpnerf.data.images import read_all
from warpnerf.errors import UserError


def test_order_and_values_whatever_the_finishing_order():
    def read_one(k):
        time.sleep(0.002 * ((7 * k) % 5))  # later items often finish first
        return np.full((2, 3, 3), float(k), dtype=np.float32)

    out = read_all(list(range(30)), read_one)  # (30: past the progress bar's threshold)
    assert out.shape == (30, 2, 3, 3) and out.dtype == np.float32
    assert np.array_equal(out[:, 0, 0, 0], np.arange(30, dtype=np.float32))


def test_first_failure_in_order_raises_and_checks_run_in_order():
    seen = []

    def read_one(k):
        if k in (3, 6):
            time.sleep(0.01 if k == 3 else 0.0)  # 6 fails first in time, 3 first in order
            raise UserError(f"bad image {k}")
        return np.zeros((1, 1, 3), np.float32) + k

    def check(j, img):
        assert threading.current_thread() is threading.main_thread()
        seen.append(j)

    with pytest.raises(UserError, match="bad image 3"):
        read_all(list(range(10)), read_one, check)
    assert seen == [0, 1, 2]


def test_a_check_stops_the_load_and_shapes_must_agree():
    def check(j, img):
        if j == 1:
            raise UserError("size differs")

    with pytest.raises(UserError, match="size differs"):
        read_all([0, 1, 2], lambda k: np.zeros((2, 2, 3), np.float32), check)
    with pytest.raises(ValueError, match="shape"):
        read_all([2, 3], lambda k: np.zeros((k, k, 3), np.float32))
