"""Keeping a dataset's file names inside its folder: the one rule every loader applies to the
names a dataset file gives (COLMAP image names, ``transforms*.json`` ``file_path``)."""

from __future__ import annotations

from pathlib import Path, PurePosixPath, PureWindowsPath

__all__ = ["is_inside_name", "outside_reason", "OPT_IN"]

OPT_IN = "--allow-outside-paths"  # the flag that lets a dataset name files outside its folder


def is_inside_name(name: str) -> bool:
    """Whether ``name`` is a relative path that stays inside the folder it is relative to, read
    as written: not empty, not absolute (``/x``, ``C:\\x``, ``\\\\host``), no ``..`` part (with
    either separator)."""
    if not isinstance(name, str) or not name or "\0" in name:
        return False
    posix = name.replace("\\", "/")
    return (
        not posix.startswith("/")
        and not PureWindowsPath(name).drive
        and ".." not in PurePosixPath(posix).parts
    )


def outside_reason(root: Path, name: str, file: Path | None = None) -> str | None:
    """Why ``name`` (and the existing ``file`` it names, when given) is not inside the folder
    ``root``, or None when it is: absolute or climbing out with ``..``, or resolving (through
    symlinks) to a place outside ``root``'s own resolved path."""
    if not is_inside_name(name):
        return "is absolute or climbs out with '..'"
    if file is not None:
        real, top = Path(file).resolve(), Path(root).resolve()
        if not real.is_relative_to(top):
            return f"resolves (through a symlink) to {real}"
    return None
