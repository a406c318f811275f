"""Reading untrusted JSON files (transforms files, SDF scenes, run configs) and checking the
fields of a JSON object against a dataclass, with one-line :class:`UserError` messages that name
the file, the field and the expected form.

``read_json`` turns every way a file can fail into a UserError: missing or unreadable (OSError),
larger than ``MAX_JSON_BYTES``, not UTF-8, not JSON, and nested deeper than Python's parser
allows (``'[' * 100000`` raises RecursionError in :func:`json.loads`).
"""

from __future__ import annotations

import json
import math
import reprlib
import typing
from pathlib import Path

from .errors import UserError

__all__ = ["read_json", "check_fields", "field_error", "is_device", "show", "MAX_JSON_BYTES",
           "MAX_INT"]  # fmt: skip

MAX_JSON_BYTES = 64 << 20  # 64 MiB: far above any transforms file, scene or run config
MAX_INT = 2**31  # integer fields (counts, sizes, seeds) stay below this (int32 kernels, seeds)

_repr = reprlib.Repr()
_repr.maxstring = _repr.maxother = 40
_repr.maxlist = _repr.maxdict = 4
_repr.maxlevel = 2


def show(v) -> str:
    """A short repr of ``v`` for an error message (bounded in length and depth)."""
    return _repr.repr(v)


def read_json(path, what: str = "JSON file", max_bytes: int = MAX_JSON_BYTES):
    """The parsed content of the JSON file ``path`` (any JSON value), or a UserError naming the
    file and ``what`` it should be (e.g. "transforms file", "run config")."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise UserError(f"{path}: no such file (expected the {what})") from None
    except OSError as e:  # permissions, a folder named like the file, I/O errors
        raise UserError(f"{path}: not a readable {what} (cannot read: {e.strerror or e})") from None
    if len(data) > max_bytes:
        raise UserError(
            f"{path}: the {what} is larger than {max_bytes >> 20} MiB; not a JSON file of this kind"
        )
    try:
        return json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        raise UserError(f"{path}: not valid JSON (not UTF-8 text: {e.reason})") from None
    except RecursionError:
        raise UserError(f"{path}: not valid JSON for the {what} (nested too deeply)") from None
    except ValueError as e:  # JSONDecodeError; integers of more than 4300 digits
        raise UserError(f"{path}: not valid JSON ({str(e)[:200]})") from None


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
