"""Triangle meshes: reading OBJ and PLY files, validation, a BVH built on the host, and its traversal in JAX.

- Files: `read_mesh(path)` reads Wavefront OBJ (`v`, `vn`, `f`; polygons fan-triangulated; negative, i.e. relative,
  indices) and PLY (ASCII, binary little- and big-endian; `vertex` x, y, z and optional nx, ny, nz; `face`
  `vertex_indices`/`vertex_index` lists, polygons fan-triangulated) with small hand-written readers: numpy only, no
  new dependency. `write_ply` writes binary little-endian PLY (the format Mitsuba's `ply` shape reads).
- Front faces are counter-clockwise seen from the front (as in Mitsuba and PLY): the geometric normal of the triangle
  `(v0, v1, v2)` is `normalize(cross(v1 - v0, v2 - v0))`. Normals are flat (per face) unless `smooth=True` and the
  file has vertex normals: then the shading normal is the barycentric interpolation of the vertex normals.
- The BVH (`build_bvh`) is 4-wide with leaves of at most 4 triangles, built on the host by the surface area
  heuristic (an exact sweep over sorted centroids; a side's cost counts 4-triangle blocks, as in Embree) and
  stored as one table of 36-float rows: a leaf row holds 4 triangles, a node row its 4 children's boxes and rows.
  One traversal step reads one row (one gather) and either tests 4 triangles or 4 boxes (one vector op each),
  goes to the nearest child hit and pushes the others (farther first); the stack needs at most 3 entries per
  level, known when the mesh is built. Shadow rays stop at the first hit.
- Traversal under `vmap` (every render traces a chunk of rays at once) is batched with lane compaction
  (`jax.custom_batching.custom_vmap`): a vectorized while loop costs as many steps as its slowest lane needs, so
  the batch runs at full width until a quarter of its lanes are still walking, then those continue in a batch a
  quarter the size, and so on (`_walk_batch`). Each lane takes the same steps as the per-ray loop (`_walk_one`,
  used without `vmap`), so the hits are the same.
- Ray/triangle intersection is watertight (Woop, Benthin, Wald 2013, "Watertight Ray/Triangle Intersection", JCGT
  2(1)): vertices are sheared into a ray-aligned frame and tested with 2-D edge functions that two triangles sharing
  an edge compute with the same operands, so a ray through a shared edge or vertex hits at least one of them.
- Geometry is fixed (not differentiated): the traversal runs under `stop_gradient` in `lax.while_loop`s, returns the
  hit triangle's slot, and the differentiable quantities (distance along the ray from the hit triangle's plane, its
  normal) are recomputed from that triangle alone, so medium, light and BSDF parameters differentiate in forward and
  reverse mode as in analytic scenes.
"""

from __future__ import annotations

import functools
import math
import os
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._bsdf import AbstractBSDF
from ._math import cross, dot, safe_div, safe_norm, safe_normalize
from ._sampling import uniform_triangle
from ._shapes import AbstractShape, AreaSample, ShapeHit, SurfacePoint
from ._validate import concrete_values, polygons_in_box

__all__ = ["Mesh", "MeshError", "MeshData", "read_mesh", "write_ply", "build_bvh", "transform_matrix"]

T_MIN = 1e-4
"""Smallest accepted hit distance (scene units), as for the analytic shapes (`_shapes.T_MIN`)."""

_BOX_SLACK = 1.0 + 4.0 * 2.0**-24 * 3
"""Factor on a box's exit distance: covers the float32 rounding of the slab test (pbrt-v4's `1 + 2 gamma(3)`, with
room), so a box never misses a ray that hits a triangle inside it."""


class MeshError(ValueError):
    """A mesh file is missing, unreadable or invalid; the message names the file."""


class MeshData(NamedTuple):
    """A mesh as read from a file: `vertices` (V, 3) float64, `faces` (F, 3) int64 (counter-clockwise = front),
    `normals` (N, 3) float64 normals, or None when the file has none, and `normal_faces` (F, 3) int64: the index into
    `normals` of each face corner (an OBJ's `f v//vn` indexes normals apart from vertices), or None when the normals
    are per vertex (`N = V`, corner `j` of face `i` has `normals[faces[i, j]]`, as in a PLY)."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    normal_faces: np.ndarray | None = None

    def corner_normals(self) -> np.ndarray | None:
        """The normal at each face corner, (F, 3 corners, 3), or None without normals."""
        if self.normals is None:
            return None
        return self.normals[self.faces if self.normal_faces is None else self.normal_faces]


# ------------------------------------------------------------------------------------------------------- readers
def _fan(polys) -> list:
    """Fan-triangulate polygons (lists of vertex indices)."""
    tris = []
    for p in polys:
        for k in range(1, len(p) - 1):
            tris.append((p[0], p[k], p[k + 1]))
    return tris


def _obj_index(text: str, count: int, what: str) -> int:
    """An OBJ index (1-based; negative: relative to the `count` elements read so far) as a 0-based index."""
    i = int(text)
    if i == 0:
        raise ValueError(f"OBJ {what} indices start at 1 (0 is invalid)")
    return i - 1 if i > 0 else count + i


def _read_obj(path: str) -> MeshData:
    """Wavefront OBJ: `v`, `vn` and `f` with corners `v`, `v/vt`, `v//vn` or `v/vt/vn`. Normals are read by each
    corner's normal index (as the OBJ format and Mitsuba do), so a vertex may have different normals in different
    faces; a file whose faces give no normal index (or only some of them do) has no normals (flat shading)."""
    verts, norms, polys, npolys = [], [], [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            tag = parts[0]
            try:
                if tag == "v":
                    if len(parts) < 4:
                        raise ValueError("a vertex needs 3 coordinates")
                    verts.append([float(x) for x in parts[1:4]])
                elif tag == "vn":
                    if len(parts) < 4:
                        raise ValueError("a normal needs 3 coordinates")
                    norms.append([float(x) for x in parts[1:4]])
                elif tag == "f":
                    if len(parts) < 4:
                        raise ValueError("a face needs at least 3 vertices")
                    idx, nidx = [], []
                    for tok in parts[1:]:
                        fields = tok.split("/")
                        idx.append(_obj_index(fields[0], len(verts), "vertex"))
                        has_n = len(fields) >= 3 and fields[2] != ""
                        nidx.append(_obj_index(fields[2], len(norms), "normal") if has_n else None)
                    polys.append(idx)
                    npolys.append(nidx)
            except ValueError as e:
                raise MeshError(f"{path}: line {lineno}: cannot parse {line.strip()!r}: {e}") from None
    v = np.asarray(verts, np.float64).reshape(-1, 3)
    f = np.asarray(_fan(polys), np.int64).reshape(-1, 3)
    if norms and npolys and all(i is not None for p in npolys for i in p):
        return MeshData(v, f, np.asarray(norms, np.float64).reshape(-1, 3),
                        np.asarray(_fan(npolys), np.int64).reshape(-1, 3))
    return MeshData(v, f, None)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def _ply_header(raw: bytes, path: str):
    """`(format, elements, body_start)` of a PLY file; `elements`: `[name, count, [(name, dtype) or (name,
    (count_dtype, item_dtype))]]`. Counts must be integers >= 0; a header may end with `end_header` and no newline
    (then no data follows)."""
    if not raw.startswith(b"ply"):
        raise MeshError(f"{path}: not a PLY file (no 'ply' magic)")
    end = raw.find(b"\nend_header") + 1
    if end < 1:
        raise MeshError(f"{path}: PLY header has no end_header line")
    after = end + len(b"end_header")
    rest = raw[after:after + 2]
    if rest.startswith(b"\n"):
        body_start = after + 1
    elif rest == b"\r\n":
        body_start = after + 2
    elif rest == b"":  # `end_header` as the file's last bytes: a header with no data
        body_start = after
    else:
        raise MeshError(f"{path}: PLY header's end_header is followed by {raw[after:after + 8]!r}, not a newline; "
                        f"expected end_header on a line of its own")
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []
    for line in header[1:]:
        p = line.split()
        if not p or p[0] in ("comment", "obj_info"):
            continue
        try:
            if p[0] == "format":
                fmt = p[1]
            elif p[0] == "element":
                elements.append([p[1], int(p[2]), []])
            elif p[0] == "property":
                if p[1] == "list":
                    elements[-1][2].append((p[4], (_PLY_TYPES[p[2]], _PLY_TYPES[p[3]])))
                else:
                    elements[-1][2].append((p[2], _PLY_TYPES[p[1]]))
        except (KeyError, IndexError, ValueError):
            raise MeshError(f"{path}: cannot parse PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise MeshError(f"{path}: unknown PLY format {fmt!r}")
    for name, count, props in elements:
        if count < 0:
            raise MeshError(f"{path}: PLY header line 'element {name} {count}': the count {count} is negative; "
                            f"expected an integer >= 0")
        for pname, dt in props:
            if name == "face" and pname in ("vertex_indices", "vertex_index") and (
                    not isinstance(dt, tuple) or dt[1].startswith("f")):
                raise MeshError(f"{path}: PLY face property {pname} is not a list of integers; expected e.g. "
                                f"'property list uchar int {pname}'")
    # each record takes at least this many bytes (binary: its fixed part; ASCII: one digit and a separator per
    # value), so a count the data cannot hold (10^20) is refused before anything is allocated or looped over
    size = len(raw) - body_start
    for name, count, props in elements:
        per = sum(np.dtype(dt[0] if isinstance(dt, tuple) else dt).itemsize for _, dt in props) if fmt != "ascii" \
            else 2 * len(props)
        slack = 1 if fmt == "ascii" else 0  # the last ASCII value needs no separator after it
        if count * per > size + slack:
            raise MeshError(f"{path}: PLY header declares {count} {name} records, but the file's {size} bytes of data "
                            f"hold at most {(size + slack) // max(per, 1)}; the file is cut short or the count is "
                            f"wrong")
    return fmt, elements, body_start


def _read_ply(path: str) -> MeshData:
    with open(path, "rb") as fh:
        raw = fh.read()
    fmt, elements, body_start = _ply_header(raw, path)
    data = {}
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        try:
            for name, count, props in elements:
                rows = []
                for r in range(count):
                    row = {}
                    for pname, dt in props:
                        if isinstance(dt, tuple):
                            k = int(tokens[pos])
                            if k < 0 or pos + 1 + k > len(tokens):
                                raise MeshError(f"{path}: PLY data ends inside {name} {r} of {count} ({pname} "
                                                f"declares {k} values, {len(tokens) - pos - 1} remain); expected "
                                                f"{count} complete {name} records")
                            item = int if dt[1][0] in "iu" else float
                            row[pname] = [item(x) for x in tokens[pos + 1:pos + 1 + k]]
                            pos += 1 + k
                        else:
                            row[pname] = float(tokens[pos])
                            pos += 1
                    rows.append(row)
                data[name] = rows
        except (IndexError, ValueError) as e:
            if isinstance(e, MeshError):
                raise
            raise MeshError(f"{path}: PLY data ends early or holds a non-number (at value {pos + 1}); expected "
                            f"{', '.join(f'{c} {n} records' for n, c, _ in elements)}") from None
        if pos < len(tokens):
            raise MeshError(f"{path}: PLY data has {len(tokens) - pos} values after the records the header declares "
                            f"({', '.join(f'{c} {n}' for n, c, _ in elements)}); expected exactly the declared counts")
        verts = data.get("vertex", [])
        v = np.array([[r.get("x", np.nan), r.get("y", np.nan), r.get("z", np.nan)] for r in verts], np.float64)
        has_n = bool(verts) and all(k in verts[0] for k in ("nx", "ny", "nz"))
        n = np.array([[r["nx"], r["ny"], r["nz"]] for r in verts], np.float64) if has_n else None
        polys = [[int(i) for i in (r.get("vertex_indices") or r.get("vertex_index") or [])]
                 for r in data.get("face", [])]
    else:
        bo = "<" if fmt == "binary_little_endian" else ">"
        buf = memoryview(raw)[body_start:]
        pos = 0
        v, n, polys = None, None, []
        try:
            for name, count, props in elements:
                if all(not isinstance(dt, tuple) for _, dt in props):
                    dtype = np.dtype([(pn, bo + dt) for pn, dt in props])
                    arr = np.frombuffer(buf, dtype, count, pos)
                    pos += dtype.itemsize * count
                    if name == "vertex":
                        v = np.stack([arr[c].astype(np.float64) for c in ("x", "y", "z")], axis=-1)
                        if all(c in arr.dtype.names for c in ("nx", "ny", "nz")):
                            n = np.stack([arr[c].astype(np.float64) for c in ("nx", "ny", "nz")], axis=-1)
                    continue
                pos, lists = _read_binary_lists(buf, pos, count, props, bo)
                if name == "face":
                    key = "vertex_indices" if "vertex_indices" in lists else "vertex_index"
                    polys = lists.get(key, [])
        except (ValueError, KeyError):
            raise MeshError(f"{path}: PLY data ends early or is malformed; expected "
                            f"{', '.join(f'{c} {n} records' for n, c, _ in elements)}") from None
        if pos < len(buf):
            raise MeshError(f"{path}: PLY data has {len(buf) - pos} bytes after the records the header declares "
                            f"({', '.join(f'{c} {n}' for n, c, _ in elements)}); expected exactly the declared counts")
        if v is None:
            v = np.zeros((0, 3))
    faces = polys if isinstance(polys, np.ndarray) else np.asarray(_fan(polys), np.int64).reshape(-1, 3)
    return MeshData(np.asarray(v, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3), n)


def _read_binary_lists(buf, pos, count, props, bo):
    """Binary PLY element with list properties. Fast path: every list has the same length as the first record's
    (all triangles); otherwise record by record. A negative list length is malformed (ValueError)."""
    out = {}
    # fast path: fixed-length lists, checked afterwards
    fields, k0, p = [], {}, pos
    for pname, dt in props:
        if isinstance(dt, tuple):
            cdt, idt = dt
            k = int(np.frombuffer(buf, bo + cdt, 1, p)[0]) if count else 0
            if k < 0:
                raise ValueError("negative list length")
            k0[pname] = k
            fields += [(pname + "__n", bo + cdt), (pname, bo + idt, (k,))]
            p += np.dtype(cdt).itemsize + k * np.dtype(idt).itemsize
        else:
            fields.append((pname, bo + dt))
            p += np.dtype(dt).itemsize
    dtype = np.dtype(fields)
    if pos + dtype.itemsize * count <= len(buf):
        arr = np.frombuffer(buf, dtype, count, pos)
        if all(np.all(arr[pn + "__n"] == k) for pn, k in k0.items()):
            for pn, k in k0.items():
                vals = arr[pn].astype(np.int64).reshape(count, k)
                out[pn] = _fan_array(vals) if k != 3 else vals
            return pos + dtype.itemsize * count, out
    lists = {pn: [] for pn, dt in props if isinstance(dt, tuple)}
    for _ in range(count):
        for pname, dt in props:
            if isinstance(dt, tuple):
                cdt, idt = dt
                k = int(np.frombuffer(buf, bo + cdt, 1, pos)[0])
                if k < 0:
                    raise ValueError("negative list length")
                pos += np.dtype(cdt).itemsize
                lists[pname].append(np.frombuffer(buf, bo + idt, k, pos).astype(np.int64).tolist())
                pos += k * np.dtype(idt).itemsize
            else:
                pos += np.dtype(dt).itemsize
    return pos, lists


def _fan_array(polys: np.ndarray) -> np.ndarray:
    k = polys.shape[1]
    if k < 3:
        return np.zeros((0, 3), np.int64)
    return np.concatenate([np.stack([polys[:, 0], polys[:, j], polys[:, j + 1]], -1) for j in range(1, k - 1)])


def read_mesh(path) -> MeshData:
    """Read an OBJ (`.obj`) or PLY (`.ply`) file and validate it (`validate_mesh`).

    **Raises:** `MeshError` naming the file: missing or unreadable file, unknown extension, malformed data, no faces,
    face indices out of range, non-finite vertices, degenerate (zero-area) faces."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise MeshError(f"{path}: mesh file not found")
    ext = os.path.splitext(path)[1].lower()
    try:
        if ext == ".obj":
            mesh = _read_obj(path)
        elif ext == ".ply":
            mesh = _read_ply(path)
        else:
            raise MeshError(f"{path}: unknown mesh format {ext!r}; expected .obj or .ply")
    except OSError as e:
        raise MeshError(f"{path}: cannot read mesh file: {e.strerror or e}") from None
    validate_mesh(mesh, path)
    return mesh


@functools.lru_cache(maxsize=8)
def _read_cached(path: str, mtime_ns: int, size: int) -> MeshData:
    return read_mesh(path)


def read_mesh_cached(path) -> MeshData:
    """`read_mesh`, cached by (path, modification time, size): scene loading validates and then builds each mesh."""
    path = os.path.abspath(os.fspath(path))
    try:
        st = os.stat(path)
    except OSError:
        raise MeshError(f"{path}: mesh file not found") from None
    return _read_cached(path, st.st_mtime_ns, st.st_size)


def validate_mesh(mesh: MeshData, path: str = "<mesh>") -> None:
    """Raise `MeshError` (naming `path`) unless the mesh has faces, finite vertices, in-range indices and no
    degenerate (zero-area, e.g. repeated-vertex) faces."""
    v, f = mesh.vertices, mesh.faces
    if f.shape[0] == 0:
        raise MeshError(f"{path}: the mesh has no faces ({v.shape[0]} vertices)")
    bad = ~np.all(np.isfinite(v), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise MeshError(f"{path}: {int(bad.sum())} vertices are not finite (first: vertex {i} = {v[i].tolist()})")
    out = (f < 0) | (f >= v.shape[0])
    if out.any():
        i = int(np.argmax(out.any(axis=1)))
        raise MeshError(f"{path}: face {i} has vertex indices {f[i].tolist()} out of range [0, {v.shape[0] - 1}]")
    tri = v[f]
    area2 = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    scale = float(np.max(np.ptp(v, axis=0))) if v.shape[0] else 0.0
    degenerate = area2 <= 1e-14 * scale * scale
    if degenerate.any():
        i = int(np.argmax(degenerate))
        raise MeshError(f"{path}: {int(degenerate.sum())} of {f.shape[0]} faces are degenerate (zero area; first: "
                        f"face {i}, vertices {f[i].tolist()}); remove them from the file")
    if mesh.normals is not None:
        if not np.all(np.isfinite(mesh.normals)):
            raise MeshError(f"{path}: vertex normals are not finite")
        nf = mesh.normal_faces
        if nf is None and mesh.normals.shape[0] != v.shape[0]:
            raise MeshError(f"{path}: {mesh.normals.shape[0]} vertex normals for {v.shape[0]} vertices; expected one "
                            f"normal per vertex")
        if nf is not None:
            if nf.shape != f.shape:
                raise MeshError(f"{path}: normal indices of shape {nf.shape} for faces of shape {f.shape}; expected "
                                f"one normal index per face corner")
            out = (nf < 0) | (nf >= mesh.normals.shape[0])
            if out.any():
                i = int(np.argmax(out.any(axis=1)))
                raise MeshError(f"{path}: face {i} has normal indices {nf[i].tolist()} out of range "
                                f"[0, {mesh.normals.shape[0] - 1}]")


def write_ply(path, vertices, faces, normals=None) -> None:
    """Write a binary little-endian PLY: float32 `x y z` (and `nx ny nz`), faces as `uchar int` lists."""
    v = np.asarray(vertices, np.float32).reshape(-1, 3)
    f = np.asarray(faces, np.int32).reshape(-1, 3)
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    head = ["ply", "format binary_little_endian 1.0", "comment written by jaxfog", f"element vertex {len(v)}"]
    head += [f"property float {p}" for p in props]
    head += [f"element face {len(f)}", "property list uchar int vertex_indices", "end_header"]
    vd = np.zeros(len(v), np.dtype([(p, "<f4") for p in props]))
    for i, p in enumerate("xyz"):
        vd[p] = v[:, i]
    if normals is not None:
        nrm = np.asarray(normals, np.float32).reshape(-1, 3)
        for i, p in enumerate(("nx", "ny", "nz")):
            vd[p] = nrm[:, i]
    fd = np.zeros(len(f), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    fd["n"], fd["i"] = 3, f
    with open(path, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii"))
        fh.write(vd.tobytes())
        fh.write(fd.tobytes())


# ----------------------------------------------------------------------------------------------------- transforms
def transform_matrix(to_world) -> np.ndarray:
    """The 4x4 float64 matrix of a scene file's `to_world` (None: identity): either `{"matrix": 4x4}` or any of
    `{"scale": s or [sx, sy, sz], "rotate": {"axis": [x, y, z], "angle": degrees}, "translate": [x, y, z]}`,
    applied in that order (scale, then rotate, then translate: M = T R S)."""
    if to_world is None:
        return np.eye(4)
    if to_world.get("matrix") is not None:
        return np.asarray(to_world["matrix"], np.float64).reshape(4, 4)
    m = np.eye(4)
    s = to_world.get("scale")
    if s is not None:
        m = np.diag(list(np.broadcast_to(np.asarray(s, np.float64), (3,))) + [1.0]) @ m
    r = to_world.get("rotate")
    if r is not None:
        a = np.asarray(r["axis"], np.float64)
        a = a / np.linalg.norm(a)
        th = math.radians(r["angle"])
        K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        R = np.eye(4)
        R[:3, :3] = np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * (K @ K)
        m = R @ m
    t = to_world.get("translate")
    if t is not None:
        T = np.eye(4)
        T[:3, 3] = t
        m = T @ m
    return m


def apply_transform(mesh: MeshData, m: np.ndarray) -> MeshData:
    """World-space vertices (and normals, by the inverse transpose); a mirroring transform (det < 0) flips the
    winding so that front faces stay front faces. (Mitsuba 3 keeps the winding, so there a mirrored mesh faces the
    other way: `to_mitsuba` of a mirrored mesh is not the same scene, and the XML import refuses one.)"""
    m = np.asarray(m, np.float64)
    v = mesh.vertices @ m[:3, :3].T + m[:3, 3]
    n = None
    if mesh.normals is not None:
        n = mesh.normals @ np.linalg.inv(m[:3, :3])
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    keep = np.linalg.det(m[:3, :3]) > 0
    f = mesh.faces if keep else mesh.faces[:, ::-1]
    nf = mesh.normal_faces if keep or mesh.normal_faces is None else mesh.normal_faces[:, ::-1]
    return MeshData(v, f, n, nf)


# -------------------------------------------------------------------------------------------------------- the BVH
WIDTH = 4
"""Children per BVH node and triangles per leaf (both 4): a node row holds 4 child boxes and references (28
floats), a leaf row 4 triangles (36 floats), so nodes and leaves share one (rows, 36) table and a traversal step
reads one row."""

ROW = 36
"""Floats per row of `Mesh.rows`."""

_SAH_TRAVERSAL = 1.0
"""SAH cost of one node visit, in units of one leaf visit (a leaf tests its 4 triangles in one vector op, so a
leaf costs one step whatever its count; see `_sah_split`)."""


class BVH(NamedTuple):
    """Host BVH arrays (4-wide). `rows` (R, 36) float32: rows `0 .. n_leaves - 1` are leaves (triangle `k` of leaf
    `r`: vertex `i`, coordinate `c` at `rows[r, (3 i + c) 4 + k]`, unused lanes zero), the others internal nodes
    (child `k`'s box: `lo[a] = rows[r, 4 a + k]`, `hi[a] = rows[r, 12 + 4 a + k]`; its row `rows[r, 24 + k]` as a
    float, -1 for no child); `order` (4 n_leaves,): the input triangle of each leaf slot (-1: unused); `root`: the
    root's row; `depth`: internal nodes on the longest root-to-leaf path; `box`: the float32 bounds of all
    triangles, rounded outward (lo then hi, 6 Python floats)."""

    rows: np.ndarray
    order: np.ndarray
    n_leaves: int
    root: int
    depth: int
    box: tuple


def _area(lo, hi):
    e = np.maximum(hi - lo, 0.0)
    return e[..., 0] * e[..., 1] + e[..., 1] * e[..., 2] + e[..., 2] * e[..., 0]


def _sah_split(lo_t, hi_t, cen, idx):
    """Split the triangles `idx` (more than 4) in two by the surface area heuristic, sweeping every split of the
    centroids sorted along each axis (pbrt-v4 and Embree bin the large nodes; the exact sweep is vectorized here,
    the three axes at once). The cost of a side is its area times its number of 4-triangle blocks (Embree's block
    SAH: a leaf step tests 4 triangles at the price of one), so the split favours full leaves. Returns both sides as
    `(idx, lo, hi)` (float64 bounds)."""
    n = len(idx)
    srt = idx[np.argsort(cen[idx], axis=0, kind="stable").T]  # (3 axes, n)
    lo, hi = lo_t[srt], hi_t[srt]  # (3, n, 3)
    l_lo, l_hi = np.minimum.accumulate(lo, 1), np.maximum.accumulate(hi, 1)
    r_lo = np.minimum.accumulate(lo[:, ::-1], 1)[:, ::-1]
    r_hi = np.maximum.accumulate(hi[:, ::-1], 1)[:, ::-1]
    k = np.arange(1, n)
    cost = _area(l_lo[:, :-1], l_hi[:, :-1]) * ((k + 3) // 4) + _area(r_lo[:, 1:], r_hi[:, 1:]) * ((n - k + 3) // 4)
    c = cen[srt[:, [0, -1]], np.arange(3)[:, None]]
    cost[c[:, 0] == c[:, 1]] = np.inf  # no spread along this axis
    a, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    if not np.isfinite(cost[a, j]):  # all centroids equal: any split
        a, j = 0, n // 2 - 1
    return ((srt[a, :j + 1], l_lo[a, j], l_hi[a, j]), (srt[a, j + 1:], r_lo[a, j + 1], r_hi[a, j + 1]))


def build_bvh(tris) -> BVH:
    """4-wide BVH over triangles `tris` (F, 3, 3) with leaves of at most 4 triangles, built top-down by the block
    surface area heuristic (`_sah_split`): a node's children come from splitting, again and again, its child of
    largest area that has more than 4 triangles, until it has 4 (Embree's wide-BVH build). Boxes are the float32
    bounds rounded outward. Leaves are numbered depth-first (rows `0 ..`), internal nodes after them."""
    tris = np.asarray(tris, np.float64)
    F = tris.shape[0]
    lo_t, hi_t = tris.min(axis=1), tris.max(axis=1)
    cen = tris.mean(axis=1)

    def box32(lo, hi):
        return (np.nextafter(lo.astype(np.float32), np.float32(-np.inf)),
                np.nextafter(hi.astype(np.float32), np.float32(np.inf)))

    leaves, nodes = [], []  # leaves: index arrays; nodes: per child [reference ('L' | 'N', id), float32 box]
    depth = 0
    root = None
    stack = [((np.arange(F), lo_t.min(0), hi_t.max(0)), None, 0, 0)]  # ((idx, lo, hi), parent, position, depth)
    while stack:
        item, parent, pos, dep = stack.pop()
        if len(item[0]) <= WIDTH:
            ref = ("L", len(leaves))
            leaves.append(item[0])
        else:
            kids = [item]
            while len(kids) < WIDTH:
                big = [i for i, kk in enumerate(kids) if len(kk[0]) > WIDTH]
                if not big:
                    break
                i = max(big, key=lambda i: _area(kids[i][1], kids[i][2]))
                kids[i:i + 1] = list(_sah_split(lo_t, hi_t, cen, kids[i][0]))
            ref = ("N", len(nodes))
            nodes.append([[None, box32(kk[1], kk[2])] for kk in kids])
            depth = max(depth, dep + 1)
            for j in range(len(kids) - 1, -1, -1):  # pushed in reverse: the first child's leaves come first
                stack.append((kids[j], ref[1], j, dep + 1))
        if parent is None:
            root = ref
        else:
            nodes[parent][pos][0] = ref
    n_leaves = len(leaves)
    if n_leaves + len(nodes) >= 2**24:
        raise MeshError(f"{F} triangles: too many BVH rows for float32 references (at most about 50 million)")
    rows = np.zeros((n_leaves + len(nodes), ROW), np.float32)
    order = np.full(n_leaves * WIDTH, -1, np.int64)
    counts = np.array([len(idx) for idx in leaves])
    flat = np.concatenate(leaves)
    lane = np.arange(len(flat)) - np.repeat(np.cumsum(counts) - counts, counts)
    leaf = np.repeat(np.arange(n_leaves), counts)
    order[leaf * WIDTH + lane] = flat
    lv = rows[:n_leaves].reshape(n_leaves, 3, 3, WIDTH)
    lv[leaf, :, :, lane] = tris[flat].astype(np.float32)
    rows[:n_leaves] = lv.reshape(n_leaves, ROW)
    for q, kids in enumerate(nodes):
        row = rows[n_leaves + q]
        row[24:28] = -1.0
        for k, (ref, (lo, hi)) in enumerate(kids):
            row[0:12].reshape(3, WIDTH)[:, k] = lo
            row[12:24].reshape(3, WIDTH)[:, k] = hi
            row[24 + k] = ref[1] if ref[0] == "L" else n_leaves + ref[1]
    root_row = root[1] if root[0] == "L" else n_leaves + root[1]
    lo, hi = box32(lo_t.min(0), hi_t.max(0))
    return BVH(rows, order, n_leaves, int(root_row), int(depth), tuple(float(x) for x in np.concatenate([lo, hi])))


# -------------------------------------------------------------------------------------------------------- the Module
def _array_arg(x, name: str, path: str, kind) -> np.ndarray:
    """`Mesh.from_arrays`' argument `name` as an (n, 3) float64 (`kind` float) or int64 (`kind` int) array, or a
    `MeshError` naming it, the shape or type it has and what is valid: no reshaping (a (6, 2) array is not 4
    vertices) and no truncation (face index 1.5 is not 1)."""
    what = "an (n, 3) array of numbers" if kind is float else "an (n, 3) array of integers"
    try:
        a = np.asarray(x)
    except (TypeError, ValueError):
        raise MeshError(f"{path}: {name}: got {type(x).__name__}; expected {what}") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise MeshError(f"{path}: {name} has shape {a.shape}; expected {what} (shape (n, 3))")
    if kind is int:
        if a.dtype == bool or not np.issubdtype(a.dtype, np.integer):
            raise MeshError(f"{path}: {name} has dtype {a.dtype}; expected {what} (indices: a float index would be "
                            f"truncated)")
        return a.astype(np.int64)
    if a.dtype == bool or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise MeshError(f"{path}: {name} has dtype {a.dtype}; expected {what}")
    return a.astype(np.float64)


class Mesh(AbstractShape):
    """A triangle mesh with its BVH and its `bsdf` (any BSDF; one-sided BSDFs work on the front faces, which are
    counter-clockwise seen from the front). An `AbstractShape` that is intersected on its own (not `stacked`):
    nearest and any hit by BVH traversal (`mesh_nearest`, `mesh_occluded`; the hit's `prim` is its triangle's
    slot), the surface's distance and normal from the hit triangle (`mesh_hit`); area sampling picks a triangle by
    its area.

    Build it with `Mesh.from_arrays(vertices, faces, bsdf, normals=None, smooth=False)` or `Mesh.from_file(path,
    bsdf, to_world=None, smooth=False)`. The geometry is fixed once built (its arrays are the BVH's leaf order and
    are not differentiated); replacing its BSDF values with `eqx.tree_at` is fine.

    **Fields:** `rows` (rows, 36): the 4-wide BVH (see `BVH`): rows `0 .. n_leaves - 1` are leaves of 4 triangle
    slots (slot `s` is leaf `s // 4`, lane `s % 4`; unused slots are zero and never hit; `leaves` is the same data as
    (leaves, 3 vertices, 3 coordinates, 4)) with world-space vertices; each triangle's vertices are sorted by their
    index in the file, `wind` (leaves, 4) is +1 where that kept the file's winding and -1 where it reversed it;
    `vn`: vertex normals in the `leaves` layout, or None (flat normals); `face` (slots,): the file's face index of
    each slot (-1: unused); static `root` (the root's row), `box` (the whole mesh's float32 box, rounded outward:
    lo then hi, 6 floats), `stack_size`, `n_leaves`, `n_faces`.
    """

    rows: Float[Array, "R 36"]
    vn: Float[Array, "Nl 3 3 4"] | None
    wind: Float[Array, "Nl 4"]
    face: Int[Array, "S"]
    bsdf: AbstractBSDF
    root: int = eqx.field(static=True)
    box: tuple = eqx.field(static=True)
    stack_size: int = eqx.field(static=True)
    n_leaves: int = eqx.field(static=True)
    n_faces: int = eqx.field(static=True)
    stacked: ClassVar[bool] = False

    @property
    def leaves(self) -> Float[Array, "Nl 3 3 4"]:
        """The leaf rows as (leaves, 3 vertices, 3 coordinates, 4 lanes)."""
        return self.rows[: self.n_leaves].reshape(self.n_leaves, 3, 3, WIDTH)

    # ------------------------------------------------------------------------------------------ AbstractShape
    def intersect(self, o, d, t_max) -> ShapeHit:
        t, slot = mesh_nearest(self, o, d, t_max)
        found = slot >= 0
        return ShapeHit(jnp.where(found, t, jnp.inf), found, jnp.maximum(slot, 0))

    def surface(self, o, d, hit) -> SurfacePoint:
        return SurfacePoint(*mesh_hit(self, o, d, hit.prim))

    def any_hit(self, o, d, t_max):
        return mesh_occluded(self, o, d, t_max)

    def bounds(self):
        return jnp.asarray(self.box[:3], jnp.float32), jnp.asarray(self.box[3:], jnp.float32)

    def _triangles(self):
        """Every leaf slot's triangle `(slots, 3 vertices, 3)` (unused slots: zero, of area 0), its front normal
        direction `cross(v1 - v0, v2 - v0)` times the winding sign `(slots, 3)`, and its area `(slots,)`."""
        tri = jax.lax.stop_gradient(self.leaves).transpose(0, 3, 1, 2).reshape(-1, 3, 3)
        ng = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) * self.wind.reshape(-1, 1)
        return tri, ng, 0.5 * safe_norm(ng)

    def sample_area(self, u) -> AreaSample:
        """A triangle with probability proportional to its area (`u[0]` against the areas' running sum, then
        rescaled into that triangle's share), then a point uniform in it (`_sampling.uniform_triangle`)."""
        tri, ng, area = self._triangles()
        cdf = jnp.cumsum(area)
        total = cdf[-1]
        x = u[0] * total
        k = jnp.clip(jnp.searchsorted(cdf, x, side="right"), 0, area.shape[0] - 1)
        u0 = jnp.clip(safe_div(x - (cdf[k] - area[k]), area[k]), 0.0, 1.0)
        b0, b1, b2 = uniform_triangle(u0, u[1])
        p = b0 * tri[k, 0] + b1 * tri[k, 1] + b2 * tri[k, 2]
        return AreaSample(p, safe_normalize(ng[k]), 1.0 / total)

    def pdf_area(self, p):
        return 1.0 / jnp.sum(self._triangles()[2])

    def box_relation(self, lo, hi):
        vals = concrete_values(self.rows, lo, hi)
        if vals is None:
            return None
        used = np.asarray(self.face) >= 0
        tri = np.asarray(self.leaves, np.float64).transpose(0, 3, 1, 2).reshape(-1, 3, 3)[used]
        return polygons_in_box(tri, vals[1], vals[2])

    @classmethod
    def from_arrays(cls, vertices, faces, bsdf, normals=None, smooth: bool = False,
                    path: str = "Mesh.from_arrays", normal_faces=None) -> "Mesh":
        """A mesh from world-space `vertices` (V, 3) floats, `faces` (F, 3) integers (indices into `vertices`,
        counter-clockwise = front) and optional `normals`: (V, 3), one per vertex, or (N, 3) with `normal_faces`
        (F, 3) integers, each face corner's index into `normals` (an OBJ's `f v//vn`). Smooth shading normals when
        `smooth` and normals are given (else flat). Validated: a `MeshError` names `path` (or the argument), the
        value and what is valid."""
        data = MeshData(_array_arg(vertices, "vertices", path, float), _array_arg(faces, "faces", path, int),
                        None if normals is None else _array_arg(normals, "normals", path, float),
                        None if normal_faces is None else _array_arg(normal_faces, "normal_faces", path, int))
        validate_mesh(data, path)
        if smooth and data.normals is None:
            raise MeshError(f"{path}: smooth shading needs vertex normals, and the mesh has none")
        # vertices of each face sorted by index (so shared edges are evaluated identically, see `triangle_edges`);
        # the winding lost by sorting is kept as +-1 per face (an odd permutation flips the normal)
        perm = np.argsort(data.faces, axis=1, kind="stable")
        faces = np.take_along_axis(data.faces, perm, axis=1)
        wind = np.where((perm[:, 0] < perm[:, 1]) ^ (perm[:, 1] < perm[:, 2]) ^ (perm[:, 0] < perm[:, 2]), 1.0, -1.0)
        tri = data.vertices[faces]
        bvh = build_bvh(tri)
        slot_ok = bvh.order >= 0
        safe = np.where(slot_ok, bvh.order, 0)

        def per_leaf(x):  # (faces, 3, 3) -> (leaves, 3, 3, 4), unused slots zero
            x = np.where(slot_ok[:, None, None], x.astype(np.float32)[safe], 0.0).astype(np.float32)
            return jnp.asarray(np.ascontiguousarray(x.reshape(-1, WIDTH, 3, 3).transpose(0, 2, 3, 1)))

        nf = data.faces if data.normal_faces is None else data.normal_faces
        vn = per_leaf(data.normals[np.take_along_axis(nf, perm, axis=1)]) if smooth else None
        w = np.where(slot_ok, wind[safe], 1.0).astype(np.float32).reshape(-1, WIDTH)
        return cls(rows=jnp.asarray(bvh.rows), vn=vn, wind=jnp.asarray(w),
                   face=jnp.asarray(bvh.order.astype(np.int32)), bsdf=bsdf, root=bvh.root, box=bvh.box,
                   stack_size=max(1, (WIDTH - 1) * bvh.depth), n_leaves=bvh.n_leaves,
                   n_faces=int(data.faces.shape[0]))

    @classmethod
    def from_file(cls, path, bsdf, to_world=None, smooth: bool = False) -> "Mesh":
        """A mesh from an OBJ/PLY file, with an optional `to_world` (a 4x4 matrix or a scene file's transform
        dict, see `transform_matrix`)."""
        data = read_mesh_cached(path)
        m = to_world if isinstance(to_world, np.ndarray) else transform_matrix(to_world)
        data = apply_transform(data, m)
        return cls.from_arrays(data.vertices, data.faces, bsdf, data.normals, smooth, os.fspath(path),
                               normal_faces=data.normal_faces)


# ------------------------------------------------------------------------------------------------- intersection
class RayFrame(NamedTuple):
    """The per-ray part of the watertight test: origin, one-hot rows picking the sheared axes, and the shear."""

    o: Float[Array, "3"]
    ex: Float[Array, "3"]
    ey: Float[Array, "3"]
    ez: Float[Array, "3"]
    sx: Float[Array, ""]
    sy: Float[Array, ""]
    sz: Float[Array, ""]


def ray_frame(o, d) -> RayFrame:
    """Woop et al.'s ray set-up: `kz` the dominant axis of `d`, `kx`, `ky` the others; shear `S = (d_kx / d_kz,
    d_ky / d_kz, 1 / d_kz)`. Axes are picked by one-hot rows (exact: sums with zeros), not gathers."""
    kz = jnp.argmax(jnp.abs(d))
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    ax = jnp.arange(3)
    ex, ey, ez = ((ax == k).astype(d.dtype) for k in (kx, ky, kz))
    dz = dot(d, ez)
    return RayFrame(o, ex, ey, ez, dot(d, ex) / dz, dot(d, ey) / dz, 1.0 / dz)


def triangle_edges(rf: RayFrame, tris):
    """Edge functions `(U, V, W)` and `(det, T)` of the watertight test for triangles `tris` (3 vertices, 3 coords,
    K) (structure of arrays: measured 50x faster on a CPU than (K, 3, 3)): the hit is at `t = T / det` with
    barycentrics `(U, V, W) / det` of `(v0, v1, v2)`.

    Each vertex is sheared on its own, and an edge's function uses only its two vertices, always in the same
    order (the first has the lower index in the file: `Mesh` stores each triangle's vertices sorted by index, with
    the winding kept in `Mesh.wind`), so two triangles sharing an edge compute bit-identical values, and a ray
    through the edge is inside one of them. The fixed order matters: XLA contracts `a b - c d` into a fused
    multiply-add, after which `f(P, Q)` is no longer exactly `-f(Q, P)` (measured: 2% of rays through the vertices
    of a closed mesh leaked with the textbook order)."""
    X, Y, Z = [], [], []
    for i in range(3):
        px, py, pz = tris[i, 0] - rf.o[0], tris[i, 1] - rf.o[1], tris[i, 2] - rf.o[2]
        a_x = px * rf.ex[0] + py * rf.ex[1] + pz * rf.ex[2]
        a_y = px * rf.ey[0] + py * rf.ey[1] + pz * rf.ey[2]
        a_z = px * rf.ez[0] + py * rf.ez[1] + pz * rf.ez[2]
        X.append(a_x - rf.sx * a_z)
        Y.append(a_y - rf.sy * a_z)
        Z.append(rf.sz * a_z)
    (Ax, Bx, Cx), (Ay, By, Cy) = X, Y

    def edge(P, Q):  # the edge function of the edge from P to Q: always with P the vertex of lower file index
        return P[0] * Q[1] - P[1] * Q[0]

    A, B, C = (Ax, Ay), (Bx, By), (Cx, Cy)
    U = -edge(B, C)
    V = edge(A, C)
    W = -edge(A, B)
    det = U + V + W
    T = U * Z[0] + V * Z[1] + W * Z[2]
    return U, V, W, det, T


def intersect_triangles(rf: RayFrame, tris, t_max):
    """Hit distances (in `(T_MIN, t_max)`, else inf) of the ray with triangles `tris` (3, 3, K); both faces hit.
    A ray through a shared edge or vertex hits (edge functions of 0 count as inside)."""
    U, V, W, det, T = triangle_edges(rf, tris)
    inside = ((U >= 0) & (V >= 0) & (W >= 0)) | ((U <= 0) & (V <= 0) & (W <= 0))
    ok = inside & (det != 0)
    t = T / jnp.where(ok, det, 1.0)
    return jnp.where(ok & (t > T_MIN) & (t < t_max), t, jnp.inf)


class _Walk(NamedTuple):
    """One ray's traversal state: `cur` the row to visit next (-1: done), the stack of rows still to visit (`sp`
    entries), the nearest hit so far (`t_best`, `slot`, -1 for none) and the ray (its frame and inverse
    direction)."""

    cur: Int[Array, ""]
    stack: Int[Array, "S"]
    sp: Int[Array, ""]
    t_best: Float[Array, ""]
    slot: Int[Array, ""]
    rf: RayFrame
    inv_d: Float[Array, "3"]


def _walk_start(root: int, S: int, box: tuple, o, d, t_max) -> _Walk:
    """A ray's walk from the root; a ray that misses the whole mesh's box `(lo, hi)` before `t_max` is done at once
    (no step: under `vmap` the batch's first, full-width stage then runs only if enough rays remain). The box
    contains every child box, and the rounding of the slab test is monotonic, so no ray that hits a child box
    misses it."""
    tiny = jnp.float32(1e-30)
    inv_d = 1.0 / jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d)
    t_max = jnp.asarray(t_max, jnp.float32)
    lo, hi = np.asarray(box[:3], np.float32), np.asarray(box[3:], np.float32)
    t0, t1 = (lo - o) * inv_d, (hi - o) * inv_d
    tn = jnp.max(jnp.minimum(t0, t1))
    tf = jnp.min(jnp.maximum(t0, t1)) * _BOX_SLACK
    hit = (tn <= tf) & (tf > T_MIN) & (tn < t_max)
    return _Walk(jnp.where(hit, jnp.int32(root), -1), jnp.full(S, -1, jnp.int32), jnp.int32(0), t_max,
                 jnp.int32(-1), ray_frame(o, d), inv_d)


def _cswap(a, b):
    """Compare-exchange of (key, row) pairs by key."""
    swap = b[0] < a[0]
    return ((jnp.where(swap, b[0], a[0]), jnp.where(swap, b[1], a[1])),
            (jnp.where(swap, a[0], b[0]), jnp.where(swap, a[1], b[1])))


def _walk_step(rows, n_leaves: int, any_hit: bool, w: _Walk) -> _Walk:
    """One traversal step of one ray: read the row `cur` (one gather). A leaf: test its 4 triangles, keep the
    nearest hit. A node: test its 4 child boxes (one vector slab test), go to the nearest child hit and push the
    others, farther first (so they pop nearest first); with none hit, pop the stack. A done ray (`cur` -1) is left
    as it is. With `any_hit`, the first hit ends the walk."""
    active = w.cur >= 0
    r = rows[jnp.maximum(w.cur, 0)]
    is_leaf = w.cur < n_leaves
    o = w.rf.o
    # node: the 4 child boxes, (axis, child)
    lo, hi, ref = r[0:12].reshape(3, WIDTH), r[12:24].reshape(3, WIDTH), r[24:28]
    t0 = (lo - o[:, None]) * w.inv_d[:, None]
    t1 = (hi - o[:, None]) * w.inv_d[:, None]
    tn = jnp.max(jnp.minimum(t0, t1), axis=0)
    tf = jnp.min(jnp.maximum(t0, t1), axis=0) * _BOX_SLACK
    ok = (ref >= 0) & (tn <= tf) & (tf > T_MIN) & (tn < w.t_best)
    key = jnp.where(ok, jnp.maximum(tn, 0.0), jnp.inf)
    refi = ref.astype(jnp.int32)
    e = [(key[k], refi[k]) for k in range(WIDTH)]
    e[0], e[1] = _cswap(e[0], e[1])  # a sorting network on 4: (0,1) (2,3) (0,2) (1,3) (1,2)
    e[2], e[3] = _cswap(e[2], e[3])
    e[0], e[2] = _cswap(e[0], e[2])
    e[1], e[3] = _cswap(e[1], e[3])
    e[1], e[2] = _cswap(e[1], e[2])
    n_hit = jnp.sum(ok.astype(jnp.int32))
    # leaf: its 4 triangles
    tt = intersect_triangles(w.rf, r.reshape(3, 3, WIDTH), w.t_best)
    k = jnp.argmin(tt)
    better = active & is_leaf & (tt[k] < w.t_best)
    t_best = jnp.where(better, tt[k], w.t_best)
    slot = jnp.where(better, w.cur * WIDTH + k.astype(jnp.int32), w.slot)
    # next row: descend to the nearest child hit, pushing the m others; or pop. The stack is written and read with
    # masks over its slots (elementwise; a per-lane scatter is slow under vmap): slots sp, sp + 1, sp + 2 get
    # children m, m - 1, m - 2 (farthest first); the writes past sp + m - 1, and all writes when popping, land
    # above the new top, where nothing live is kept, so they need no mask.
    descend = ~is_leaf & (n_hit > 0)
    m = n_hit - 1
    slots = jnp.arange(w.stack.shape[0], dtype=jnp.int32)
    q = slots - w.sp
    v0 = jnp.where(m == 3, e[3][1], jnp.where(m == 2, e[2][1], e[1][1]))
    v1 = jnp.where(m == 3, e[2][1], e[1][1])
    stack = jnp.where(q == 0, v0, jnp.where(q == 1, v1, jnp.where(q == 2, e[1][1], w.stack)))
    top = jnp.max(jnp.where(slots == w.sp - 1, w.stack, -1))
    nxt = jnp.where(descend, e[0][1], top)
    sp = jnp.where(descend, w.sp + m, jnp.maximum(w.sp - 1, 0))
    if any_hit:
        nxt = jnp.where(slot >= 0, -1, nxt)
    # a done ray's stack and stack pointer are dead: only its hit is kept
    return w._replace(cur=jnp.where(active, nxt, -1), stack=stack, sp=sp, t_best=t_best, slot=slot)


def _walk_one(rows, o, d, t_max, *, root, S, box, n_leaves, any_hit):
    """One ray's traversal: `_walk_step` in a `lax.while_loop` until the stack is empty."""
    w = jax.lax.while_loop(lambda w: w.cur >= 0, functools.partial(_walk_step, rows, n_leaves, any_hit),
                           _walk_start(root, S, box, o, d, t_max))
    return w.t_best, w.slot


_MIN_WIDTH = 16
"""The narrowest stage of the batched traversal (`_walk_batch`): each stage is one more loop to compile (seconds on a
CPU), and below this few lanes are left to gain from."""

_SHRINK = 4
"""Each stage of the batched traversal has this many times fewer lanes than the one before."""


def _stage_widths(n: int) -> list[int]:
    """Lane counts of the batched traversal's stages: `n`, then `1 / _SHRINK` of the previous (rounded up) while that
    is at least `_MIN_WIDTH`: 1024 rays run in stages of 1024, 256, 64 and 16 lanes, 48 rays in one."""
    widths = [n]
    while -(-widths[-1] // _SHRINK) >= _MIN_WIDTH:
        widths.append(-(-widths[-1] // _SHRINK))
    return widths


def _walk_batch(rows, O, D, TM, *, root, S, box, n_leaves, any_hit):
    """Traversal of a batch of rays `O`, `D` (n, 3), `TM` (n,) with lane compaction: a vectorized while loop runs
    all lanes until at most a quarter of them are still walking; those are gathered into a batch of a quarter the
    size, and so on down to `_MIN_WIDTH` lanes, which run until all are done. A vectorized while loop costs as many
    full-width steps as its slowest lane needs; compaction makes the few long walks (rays grazing many boxes) run
    narrow. The results equal the per-ray walk's (`_walk_one`): the same steps, lane by lane."""
    n = O.shape[0]
    step = jax.vmap(functools.partial(_walk_step, rows, n_leaves, any_hit))
    w = jax.vmap(functools.partial(_walk_start, root, S, box))(O, D, TM)
    lane = jnp.arange(n, dtype=jnp.int32)
    t_out, slot_out = w.t_best, w.slot
    widths = _stage_widths(n)
    for i, width in enumerate(widths):
        if i > 0:  # the walking lanes first (at most `width` of them), then done ones
            pick = jnp.argsort(w.cur < 0, stable=True)[:width]
            w = jax.tree.map(lambda x: x[pick], w)
            lane = lane[pick]
        stop = widths[i + 1] if i + 1 < len(widths) else 0
        w = jax.lax.while_loop(lambda w: jnp.sum((w.cur >= 0).astype(jnp.int32)) > stop, step, w)
        t_out = t_out.at[lane].set(w.t_best, unique_indices=True)
        slot_out = slot_out.at[lane].set(w.slot, unique_indices=True)
    return t_out, slot_out


@functools.lru_cache(maxsize=None)
def _walker(root: int, S: int, box: tuple, n_leaves: int, any_hit: bool):
    """The traversal `(rows, o, d, t_max) -> (t, slot)` of one ray, with a batching rule (`custom_vmap`): under
    `vmap` over rays it runs `_walk_batch` (lane compaction) instead of a vectorized per-ray loop."""
    kw = dict(root=root, S=S, box=box, n_leaves=n_leaves, any_hit=any_hit)
    one = functools.partial(_walk_one, **kw)
    walk = jax.custom_batching.custom_vmap(one)

    @walk.def_vmap
    def _rule(axis_size, in_batched, rows, o, d, t_max):
        rb, ob, db, tb = in_batched
        if rb:  # a batch of meshes: the plain vectorized walk
            axes = tuple(0 if b else None for b in in_batched)
            return jax.vmap(one, in_axes=axes)(rows, o, d, t_max), (True, True)
        O = o if ob else jnp.broadcast_to(o, (axis_size, 3))
        D = d if db else jnp.broadcast_to(d, (axis_size, 3))
        TM = t_max if tb else jnp.broadcast_to(t_max, (axis_size,))
        return _walk_batch(rows, O, D, TM, **kw), (True, True)

    return walk


def _traverse(mesh: Mesh, o, d, t_max, any_hit: bool):
    """Nearest hit (or, with `any_hit`, whether any hit) with `t < t_max`: `(t, slot)`; `slot` -1 on a miss.
    Runs on stop-gradient inputs (no derivative flows through it); under `vmap`, batched with lane compaction."""
    o, d, t_max = jax.lax.stop_gradient((jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32),
                                         jnp.asarray(t_max, jnp.float32)))
    rows = jax.lax.stop_gradient(mesh.rows)
    return _walker(mesh.root, mesh.stack_size, mesh.box, mesh.n_leaves, any_hit)(rows, o, d, t_max)


def mesh_nearest(mesh: Mesh, o, d, t_max=jnp.inf):
    """Nearest hit with the mesh: `(t, slot)` (inf and -1 on a miss), not differentiated (see `mesh_hit`)."""
    return _traverse(mesh, o, d, t_max, any_hit=False)


def mesh_occluded(mesh: Mesh, o, d, dist) -> Array:
    """Whether the mesh blocks the segment from `o` along unit `d` before `dist` (any hit, early out)."""
    _, slot = _traverse(mesh, o, d, dist, any_hit=True)
    return slot >= 0


def mesh_hit(mesh: Mesh, o, d, slot):
    """Differentiable distance and front normal `(t, n)` at the hit triangle `slot` (>= 0): `t` from the
    triangle's plane, `n` its geometric normal, or the interpolated vertex normals (smooth meshes), flipped to the
    geometric front side's hemisphere so that it stays a front normal."""
    L = WIDTH
    tri = jax.lax.stop_gradient(mesh.rows[slot // L].reshape(3, 3, L)[:, :, slot % L])
    ng = cross(tri[1] - tri[0], tri[2] - tri[0]) * jax.lax.stop_gradient(mesh.wind[slot // L, slot % L])
    t = safe_div(dot(tri[0] - o, ng), dot(d, ng))
    n = safe_normalize(ng)
    if mesh.vn is not None:
        U, V, W, det, _ = triangle_edges(ray_frame(*jax.lax.stop_gradient((o, d))), tri[:, :, None])
        b = jnp.stack([U[0], V[0], W[0]]) / jnp.where(det[0] != 0, det[0], 1.0)
        vn = jax.lax.stop_gradient(mesh.vn[slot // L, :, :, slot % L])
        ns = safe_normalize(b[0] * vn[0] + b[1] * vn[1] + b[2] * vn[2])
        n = jnp.where(dot(ns, n) > 0, ns, n)
    return t, n


def brute_force_nearest(mesh: Mesh, o, d, t_max=jnp.inf):
    """`mesh_nearest` without the BVH: every triangle (reference and benchmark)."""
    o, d = jax.lax.stop_gradient((o, d))
    tris = jax.lax.stop_gradient(mesh.leaves).transpose(1, 2, 0, 3).reshape(3, 3, -1)
    tt = intersect_triangles(ray_frame(o, d), tris, t_max)
    k = jnp.argmin(tt)
    return tt[k], jnp.where(jnp.isfinite(tt[k]), k, -1).astype(jnp.int32)
