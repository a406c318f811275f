"""PLY files: writing a mesh (optionally with vertex colours and normals), reading a mesh and
reading the vertices of any PLY file as a point cloud, each file bounded and checked as input."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .outputs import atomic_path
from .safe_open import open_input, read_input

__all__ = ["write_ply", "read_ply", "read_ply_points", "MAX_PLY_BYTES"]


def write_ply(path, vertices: np.ndarray, faces: np.ndarray, replace_foreign: bool = False,
              colors=None, normals=None) -> None:  # fmt: skip
    """Binary little-endian PLY (float32 xyz, optional float32 nx/ny/nz and uchar red/green/blue
    per vertex, int32 triangle indices; no faces for a point cloud), written atomically with
    plyfile."""
    import plyfile

    v = np.asarray(vertices, dtype="<f4").reshape(-1, 3)
    f = np.asarray(faces, dtype="<i4").reshape(-1, 3)
    row = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        nr = np.asarray(normals)
        if nr.shape != (len(v), 3):
            raise ValueError(f"normals must be [{len(v)}, 3], got {nr.shape}")
        row += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != (len(v), 3) or c.dtype != np.uint8:
            raise ValueError(f"colors must be uint8 [{len(v)}, 3], got {c.dtype} {c.shape}")
        row += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(v), dtype=row)
    rows["x"], rows["y"], rows["z"] = v.T
    if normals is not None:
        rows["nx"], rows["ny"], rows["nz"] = np.asarray(nr, dtype="<f4").T
    if colors is not None:
        rows["red"], rows["green"], rows["blue"] = c.T
    tris = np.empty(len(f), dtype=[("vertex_indices", "<i4", (3,))])
    tris["vertex_indices"] = f
    data = plyfile.PlyData([
        plyfile.PlyElement.describe(rows, "vertex"),
        plyfile.PlyElement.describe(tris, "face", len_types={"vertex_indices": "u1"}),
    ], byte_order="<")  # fmt: skip
    with atomic_path(path, replace_foreign) as tmp, open(tmp, "wb") as fh:
        data.write(fh)


MAX_PLY_BYTES = 1 << 32  # 4 GiB: larger mesh files are refused before reading


def read_ply(path, colors: bool = False, normals: bool = False):
    """(vertices [V, 3] float32, faces [F, 3] int32) of a PLY mesh or point cloud (plyfile:
    ascii or binary; faces must be triangles), plus the vertex colours uint8 [V, 3] when
    ``colors`` and the normals [V, 3] when ``normals`` (None when the file has none).

    The file may be untrusted (a run folder's mesh): the header's counts are checked against the
    file's size before plyfile allocates anything, and an unreadable file, non-triangle faces,
    face indices outside the vertices or non-finite coordinates are a
    :class:`~warpnerf.errors.UserError` naming the file."""
    import plyfile

    from .errors import UserError

    path = Path(path)

    def bad(msg):
        return UserError(f"{path}: unreadable PLY file ({msg})")

    try:
        size = path.stat().st_size
        if size > MAX_PLY_BYTES:
            raise bad(f"{size} bytes, more than the {MAX_PLY_BYTES} accepted")
        with open_input(path, "PLY file", follow=True) as fh:  # (no FIFO, regular files only)
            head = fh.read(_PLY_MAX_HEADER + 64)
    except OSError as e:
        raise bad(f"cannot read: {e.strerror or e}") from None
    fmt, elements, start = _ply_header(head, bad)
    counts = {name: n for name, n, _ in elements}
    # the fewest bytes the promised rows take: binary xyz floats and 1 + 3 x 4-byte triangles;
    # ascii "0 0 0\n" and "3 0 0 0\n"; any other element at least a byte a row
    per = (6, 8) if fmt == "ascii" else (12, 13)
    least = per[0] * counts.get("vertex", 0) + per[1] * counts.get("face", 0)
    least += sum(n for name, n, _ in elements if name not in ("vertex", "face"))
    if size - start < least:
        raise bad(f"the header promises more elements than its {size} bytes hold")
    try:
        with open_input(path, "PLY file", follow=True) as fh:
            ply = plyfile.PlyData.read(fh, known_list_len={"face": {"vertex_indices": 3}})
        vert = ply["vertex"].data
        names = vert.dtype.names or ()
        pts = np.stack([vert[k] for k in ("x", "y", "z")], -1).astype(np.float32)
        if "face" in ply and len(ply["face"].data):
            lists = ply["face"].data[ply["face"].data.dtype.names[0]]
            tri = np.stack([np.asarray(t) for t in lists]).astype(np.int64)
        else:
            tri = np.zeros((0, 3), np.int64)
    except UserError:
        raise
    except (plyfile.PlyParseError, KeyError, ValueError, IndexError, TypeError, OSError,
            MemoryError) as e:  # fmt: skip
        raise bad(str(e)[:200] or type(e).__name__) from None
    if tri.ndim != 2 or tri.shape[1] != 3:
        raise bad("faces must be triangles")
    if len(tri) and (tri.min() < 0 or tri.max() >= len(pts)):
        raise bad(f"face indices outside the {len(pts)} vertices")
    if not np.isfinite(pts).all():
        raise bad("non-finite vertex coordinates")
    out = (pts, tri.astype(np.int32))
    if colors:
        rgb = {"red", "green", "blue"} <= set(names)
        out += (np.stack([vert[k] for k in ("red", "green", "blue")], -1).astype(np.uint8)
                if rgb else None,)  # fmt: skip
    if normals:
        nrm = {"nx", "ny", "nz"} <= set(names)
        out += (np.stack([vert[k] for k in ("nx", "ny", "nz")], -1).astype(np.float32)
                if nrm else None,)  # fmt: skip
    return out


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}  # fmt: skip


_PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


_PLY_MAX_HEADER = 1 << 20


def _ply_header(data: bytes, bad):
    """(format, elements [(name, count, [(prop, type or None for lists)])], body offset)."""
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise bad("it does not start with 'ply'")
    end = data.find(b"end_header", 0, _PLY_MAX_HEADER)
    nl = data.find(b"\n", end) if end >= 0 else -1
    if nl < 0 or data[end + len(b"end_header") : nl].strip():
        raise bad(f"no 'end_header' line in the first {_PLY_MAX_HEADER} bytes")
    try:
        head = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise bad("the header is not ASCII text") from None
    fmt, elements = None, []
    for lineno, line in enumerate(head, 2):
        w = line.split()
        if not w or w[0] in ("comment", "obj_info"):
            continue
        if w[0] == "format" and len(w) == 3 and w[1] in _PLY_FORMATS and fmt is None:
            fmt = w[1]
        elif w[0] == "element" and len(w) == 3:
            if not (w[2].isdigit() and len(w[2]) < 19):
                raise bad(f"header line {lineno}: element count {w[2]!r} is not a count")
            elements.append((w[1], int(w[2]), []))
        elif w[0] == "property" and elements and len(w) == 3 and w[1] in _PLY_TYPES:
            elements[-1][2].append((w[2], _PLY_TYPES[w[1]]))
        elif (w[0] == "property" and elements and len(w) == 5 and w[1] == "list"
              and w[2] in _PLY_TYPES and w[3] in _PLY_TYPES):  # fmt: skip
            elements[-1][2].append((w[4], None))
        else:
            raise bad(f"header line {lineno} not understood: {line[:60]!r}")
    if fmt is None:
        raise bad("no 'format ascii|binary_little_endian|binary_big_endian 1.0' line")
    return fmt, elements, nl + 1


def read_ply_points(path):
    """(points [N, 3] float64, normals [N, 3] or None) of a PLY file's vertices (ascii, binary
    little- or big-endian; properties ``x, y, z`` and optionally ``nx, ny, nz``).

    The file is untrusted: a malformed header (no ``ply`` magic, unknown format, type or line,
    non-numeric or negative counts), a vertex count larger than the file holds (checked against
    its size before anything is allocated), list properties in the vertex element (or, in a
    binary file, before it), unparsable ASCII rows and non-finite coordinates or normals are a
    :class:`~warpnerf.errors.UserError` naming the file."""
    from pathlib import Path

    from .errors import UserError

    path = Path(path)

    def bad(msg):
        return UserError(f"{path}: unreadable PLY file ({msg})")

    try:  # (bounded, no FIFO, regular files only)
        data = read_input(path, "PLY file", MAX_PLY_BYTES, follow=True)
    except OSError as e:
        raise bad(f"cannot read: {e.strerror or e}") from None
    fmt, elements, start = _ply_header(data, bad)
    vi = next((i for i, e in enumerate(elements) if e[0] == "vertex"), None)
    if vi is None:
        raise bad("no 'element vertex' in the header")
    _, n, props = elements[vi]
    names = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise bad("the vertex element needs x, y, z properties, each once")
    if any(t is None for _, t in props):
        raise bad("list properties in the vertex element are not supported")
    if fmt == "ascii":
        lines = [ln for ln in data[start:].split(b"\n") if ln.strip()]
        skip = sum(c for _, c, _ in elements[:vi])  # one line per row of the earlier elements
        if skip + n > len(lines):
            raise bad(f"{n} vertices declared, but the file has {max(len(lines) - skip, 0)} rows")
        rows = lines[skip : skip + n]
        tokens = []
        for i, row in enumerate(rows):
            vals = row.split()
            if len(vals) != len(names):
                raise bad(f"vertex {i} has {len(vals)} values, expected {len(names)}")
            tokens += vals
        try:
            arr = np.array([float(t) for t in tokens], dtype=np.float64)
        except ValueError:
            raise bad("a vertex value is not a number") from None
        arr = arr.reshape(n, len(names))  # 0 vertices: [0, k], not [0]
        col = {k: arr[:, i] for i, k in enumerate(names)}
    else:
        order = _PLY_FORMATS[fmt]
        offset = start
        for name, count, eprops in elements[:vi]:
            if any(t is None for _, t in eprops):
                raise bad(f"element {name!r} with list properties before the vertices")
            offset += count * sum(np.dtype(t).itemsize for _, t in eprops)
        dt = np.dtype([(k, order + t) for k, t in props])
        if offset + n * dt.itemsize > len(data):
            raise bad(
                f"{n} vertices of {dt.itemsize} bytes declared, but the file has "
                f"{max(len(data) - offset, 0)} bytes for them (truncated?)"
            )
        rec = np.frombuffer(data, dt, n, offset) if n else np.zeros(0, dt)
        col = {k: rec[k].astype(np.float64) for k in names}
    pts = np.stack([col["x"], col["y"], col["z"]], 1)
    has_n = {"nx", "ny", "nz"} <= set(col)
    nrm = np.stack([col["nx"], col["ny"], col["nz"]], 1) if has_n else None
    for what, a in (("coordinates", pts), ("normals", nrm)):
        if a is not None and not np.isfinite(a).all():
            i = int(np.argmin(np.isfinite(a).all(axis=1)))
            raise bad(f"vertex {i} has non-finite {what} {a[i].tolist()}")
    return pts, nrm
