"""Reading untrusted JSON files (transforms files, SDF scenes, run configs) and checking the
fields of a JSON object against a dataclass, with one-line :class:`UserError` messages that name
the file, the field and the expected form.

``read_json`` turns every way a file can fail into a UserError naming the file: missing or
unreadable (OSError), a FIFO, device or folder (never opened blocking; a link too, inside a run
folder), larger than its kind holds (:data:`JSON_LIMITS`: parsing costs up to ~30x a file's size
in memory, so each kind is bounded by what a valid file of it can hold), not UTF-8, not JSON, and
nested deeper than :data:`MAX_JSON_DEPTH` levels (deeper than Python's parser allows, ``'[' *
100000``, raises RecursionError in :func:`json.loads`; a few hundred levels parse but break the
code that walks or rewrites the value later).
"""

from __future__ import annotations

import contextlib
import copy
import json
import math
import os
import reprlib
import stat
import typing
from pathlib import Path

from .errors import UserError

__all__ = ["read_json", "read_run_config", "one_read_per_command", "check_fields", "field_error",
           "is_device", "show", "MAX_JSON_BYTES", "JSON_LIMITS", "MAX_JSON_DEPTH",
           "MAX_INT"]  # fmt: skip

MAX_JSON_BYTES = 64 << 20  # 64 MiB: a JSON file of a kind not in JSON_LIMITS
# bytes a JSON file of each kind may hold (its ``what`` in read_json), each far above the largest
# valid file of that kind: a run's config (~2 KB; a capture's list of unregistered images is all
# that grows), its run record (256 sessions of ~1-2 KB), a camera path (1000 keyframes, ~1 MB as
# warpnerf writes it), an SDF scene (primitives of ~200 bytes), a dataset's transforms file
# (~1 KB a frame: ~60,000 frames)
JSON_LIMITS = {
    "run config": 16 << 20,
    "run record": 8 << 20,
    "camera path": 4 << 20,
    "JSON scene": 4 << 20,
    "transforms file": 64 << 20,
}
MAX_JSON_DEPTH = 32  # nesting levels; the deepest valid input (a camera path) has 5
_IN_RUN = ("run config", "run record")  # files of a run folder: a link there is not followed
MAX_INT = 2**31  # integer fields (counts, sizes, seeds) stay below this (int32 kernels, seeds)

_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 40
_repr.maxlist = _repr.maxdict = 4
_repr.maxlevel = 2


def show(v) -> str:
    """A short repr of ``v`` for an error message (bounded in length and depth)."""
    return _repr.repr(v)


def read_json(path, what: str = "JSON file", max_bytes: int | None = None):
    """The parsed content of the JSON file ``path`` (any JSON value), or a UserError naming the
    file and ``what`` it should be (e.g. "transforms file", "run config"). ``max_bytes``: the
    kind's limit in :data:`JSON_LIMITS` (or :data:`MAX_JSON_BYTES`) unless given."""
    from .safe_writes import read_input

    path = Path(path)
    limit = max_bytes if max_bytes is not None else JSON_LIMITS.get(what, MAX_JSON_BYTES)
    try:
        data = read_input(path, what, limit, follow=what not in _IN_RUN)
    except OSError as e:  # permissions, I/O errors
        raise UserError(f"{path}: not a readable {what} (cannot read: {e.strerror or e})") from None
    try:
        value = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text: {e.reason})") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON for the {what} (nested too deeply)") from None
    except ValueError as e:  # JSONDecodeError; integers of more than 4300 digits
        raise UserError(f"{path}: not valid JSON ({str(e)[:200]})") from None
    if _deeper_than(value, MAX_JSON_DEPTH):
        raise UserError(
            f"{path}: not valid JSON for the {what} (nested deeper than {MAX_JSON_DEPTH} levels)"
        )
    return value


_RUN_CONFIGS: dict | None = None  # inside one_read_per_command: the run configs read, by file


@contextlib.contextmanager
def one_read_per_command():
    """While this holds (a ``warpnerf`` command), :func:`read_run_config` reads each run's
    config.json from the disk once: the resume checks, the method registry and the run's
    loader ask for the same file, and get copies of the one read. A file replaced meanwhile
    (another inode, size or time) is read again."""
    global _RUN_CONFIGS
    outer, _RUN_CONFIGS = _RUN_CONFIGS, {} if _RUN_CONFIGS is None else _RUN_CONFIGS
    try:
        yield
    finally:
        _RUN_CONFIGS = outer


def read_run_config(path):
    """A run folder's config.json ``path`` parsed (any JSON value: the callers check its form),
    with :func:`read_json`'s bounds and one-line errors; read once per command (see
    :func:`one_read_per_command`), each caller getting its own copy."""
    path = Path(path)
    key = None
    if _RUN_CONFIGS is not None:
        try:
            st = os.lstat(path)
        except OSError:
            st = None
        if st is not None and stat.S_ISREG(st.st_mode):  # (others: read_json names them)
            key = (str(path.absolute()), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
    if key is None:
        return read_json(path, "run config")
    if key not in _RUN_CONFIGS:
        _RUN_CONFIGS[key] = read_json(path, "run config")
    return copy.deepcopy(_RUN_CONFIGS[key])


def _deeper_than(value, limit: int) -> bool:
    """Whether lists and objects nest more than ``limit`` levels in ``value`` (no recursion)."""
    stack = [(value, 1)] if isinstance(value, (list, dict)) else []
    while stack:
        v, depth = stack.pop()
        if depth > limit:
            return True
        items = v.values() if isinstance(v, dict) else v
        stack.extend((x, depth + 1) for x in items if isinstance(x, (list, dict)))
    return False


def _expected(hint) -> tuple[tuple, bool]:
    """(allowed base types, None allowed) of a field's annotation (int, float, bool, str, dict,
    list, each optionally ``| None``)."""
    args = typing.get_args(hint) or (hint,)
    return tuple(a for a in args if a is not type(None)), type(None) in args


def _form(types: tuple, optional: bool) -> str:
    names = {int: "an integer", float: "a finite number", bool: "true or false", str: "a string",
             dict: "an object", list: "a list", tuple: "a list"}  # fmt: skip
    text = " or ".join(names.get(t, t.__name__) for t in types)
    return text + (" or null" if optional else "")


def _check_value(v, types: tuple) -> object:
    """``v`` (ints as floats for float fields) when it has one of ``types``, else raises
    ValueError. Booleans are not numbers here (``bool`` is a subclass of ``int``)."""
    for t in types:
        if t is bool and type(v) is bool:
            return v
        if t is int and type(v) is int and -MAX_INT < v < MAX_INT:
            return v
        if t is float and type(v) in (int, float) and math.isfinite(v):
            return float(v)
        if t in (str, dict, list) and type(v) is t:
            return v
    raise ValueError


def check_fields(cls, d, where: str) -> dict:
    """The JSON object ``d`` checked against the dataclass ``cls``: no unknown field names, and
    every value of the annotated type (int, float, bool, str, dict, ..., optionally None;
    integers within +-2^31, floats finite). Returns the fields as keyword arguments for ``cls``;
    UserError naming ``where`` and the field otherwise."""
    if not isinstance(d, dict):
        raise UserError(f"{where}: expected a JSON object of settings, got {type(d).__name__}")
    hints = typing.get_type_hints(cls)
    names = [f for f in cls.__dataclass_fields__ if f in hints]
    unknown = sorted(str(k) for k in d if k not in names)
    if unknown:
        raise UserError(f"{where}: unknown field(s) {show(unknown)} (not settings of this kind)")
    out = {}
    for name in names:
        if name not in d:
            continue
        types, optional = _expected(hints[name])
        v = d[name]
        if v is None and optional:
            out[name] = None
            continue
        try:
            out[name] = _check_value(v, types)
        except ValueError:
            bound = " in (-2^31, 2^31)" if int in types else ""
            raise UserError(
                f"{where}: field '{name}' must be {_form(types, optional)}{bound}, got {show(v)}"
            ) from None
    return out


def field_error(where: str | None, name: str, rule: str) -> UserError:
    """The error for a setting ``name`` that breaks ``rule`` ("must be >= 1, got 0"): naming the
    command-line flag (``--name-with-dashes``) when ``where`` is None (the settings came from the
    command line), else the file ``where`` and the config field."""
    if where is None:
        return UserError(f"--{name.replace('_', '-')} {rule}")
    return UserError(f"{where}: field '{name}' {rule}")


def is_device(v) -> bool:
    """Whether ``v`` names a device a run may be saved with: "cpu", "cuda" or "cuda:N"."""
    return isinstance(v, str) and (v in ("cpu", "cuda") or (v[:5] == "cuda:" and v[5:].isdigit()))
