"""The package's import graph: no cycles, and imports only point down the layers of
docs/ARCHITECTURE.md (lazy imports inside functions count too)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# layer of each top-level part of the package: a module may import its own layer or lower ones
LAYERS = {
    "kernels": 0,
    "errors": 1,
    "trace": 1,  # (an alias of sphere_tracing for one release)
    "sphere_tracing": 1,
    "options": 1,
    "plugins": 1,
    "reference": 2,
    "ops": 2,
    "outputs": 2,
    "json_input": 2,
    "safe_writes": 2,
    "io": 2,  # (io, jsonio, files: aliases of outputs, json_input, safe_writes for one release)
    "jsonio": 2,
    "files": 2,
    "safe_open": 2,
    "ply": 2,
    "metrics": 2,
    "field_protocol": 2,  # (what renderers call on a field; imports torch only)
    "data": 3,
    "fields": 4,
    "occupancy": 4,
    "render": 5,
    "render_marched": 5,
    "render_traced": 5,
    "render_proposal": 5,
    "mesh": 5,
    "mesh_clean": 5,
    "train": 6,
    "bench": 7,
    "export": 7,
    "viewer": 7,
    "box_demo": 7,
    "demo": 7,  # (an alias of box_demo for one release)
    "cli": 8,
    "__init__": 9,
    "__main__": 9,
}
# modules placed above their folder's layer: the built-in scene is rendered by the pipeline (its
# dataset is made with fields and render; no other data module imports it)
OVERRIDES = {"warpnerf.data.synthetic": LAYERS["render"]}


def _modules() -> dict:
    """{dotted name: (path, package of relative imports)} of warpnerf and its kernels."""
    mods = {}
    for base, prefix in ((ROOT / "warpnerf", "warpnerf"), (ROOT / "kernels", "warpnerf.kernels")):
        for p in sorted(base.rglob("*.py")):
            rel = p.relative_to(base)
            if prefix == "warpnerf" and rel.parts[0] == "kernels":
                continue  # (a link to kernels/ in a source tree)
            parts = [prefix, *rel.with_suffix("").parts]
            if parts[-1] == "__init__":
                parts = parts[:-1]
                pkg = ".".join(parts)
            else:
                pkg = ".".join(parts[:-1])
            mods[".".join(parts)] = (p, pkg)
    return mods


def _from_module(node: ast.ImportFrom, pkg: str) -> str:
    """The dotted module a ``from ... import`` names, relative imports resolved against ``pkg``."""
    if not node.level:
        return node.module or ""
    up = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
    return ".".join(up + ([node.module] if node.module else []))


def _imports(mods: dict) -> dict:
    """{module: {imported modules of the package}} and a set of all top-level names imported."""
    edges = {m: set() for m in mods}
    external = {m: set() for m in mods}
    for m, (p, pkg) in mods.items():
        for node in ast.walk(ast.parse(p.read_text(), str(p))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _from_module(node, pkg)
                subs = [f"{base}.{a.name}" for a in node.names]
                names = [n for n in subs if n in mods] or [base]
            else:
                continue
            for n in names:
                external[m].add(n.split(".")[0])
                while n and n not in mods:  # warpnerf.x.y.name -> the module warpnerf.x.y
                    n = n.rpartition(".")[0]
                if n and n != m:
                    edges[m].add(n)
    return edges, external


def _layer(mod: str) -> int:
    if mod in OVERRIDES:
        return OVERRIDES[mod]
    parts = mod.split(".")
    return LAYERS["__init__"] if len(parts) == 1 else LAYERS[parts[1]]


def _cycles(edges: dict) -> list:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _parent_packages(mod: str) -> set:
    parts = mod.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def test_every_part_has_a_layer():
    mods = _modules()
    unknown = {m.split(".")[1] for m in mods if "." in m and m.split(".")[1] not in LAYERS}
    assert not unknown, f"add these parts of the package to LAYERS: {sorted(unknown)}"


def test_no_import_cycles():
    edges, _ = _imports(_modules())
    # a package's __init__ re-exporting its modules is not a cycle with them
    edges = {m: {n for n in e if n not in _parent_packages(m)} for m, e in edges.items()}
    assert _cycles(edges) == []


def test_imports_point_down_the_layers():
    edges, _ = _imports(_modules())
    upward = [
        f"{m} (layer {_layer(m)}) imports {n} (layer {_layer(n)})"
        for m, e in sorted(edges.items())
        for n in sorted(e)
        if _layer(n) > _layer(m) and n not in _parent_packages(m)
    ]
    assert upward == []


def test_kernels_import_no_torch_and_ops_no_fields():
    mods = _modules()
    edges, external = _imports(mods)
    for m in mods:
        if m.startswith("warpnerf.kernels"):
            assert "torch" not in external[m], f"{m} imports torch"
            assert all(n.startswith("warpnerf.kernels") for n in edges[m]), m
        if m.startswith("warpnerf.ops"):
            assert not [n for n in edges[m] if n.startswith(("warpnerf.fields", "warpnerf.data"))]
        if m.startswith("warpnerf.data") and m not in OVERRIDES:
            assert not [n for n in edges[m] if n.startswith(("warpnerf.train", "warpnerf.render"))]


def test_the_checker_finds_a_cycle_and_an_upward_import():
    """The test's own machinery on a made-up graph (so the tests above cannot pass vacuously)."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
    assert _layer("warpnerf.ops.rays") < _layer("warpnerf.fields.nerf")
    edges, _ = _imports(_modules())
    assert "warpnerf.ops.bridge" in edges["warpnerf.ops.composite"]


# --- issue 46: no module imports another's private names; modules stay under 600 lines ---------

# the kept tools' imports of private names, removed by the scripts cleanup (another change);
# nothing in warpnerf/ or demos/ may be listed here
SCRIPTS_ALLOWED = {
    "scripts/peers/peer_runner.py: nerfacc.cuda._backend",  # (a peer library's own internals)
}
MAX_LINES = 600


def _package_of(path: Path) -> tuple:
    """(dotted name of the module, its package) for a file under ROOT, demos/ and scripts/
    being packages of their own (their files import each other as top-level modules)."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
        return ".".join(parts), ".".join(parts)
    return ".".join(parts), ".".join(parts[:-1])


def private_imports(path: Path) -> list:
    """'file: module.name' for each import in ``path`` of a private name (a leading underscore)
    of another module, or of a private module (``_x.py``) from outside its own folder. A private
    module may serve the modules beside it (``data/_paths.py`` for the data loaders)."""
    mod, pkg = _package_of(path)
    rel = path.relative_to(ROOT).as_posix()
    loose = rel.split("/")[0] in ("demos", "scripts")  # (scripts import their neighbours by name)
    out = []

    def private_module(dotted: str) -> bool:
        parts = dotted.split(".")
        for i, part in enumerate(parts):
            if part.startswith("_") and not part.startswith("__"):
                owner = ".".join(parts[:i])
                if loose and i == 0:
                    owner = pkg  # `import _common` in demos/: its own folder
                if owner != pkg:
                    return True
        return False

    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [f"{rel}: {a.name}" for a in node.names if private_module(a.name)
                    and not (loose and "." not in a.name)]  # fmt: skip
        elif isinstance(node, ast.ImportFrom):
            base = _from_module(node, pkg)
            for a in node.names:
                name = a.name
                if (name.startswith("_") and not name.startswith("__")) or private_module(base):
                    out.append(f"{rel}: {base}.{name}")
    return out


def _sources(*tops: str) -> list:
    files = []
    for top in tops:
        for p in sorted((ROOT / top).rglob("*.py")):
            if top == "warpnerf" and "kernels" in p.relative_to(ROOT / top).parts[:1]:
                continue  # (the link to kernels/, scanned as kernels/)
            files.append(p)
    return files


def test_no_module_imports_private_names_of_another():
    found = [hit for p in _sources("warpnerf", "kernels", "demos") for hit in private_imports(p)]
    assert found == [], "make these names public where they are shared:\n" + "\n".join(found)


def test_scripts_import_no_private_names_beyond_the_known_ones():
    found = {hit for p in _sources("scripts") for hit in private_imports(p)}
    assert found <= SCRIPTS_ALLOWED, sorted(found - SCRIPTS_ALLOWED)


def test_the_private_import_check_sees_them(tmp_path, monkeypatch):
    import sys

    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    (tmp_path / "warpnerf" / "cli").mkdir(parents=True)
    (tmp_path / "demos").mkdir()
    f, demo = tmp_path / "warpnerf" / "cli" / "x.py", tmp_path / "demos" / "x.py"
    f.write_text("from warpnerf.ops._bridge import check_int\nfrom .train import _nerf_flags\n")
    assert len(private_imports(f)) == 2
    f.write_text("from ._common import check_out\nfrom warpnerf.ops.bridge import check_int\n")
    assert private_imports(f) == []  # (a private module serves its own folder)
    demo.write_text("import _common\nfrom warpnerf.data._paths import OPT_IN\n")
    assert private_imports(demo) == ["demos/x.py: warpnerf.data._paths.OPT_IN"]


def test_no_module_over_600_lines():
    long = [f"{p.relative_to(ROOT)}: {n}" for p in _sources("warpnerf", "kernels")
            if (n := len(p.read_text().splitlines())) > MAX_LINES]  # fmt: skip
    assert long == [], f"split these by responsibility (over {MAX_LINES} lines):\n" + "\n".join(
        long
    )


def test_renamed_modules_keep_their_old_import_paths_for_one_release():
    """Issue 46's renames: each old public import path re-exports the new module's names."""
    import importlib

    renamed = {"warpnerf.trace": "warpnerf.sphere_tracing", "warpnerf.io": "warpnerf.outputs",
               "warpnerf.files": "warpnerf.safe_writes", "warpnerf.jsonio": "warpnerf.json_input",
               "warpnerf.demo": "warpnerf.box_demo",
               "warpnerf.data.datasets": "warpnerf.data.loading"}  # fmt: skip
    for old, new in renamed.items():
        old_mod, new_mod = importlib.import_module(old), importlib.import_module(new)
        assert old_mod.__all__ == new_mod.__all__ and new in old_mod.__doc__
        assert all(getattr(old_mod, n) is getattr(new_mod, n) for n in new_mod.__all__), old
    from warpnerf.train.methods import LoadedRun, Opened

    assert Opened is LoadedRun
