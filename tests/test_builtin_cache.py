"""The built-in scene's disk cache (warpnerf/data/builtin_cache.py): made once, served from the
cache after, equal to a fresh render, and robust to whatever is found in the cache folder."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch

from warpnerf.data import builtin_cache as bc
from warpnerf.data import load_dataset, synthetic

# the real generator of the built-in scene at small settings (the commands' own: 64 + 4 views)
SMALL = {"n_train": 6, "n_val": 2, "size": 8}
KEY = {"what": "test", "n": 3}
SPEC = {"a": ((3, 4), "float32", 0.0, 1.0), "b": ((5,), "int64", None, None)}


def _arrays():
    rng = np.random.default_rng(0)
    return {"a": rng.random((3, 4), dtype=np.float32), "b": np.arange(5, dtype=np.int64)}


class Maker:
    """``make`` for cached_arrays that counts its calls."""

    def __init__(self):
        self.calls = 0

    def __call__(self):
        self.calls += 1
        return _arrays()


@pytest.fixture
def cache(tmp_path, monkeypatch):
    folder = tmp_path / "cache"
    monkeypatch.setenv(bc.ENV, str(folder))
    return folder


def _scene(**settings):
    """The built-in scene's images through the disk cache (not the in-process lru_cache)."""
    train, val = synthetic.make_synthetic_dataset.__wrapped__(**{**SMALL, **settings})
    return train.images, val.images


def _no_render(*a, **k):
    raise AssertionError("rendered again instead of reading the cache")


def _entry(folder):
    (path,) = folder.glob("builtin-*.npz")
    return path


def test_cache_folder_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(bc.ENV, str(tmp_path / "c"))
    assert bc.cache_dir() == tmp_path / "c"
    for off in ("off", "0", "OFF", "none"):
        monkeypatch.setenv(bc.ENV, off)
        assert bc.cache_dir() is None
    monkeypatch.delenv(bc.ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert bc.cache_dir() == tmp_path / "xdg" / "warpnerf"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert bc.cache_dir() == tmp_path / "home" / ".cache" / "warpnerf"


def test_the_test_session_never_uses_the_real_cache():
    """conftest.py points the whole session (and its subprocesses) at a temporary folder."""
    folder = os.environ.get(bc.ENV)
    assert folder and os.path.isabs(folder)
    assert not folder.startswith(os.path.expanduser("~/.cache"))


def test_second_load_is_served_from_the_cache_and_equals_a_fresh_render(cache, monkeypatch):
    t0 = time.perf_counter()
    train, val = _scene()
    t_make = time.perf_counter() - t0
    assert len(list(cache.glob("builtin-*.npz"))) == 1
    with monkeypatch.context() as m:
        m.setattr(synthetic, "render_views", _no_render)
        t0 = time.perf_counter()
        train2, val2 = _scene()
        t_read = time.perf_counter() - t0
    assert t_read < t_make / 5, (t_read, t_make)
    assert torch.equal(train2, train) and torch.equal(val2, val)
    assert train.shape == (6, 8, 8, 3) and train.dtype == torch.float32

    monkeypatch.setenv(bc.ENV, "off")  # a fresh render, no cache at all
    fresh_train, fresh_val = _scene()
    assert torch.equal(fresh_train, train) and torch.equal(fresh_val, val)
    assert len(list(cache.glob("builtin-*.npz"))) == 1


def test_commands_load_the_builtin_scene_from_the_cache(cache, monkeypatch):
    """What eval, render, export and view load (load_dataset's built-in format) in a new process
    (here: with the in-process cache cleared) comes from the disk cache."""
    synthetic.make_synthetic_dataset.cache_clear()
    first = load_dataset("builtin", "val", builtin_size=4)
    synthetic.make_synthetic_dataset.cache_clear()
    with monkeypatch.context() as m:
        m.setattr(synthetic, "render_views", _no_render)
        again = load_dataset("builtin", "val", builtin_size=4)
        train = load_dataset("builtin", "train", builtin_size=4, max_images=3, uint8=True)
    synthetic.make_synthetic_dataset.cache_clear()
    assert torch.equal(again.images, first.images) and first.images.shape == (4, 4, 4, 3)
    assert train.images.dtype == torch.uint8 and train.images.shape == (3, 4, 4, 3)


@pytest.mark.slow
def test_the_default_size_is_much_faster_from_the_cache(cache, cli_launches):
    """The commands' built-in scene (64 + 4 views of 48 x 48): rendered once (as the commands
    render it on the CPU, one lane per block), then read."""
    t0 = time.perf_counter()
    made = synthetic.make_synthetic_dataset.__wrapped__()
    t_make = time.perf_counter() - t0
    t0 = time.perf_counter()
    read = synthetic.make_synthetic_dataset.__wrapped__()
    t_read = time.perf_counter() - t0
    assert torch.equal(read[0].images, made[0].images)
    assert t_read < t_make / 20, (t_read, t_make)


def test_the_key_holds_every_setting(cache):
    p = bc.entry_path(cache, "builtin", KEY)
    assert p == bc.entry_path(cache, "builtin", dict(reversed(KEY.items())))
    assert p != bc.entry_path(cache, "builtin", {**KEY, "n": 4})
    assert p != bc.entry_path(cache, "other", KEY)
    _scene(size=4)
    _scene(size=5)
    _scene(size=4, view_dependent=False)
    assert len(list(cache.glob("builtin-*.npz"))) == 3


def test_generic_cache_round_trip(cache):
    make = Maker()
    first = bc.cached_arrays("t", KEY, SPEC, make)
    second = bc.cached_arrays("t", KEY, SPEC, make)
    assert make.calls == 1
    for k, a in _arrays().items():
        assert np.array_equal(first[k], a) and np.array_equal(second[k], a)
        assert second[k].dtype == a.dtype and second[k].flags.writeable
    assert [p.name for p in cache.iterdir()] == [bc.entry_path(cache, "t", KEY).name]  # no temps


def _flip_byte(path):
    data = bytearray(path.read_bytes())
    i = data.index(b"b.npy")  # a byte inside array a's data (just before b's member)
    data[i - 40] ^= 0x01
    path.write_bytes(bytes(data))


def _npz(path, meta_sums=True, compressed=False, **arrays):
    """Writes an entry file by hand (for tampering): ``arrays`` with a meta of the right key and,
    when ``meta_sums``, their right checksums."""
    import hashlib

    meta = {
        "key": json.loads(bc._key_json("t", KEY)),
        "sha256": {
            k: hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest() if meta_sums else "x"
            for k, a in arrays.items()
        },
    }
    raw = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    (np.savez_compressed if compressed else np.savez)(path, meta=raw, **arrays)


TAMPERINGS = {
    "flipped byte": _flip_byte,
    "truncated": lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]),
    "empty": lambda p: p.write_bytes(b""),
    "not a zip": lambda p: p.write_bytes(b"\x93NUMPY" + b"\0" * 200),
    "too large": lambda p: p.write_bytes(p.read_bytes() + b"\0" * (1 << 20)),
    "wrong shape": lambda p: _npz(p, a=np.zeros((4, 3), np.float32), b=np.arange(5)),
    "wrong dtype": lambda p: _npz(p, a=np.zeros((3, 4), np.float64), b=np.arange(5)),
    "out of range": lambda p: _npz(p, a=np.full((3, 4), 2.0, np.float32), b=np.arange(5)),
    "nan": lambda p: _npz(p, a=np.full((3, 4), np.nan, np.float32), b=np.arange(5)),
    "wrong checksum": lambda p: _npz(p, meta_sums=False, **_arrays()),
    "compressed": lambda p: _npz(p, compressed=True, **_arrays()),
    "extra member": lambda p: _npz(p, c=np.zeros(1), **_arrays()),
    "pickled": lambda p: _npz(p, a=np.array([{"x": 1}], dtype=object), b=np.arange(5)),
}


@pytest.mark.parametrize("how", list(TAMPERINGS))
def test_a_tampered_entry_is_made_again(cache, how):
    make = Maker()
    bc.cached_arrays("t", KEY, SPEC, make)
    path = bc.entry_path(cache, "t", KEY)
    TAMPERINGS[how](path)
    assert bc.read_entry(cache, "t", KEY, SPEC) is None
    out = bc.cached_arrays("t", KEY, SPEC, make)
    assert make.calls == 2
    assert all(np.array_equal(out[k], a) for k, a in _arrays().items())
    assert bc.read_entry(cache, "t", KEY, SPEC) is not None  # replaced by a valid one


def test_an_entry_of_another_key_is_not_served(cache):
    bc.cached_arrays("t", {"other": 1}, SPEC, Maker())
    os.replace(bc.entry_path(cache, "t", {"other": 1}), bc.entry_path(cache, "t", KEY))
    assert bc.read_entry(cache, "t", KEY, SPEC) is None


def test_a_symlink_in_place_of_the_entry_is_not_followed(cache, tmp_path):
    make = Maker()
    bc.cached_arrays("t", KEY, SPEC, make)
    path = bc.entry_path(cache, "t", KEY)
    target = tmp_path / "elsewhere.npz"
    os.replace(path, target)  # a valid entry, but reached through a link
    before = target.read_bytes()
    path.symlink_to(target)
    assert bc.read_entry(cache, "t", KEY, SPEC) is None
    bc.cached_arrays("t", KEY, SPEC, make)
    assert make.calls == 2
    assert not path.is_symlink() and path.is_file()  # the link replaced, not written through
    assert target.read_bytes() == before


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")
def test_a_fifo_in_place_of_the_entry_does_not_hang(cache):
    cache.mkdir()
    path = bc.entry_path(cache, "t", KEY)
    os.mkfifo(path)
    done = []
    t = threading.Thread(
        target=lambda: done.append(bc.cached_arrays("t", KEY, SPEC, Maker())), daemon=True
    )
    t.start()
    t.join(20)
    assert done, "reading a FIFO in the cache hung"
    assert path.is_file() and bc.read_entry(cache, "t", KEY, SPEC) is not None


def test_a_folder_in_place_of_the_entry_falls_back(cache, capsys):
    bc.entry_path(cache, "t", KEY).mkdir(parents=True)
    make = Maker()
    out = bc.cached_arrays("t", KEY, SPEC, make)
    assert np.array_equal(out["a"], _arrays()["a"]) and make.calls == 1
    assert [p.name for p in cache.iterdir()] == [bc.entry_path(cache, "t", KEY).name]


def test_an_unwritable_cache_falls_back_in_memory(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv(bc.ENV, str(blocker / "cache"))  # mkdir fails, even for root
    make = Maker()
    for _ in range(2):
        out = bc.cached_arrays("t", KEY, SPEC, make)
        assert np.array_equal(out["b"], np.arange(5))
    assert make.calls == 2
    err = capsys.readouterr().err
    assert err.count("note:") == 1 and "not writable" in err  # one line, once
    train, _ = _scene()  # the built-in scene too
    assert train.shape == (6, 8, 8, 3)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes anywhere")
def test_a_read_only_cache_folder_falls_back(cache):
    cache.mkdir()
    cache.chmod(0o555)
    try:
        make = Maker()
        bc.cached_arrays("t", KEY, SPEC, make)
        bc.cached_arrays("t", KEY, SPEC, make)
        assert make.calls == 2 and not list(cache.iterdir())
    finally:
        cache.chmod(0o755)


def test_a_full_disk_falls_back_and_leaves_no_temporary_file(cache, monkeypatch):
    def full(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(bc.os, "fsync", full)
    out = bc.cached_arrays("t", KEY, SPEC, Maker())
    assert np.array_equal(out["a"], _arrays()["a"])
    assert list(cache.iterdir()) == []


def test_concurrent_threads_end_with_a_valid_entry(cache):
    outs, errors = [], []

    def work():
        try:
            outs.append(bc.cached_arrays("t", KEY, SPEC, Maker()))
        except Exception as e:  # noqa: BLE001
            errors.append(e)

    threads = [threading.Thread(target=work) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert not errors and len(outs) == 8
    assert all(np.array_equal(o["a"], _arrays()["a"]) for o in outs)
    assert bc.read_entry(cache, "t", KEY, SPEC) is not None
    assert [p.name for p in cache.iterdir()] == [bc.entry_path(cache, "t", KEY).name]


_CHILD = """
import os, sys, time
import numpy as np
from warpnerf.data import builtin_cache as bc

def make():  # both processes miss the cache, make the entry and write it at the same time
    open(sys.argv[1] + ".ready", "w").close()
    while not os.path.exists(sys.argv[2]):
        time.sleep(0.01)
    return {"images": np.random.default_rng(0).random((64, 48, 48, 3), dtype=np.float32)}

spec = {"images": ((64, 48, 48, 3), "float32", 0.0, 1.0)}
out = bc.cached_arrays("race", {"n": 1}, spec, make)
np.save(sys.argv[1], out["images"])
"""


def test_two_processes_making_an_entry_at_once_end_valid(cache, tmp_path):
    go = tmp_path / "go"
    outs = [tmp_path / f"out{i}.npy" for i in range(2)]
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _CHILD, str(o), str(go)],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        for o in outs
    ]
    try:
        deadline = time.monotonic() + 60
        while not all(o.with_name(o.name + ".ready").exists() for o in outs):
            assert time.monotonic() < deadline and all(p.poll() is None for p in procs)
            time.sleep(0.01)
        go.touch()
        for p in procs:
            out, _ = p.communicate(timeout=60)
            assert p.returncode == 0, out.decode()
    finally:
        for p in procs:
            p.kill()
    a, b = (np.load(o) for o in outs)
    assert np.array_equal(a, b)
    spec = {"images": ((64, 48, 48, 3), "float32", 0.0, 1.0)}
    hit = bc.read_entry(cache, "race", {"n": 1}, spec)
    assert hit is not None and np.array_equal(hit["images"], a)
    assert [p.name for p in cache.iterdir()] == [bc.entry_path(cache, "race", {"n": 1}).name]


def _scene_key_spec():
    """The cache key and spec of the scene at the tests' settings, on the CPU."""
    return synthetic.cache_entry(6, 2, 8, True, 256, "cpu")


def test_a_tampered_scene_entry_is_rendered_again(cache, monkeypatch):
    train, _ = _scene()
    path = _entry(cache)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the train images
    path.write_bytes(bytes(data))
    assert bc.read_entry(cache, "builtin", *_scene_key_spec()) is None
    renders = []
    real = synthetic.render_views
    monkeypatch.setattr(
        synthetic, "render_views", lambda *a, **k: renders.append(1) or real(*a, **k)
    )
    train2, _ = _scene()
    assert renders and torch.equal(train2, train)
    assert bc.read_entry(cache, "builtin", *_scene_key_spec()) is not None
