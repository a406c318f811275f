"""Task configs as the single source of defaults, help and command-line flags.

A config is a dataclass whose fields are declared with :func:`option` (default, help, flag name,
check, choices, groups). :func:`add_flags` builds the argparse flags of a config class from
those declarations (so a flag's default *is* the field's default: they cannot drift), and
:func:`from_flags` builds the config's keyword arguments back from the parsed flags. The CLI
(``warpnerf train ...``) and the demos use both; the help a flag shows is the field's.

Example::

    @dataclass
    class MyConfig:
        iters: int = option(2000, "total steps", check="positive")
        lr: float = option(1e-3, "Adam's learning rate", check="positive")

    p = argparse.ArgumentParser()
    add_flags(p, MyConfig)                # --iters, --lr with MyConfig's defaults
    cfg = MyConfig(**from_flags(MyConfig, p.parse_args()))
"""

from __future__ import annotations

import argparse
import dataclasses
import math

__all__ = [
    "option", "add_flags", "from_flags", "apply_preset", "flag_of", "number_type", "CHECKS",
    "with_defaults", "section_of", "section_declaring", "check_at_least", "Settings",
    "ReadOnlyDict", "ReadOnlyList", "read_only", "writable",
]  # fmt: skip

_AUTO = "auto"


def number_type(kind, ok, rule: str):
    """An argparse type: ``kind(text)`` (int or float) that must satisfy ``ok`` (``rule`` says
    how, in the error)."""
    noun = "an integer" if kind is int else "a number"

    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {noun}, got {text!r}") from None
        if not ok(v):
            raise argparse.ArgumentTypeError(f"must be {rule}, got {text}")
        return v

    return parse


def _size(text):
    """An argparse type: 'WxH' (positive integers) -> (W, H)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH such as 400x400, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"width and height must be positive, got {text!r}")
    return w, h


# the argparse type of each (annotation, check): what the command line accepts before the
# config's own validation (which knows the other fields) runs
CHECKS = {
    ("int", "positive"): number_type(int, lambda v: v > 0, "positive and finite"),
    ("int", "nonnegative"): number_type(int, lambda v: v >= 0, ">= 0"),
    ("int", None): number_type(int, lambda v: True, "an integer"),
    # seeds feed torch generators (64-bit) after offsets and multiplications per step: 31 bits
    ("int", "seed"): number_type(int, lambda v: 0 <= v < 2**31, "an integer in [0, 2^31)"),
    ("float", "positive"): number_type(
        float, lambda v: v > 0 and math.isfinite(v), "positive and finite"
    ),
    ("float", "nonnegative"): number_type(
        float, lambda v: v >= 0 and math.isfinite(v), "finite and >= 0"
    ),
    ("float", "finite"): number_type(float, math.isfinite, "finite"),
    ("float", None): number_type(float, math.isfinite, "finite"),
    ("str", None): str,
    ("tuple", "size"): _size,
}


def option(
    default,
    help: str = "",
    *,
    flag: str | None = _AUTO,
    check: str | None = None,
    choices=None,
    groups: tuple = (),
    negate: str | None = None,
    const=None,
    metavar: str | None = None,
    required: bool = False,
):
    """A config field: its ``default``, the ``help`` its flag shows, the ``flag`` (default
    ``--name-with-dashes``; None: not on the command line), the ``check`` of its value on the
    command line (positive, nonnegative, finite, seed, size: a type of :data:`CHECKS`; or an
    argparse type of the field's own), its ``choices``, the ``groups`` of
    commands that show it (empty: every command built from the config), and for a boolean whose
    default is True, ``negate``: the flag that turns it off (e.g. ``--fixed-beta``). ``const``:
    the flag's value may be left out, meaning ``const`` (``--clean`` = ``--clean 0.01``);
    ``metavar``: the value's name in the help; ``required``: the flag must be given."""
    meta = dict(help=help, flag=flag, check=check, choices=choices, groups=tuple(groups))
    meta.update(negate=negate, const=const, metavar=metavar, required=bool(required))
    if isinstance(default, (list, dict)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


class ReadOnlyDict(dict):
    """A frozen config's dict value (``scene``, ``field_options``): a dict to every reader
    (``isinstance``, ``==``, ``json.dumps``), but changing it in place raises TypeError. A changed
    value makes a changed config: ``dataclasses.replace(cfg, scene=dict(cfg.scene, near=1.0))``."""

    def _refuse(self, *args, **kwargs):
        raise TypeError(
            "a frozen config's values are read-only: make a changed copy (dict(value, ...)) and "
            "a changed config with dataclasses.replace"
        )

    __setitem__ = __delitem__ = __ior__ = clear = pop = popitem = setdefault = update = _refuse

    def __reduce__(self):  # (copies and pickles rebuild it whole, not item by item)
        return type(self), (dict(self),)


class ReadOnlyList(list):
    """A list inside a frozen config's value (a capture's ``transform`` rows, its NDC camera):
    a list to every reader, read-only as :class:`ReadOnlyDict`."""

    _refuse = ReadOnlyDict._refuse
    __setitem__ = __delitem__ = __iadd__ = __imul__ = _refuse
    append = extend = insert = pop = remove = clear = sort = reverse = _refuse

    def __reduce__(self):
        return type(self), (list(self),)


def read_only(value):
    """``value`` with its dicts and lists (at any depth) as read-only copies."""
    if isinstance(value, dict):
        return ReadOnlyDict({k: read_only(v) for k, v in value.items()})
    if isinstance(value, list):
        return ReadOnlyList(read_only(v) for v in value)
    return value


def writable(value):
    """``value`` with its dicts and lists (at any depth) as plain, writable copies."""
    if isinstance(value, dict):
        return {k: writable(v) for k, v in value.items()}
    if isinstance(value, list):
        return [writable(v) for v in value]
    return value


class Settings:
    """The base of a run's config: built (from flags, a preset or a saved config.json),
    resolved and checked once, then :meth:`freeze` makes it read-only: setting a field of a
    frozen config raises ``dataclasses.FrozenInstanceError``, changing one of its dict or list
    values in place (``cfg.scene["near"] = 1``) a TypeError. A changed config is a new one,
    ``dataclasses.replace(cfg, ...)`` (not frozen, its dicts and lists writable copies, to be
    checked and frozen in its turn); values that change while a run trains live on its task, not
    on its config."""

    def freeze(self):
        """Makes this config read-only, its dict and list values too (and returns it)."""
        for f in dataclasses.fields(self):
            object.__setattr__(self, f.name, read_only(getattr(self, f.name)))
        object.__setattr__(self, "_frozen", True)
        return self

    @property
    def frozen(self) -> bool:
        return self.__dict__.get("_frozen", False)

    def to_dict(self) -> dict:
        """The config as its config.json holds it (plain dicts and lists)."""
        return writable(dataclasses.asdict(self))

    def __setattr__(self, name, value):
        if self.__dict__.get("_frozen", False):
            raise dataclasses.FrozenInstanceError(
                f"cannot set {name!r}: a {type(self).__name__} is read-only once resolved and "
                "checked (make a changed copy with dataclasses.replace)"
            )
        # (a copy of a frozen config, or a value taken from one, gets writable dicts and lists)
        object.__setattr__(self, name, writable(value))

    def __delattr__(self, name):
        if self.__dict__.get("_frozen", False):
            raise dataclasses.FrozenInstanceError(f"cannot delete {name!r}: read-only config")
        object.__delattr__(self, name)


def with_defaults(cls, **changes):
    """A subclass of config section ``cls`` whose fields named in ``changes`` get another default
    (a value: the field's help and flag are kept) or another declaration (an :func:`option`).
    A section is declared once and each kind of run takes it with its own defaults, e.g.
    ``class SDFConfig(with_defaults(LoopConfig, iters=2000, ckpt_every=500))``."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(changes) - set(fields))
    if unknown:
        raise TypeError(f"{cls.__name__} has no fields {', '.join(unknown)}")
    new = []
    for name, value in changes.items():
        f = fields[name]
        if not isinstance(value, dataclasses.Field):
            meta = dict(f.metadata)
            value = option(value, meta.pop("help"), **{k: meta[k] for k in _OPTION_KEYS})
        new.append((name, f.type, value))
    return dataclasses.make_dataclass(cls.__name__, new, bases=(cls,))


_OPTION_KEYS = ("flag", "check", "choices", "groups", "negate", "const", "metavar", "required")


def section_of(cfg, cls):
    """The values of config section ``cls`` (a dataclass the config class derives from) in the
    config ``cfg``, as a ``cls`` instance (a copy: the loop's settings, a field's own)."""
    return cls(**{f.name: getattr(cfg, f.name) for f in dataclasses.fields(cls)})


def check_at_least(cfg, fail, low, *names) -> None:
    """Raises ``fail(name, "must be >= low, got v")`` for the first of the fields ``names`` of
    config ``cfg`` whose value is below ``low`` (``fail(name, rule)`` builds the error)."""
    for name in names:
        if (v := getattr(cfg, name)) < low:
            raise fail(name, f"must be >= {low}, got {v}")


def section_declaring(cls, name: str):
    """The config section of config class ``cls`` that declares field ``name``: the first class
    in its bases (the most basic) that declares it, when that class has a ``TITLE`` (its flags
    are shown apart, under it); else None (the config's own fields)."""
    for k in reversed(cls.__mro__):
        if name in vars(k).get("__annotations__", {}):
            return k if vars(k).get("TITLE") else None
    return None


def _fields(cls, groups=(), include=None, exclude=()):
    for f in dataclasses.fields(cls):
        m = f.metadata
        if "flag" not in m or m["flag"] is None or f.name in exclude:
            continue
        if include is not None and f.name not in include:
            continue
        if include is None and m["groups"] and not set(m["groups"]) & set(groups):
            continue
        yield f


def flag_of(f) -> str:
    """The command-line flag of a config field (``dataclasses.Field``)."""
    flag = f.metadata.get("flag", _AUTO)
    return "--" + f.name.replace("_", "-") if flag in (_AUTO, None) else flag


def _kind(f) -> str:
    t = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    return t.replace(" | None", "").replace("Optional[", "").rstrip("]").strip()


def _default(f):
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory()


def add_flags(
    parser,
    cls,
    *,
    groups=(),
    include=None,
    exclude=(),
    defaults=None,
    unset=(),
    notes=None,
    titles=None,
) -> None:
    """Adds the flags of config class ``cls`` to ``parser``: the fields declared with a flag,
    those of the given ``groups`` too (or exactly the fields named in ``include``). Each
    flag's default is the field's default, except for those in ``defaults`` (a demo's own,
    smaller settings: {field: value}) and those in ``unset`` (default None, meaning "not
    given": the config's default applies, as :func:`from_flags` leaves them out, or a preset's
    value, see :func:`apply_preset`; the help says which default that is). ``notes``
    ({field: text}) are added to the fields' help (e.g. what a preset sets). The parsed value
    lands under the field's name. The flags of a config section with a ``TITLE`` (see
    :func:`section_declaring`) are shown together, under that title or ``titles(section)``."""
    defaults, notes = defaults or {}, notes or {}
    sections = {}
    for f in _fields(cls, groups, include, exclude):
        m, kind = f.metadata, _kind(f)
        section = section_declaring(cls, f.name)
        group = parser  # where the flag goes: its section's group (shown together) or the parser
        if section is not None and isinstance(parser, argparse.ArgumentParser):
            if section not in sections:
                title = titles(section) if titles else section.TITLE
                sections[section] = parser.add_argument_group(title)
            group = sections[section]
        default = defaults.get(f.name, _default(f))
        help_ = m["help"]
        kw = dict(dest=f.name, help=help_)
        if kind == "bool":
            if m["negate"]:
                kw.update(action="store_false", default=default)
                group.add_argument(m["negate"], **kw)
                continue
            action = argparse.BooleanOptionalAction if default else "store_true"
            group.add_argument(flag_of(f), action=action, default=default, **kw)
            continue
        if callable(m["check"]):  # (an argparse type of the field's own)
            kw["type"] = m["check"]
        elif (kind, m["check"]) not in CHECKS:
            raise TypeError(f"{cls.__name__}.{f.name}: no command-line type for {kind!r}")
        else:
            kw["type"] = CHECKS[(kind, m["check"])]
        if m["choices"] is not None:
            kw["choices"] = list(m["choices"])
        else:  # the flag's name, as argparse shows a flag whose dest is its own
            kw["metavar"] = m.get("metavar") or flag_of(f)[2:].upper().replace("-", "_")
        if m.get("const") is not None:
            kw.update(nargs="?", const=m["const"])
        if m.get("required"):
            kw["required"] = True
        if f.name in unset:
            kw["default"] = None
            if default is not None:
                kw["help"] = f"{help_} (default {default})" if help_ else f"default {default}"
        else:
            kw["default"] = default
            if default not in (None, "") and "default" not in help_ and not m.get("required"):
                kw["help"] = f"{help_} (default {default})" if help_ else f"default {default}"
        if f.name in notes:
            kw["help"] = f"{kw['help']}; {notes[f.name]}" if kw["help"] else notes[f.name]
        group.add_argument(flag_of(f), **kw)


def from_flags(cls, args, *, groups=(), include=None, exclude=()) -> dict:
    """The keyword arguments of config class ``cls`` given on the parsed ``args`` (the flags
    :func:`add_flags` made with the same ``groups``/``include``); a flag left at None, where
    the field's own default is not None, is left out (the field's default applies)."""
    kw = {}
    for f in _fields(cls, groups, include, exclude):
        if not hasattr(args, f.name):
            continue
        v = getattr(args, f.name)
        if v is None and _default(f) is not None:
            continue
        kw[f.name] = v
    return kw


def apply_preset(kw: dict, values: dict) -> dict:
    """The config keyword arguments ``kw`` (from :func:`from_flags`) with a preset's ``values``
    ({field: value}) for the fields the user did not give: absent from ``kw`` or None (their
    flags were added with ``unset``). Explicit flags win."""
    out = dict(kw)
    for name, value in values.items():
        if out.get(name) is None:
            out[name] = value
    return out
