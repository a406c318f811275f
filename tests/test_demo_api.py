"""Demos and scripts call only the public API: every ``warpnerf`` name a demo or a script in
``scripts/`` imports is listed in the
``__all__`` of a public module (``warpnerf``, its subpackages and its modules without a leading
underscore), so the library's internals can change without breaking them."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DEMOS = sorted((ROOT / "demos").glob("*.py"))
# the kept tools too (one-off studies that reach into internals live in experiments/)
SCRIPTS = sorted((ROOT / "scripts").glob("**/*.py"))


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("warpnerf"):
            yield node.lineno, node.module, [a.name for a in node.names]
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("warpnerf"):
                    yield node.lineno, a.name, []


def _public_module(name: str) -> bool:
    """A submodule without a leading underscore (``from warpnerf import reference``)."""
    import importlib.util

    leaf = name.rsplit(".", 1)[-1]
    return not leaf.startswith("_") and importlib.util.find_spec(name) is not None


@pytest.mark.parametrize("path", DEMOS + SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_demo_imports_only_public_names(path):
    bad = []
    for line, module, names in _imports(path):
        where = f"{path.name}:{line}: {module}"
        if any(part.startswith("_") for part in module.split(".")):
            bad.append(f"{where} is private")
            continue
        public = set(getattr(importlib.import_module(module), "__all__", ()))
        bad += [f"{where}.{n} is not in its __all__" for n in names
                if n not in public and not _public_module(f"{module}.{n}")]  # fmt: skip
    assert not bad, "\n".join(bad)


def test_the_check_sees_private_use(tmp_path):
    demo = tmp_path / "x.py"
    demo.write_text(
        "from warpnerf.train.nerf import Trainer\nfrom warpnerf.ops._bridge import check_int\n"
    )
    found = list(_imports(demo))
    assert [m for _, m, _ in found] == ["warpnerf.train.nerf", "warpnerf.ops._bridge"]
