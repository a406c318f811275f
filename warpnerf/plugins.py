"""Registries that outside packages extend through entry points, as nerfstudio's methods do.

warpnerf's fields (``--field``), data formats (``--format``) and methods (``train <name>``)
live in registries filled by ``register_field``, ``register_format`` and ``register_method``:
the built-in ones call them in their own modules when warpnerf is imported, and an outside
package calls them in a module it names as an entry point of a group:

====================  ======================================================
``warpnerf.fields``   modules calling :func:`warpnerf.fields.register_field`
``warpnerf.formats``  modules calling :func:`warpnerf.data.register_format`
``warpnerf.methods``  modules calling ``warpnerf.train.methods.register_method``
====================  ======================================================

e.g. in the package's ``pyproject.toml``::

    [project.entry-points."warpnerf.fields"]
    blob = "warpnerf_blob.field"

An entry point is imported (and, when it names a callable such as ``"pkg.mod:register"``,
called with no arguments) the first time its group's registry is read: its name asked, its
names listed, an entry fetched; not when warpnerf is imported, and never twice. A plugin that
fails to import or to register (an error, or a name registered already) is skipped with a
:class:`PluginWarning` naming it, its distribution and the error; the other commands work on.
"""

from __future__ import annotations

import warnings

__all__ = ["GROUPS", "PluginWarning", "Registry", "add_entry", "load_plugins"]

GROUPS = ("warpnerf.fields", "warpnerf.formats", "warpnerf.methods")

_LOADED: set = set()  # the groups whose entry points were loaded (or are loading)


class PluginWarning(UserWarning):
    """A plugin (an entry point of one of :data:`GROUPS`) that could not be loaded."""


def load_plugins(group: str) -> list:
    """Loads the entry points of ``group`` once (later calls do nothing); returns the names of
    those loaded now. A broken one gives a :class:`PluginWarning` and is skipped."""
    if group in _LOADED:
        return []
    _LOADED.add(group)  # (first: a plugin reading its own registry does not load it again)
    from importlib import metadata

    try:
        eps = metadata.entry_points(group=group)
    except Exception as e:  # (a malformed installed distribution: say so, load none)
        warnings.warn(f"warpnerf: the plugins of {group} could not be listed: {e}",
                      PluginWarning, stacklevel=3)  # fmt: skip
        return []
    loaded = []
    for ep in eps:
        dist = getattr(getattr(ep, "dist", None), "name", None)
        who = f"plugin {ep.name!r} ({ep.value}{f', from {dist}' if dist else ''})"
        try:
            obj = ep.load()
            if callable(obj):  # ("pkg.mod:register"; a module is imported and that is all)
                obj()
        except Exception as e:
            file, line = _where(e, ep.name)
            warnings.warn_explicit(
                f"warpnerf: {who} of {group} was not loaded: {type(e).__name__}: {e}",
                PluginWarning, file, line, module="warpnerf.plugins",
            )  # fmt: skip
            continue
        loaded.append(ep.name)
    return loaded


def add_entry(registry: dict, name: str, value) -> bool:
    """Registers ``value`` under ``name`` in ``registry`` (a :class:`Registry` or a plain dict)
    without loading any plugin; False (and nothing changed) when the name is taken."""
    if dict.__contains__(registry, name):
        return False
    dict.__setitem__(registry, name, value)
    return True


def _where(error: BaseException, name: str) -> tuple:
    """(file, line) a plugin's warning is shown at: the deepest place of ``error``'s traceback
    in the plugin's own code (not warpnerf's, not the import machinery's), else the entry point's
    name."""
    import importlib
    import os
    import traceback

    skip = tuple(
        os.path.dirname(os.path.abspath(f)) + os.sep for f in (importlib.__file__, __file__)
    )  # (the import machinery, warpnerf)
    frames = [f for f in traceback.extract_tb(error.__traceback__)
              if not f.filename.startswith(("<", *skip))]  # fmt: skip
    return (frames[-1].filename, frames[-1].lineno or 0) if frames else (f"<plugin {name}>", 0)


class Registry(dict):
    """A registry (name -> what is registered) whose reads first load the plugins of its
    entry-point ``group`` (:func:`load_plugins`). Registering (:func:`add_entry`) loads nothing,
    so the built-in entries fill it at import time without loading any plugin."""

    def __init__(self, group: str):
        super().__init__()
        self.group = group

    def _plugins(self) -> None:
        if self.group not in _LOADED:
            load_plugins(self.group)

    def __contains__(self, name) -> bool:
        self._plugins()
        return super().__contains__(name)

    def __getitem__(self, name):
        self._plugins()
        return super().__getitem__(name)

    def __iter__(self):
        self._plugins()
        return super().__iter__()

    def __len__(self) -> int:
        self._plugins()
        return super().__len__()

    def get(self, name, default=None):
        self._plugins()
        return super().get(name, default)

    def keys(self):
        self._plugins()
        return super().keys()

    def values(self):
        self._plugins()
        return super().values()

    def items(self):
        self._plugins()
        return super().items()

    def __repr__(self) -> str:
        self._plugins()
        return f"Registry({self.group!r}, {super().__repr__()})"
