"""Triangle meshes: reading OBJ and PLY files, validation, a BVH built on the host, and its traversal in JAX.

- Files: `read_mesh(path)` reads Wavefront OBJ (`v`, `vn`, `f`; polygons fan-triangulated; negative, i.e. relative,
  indices) and PLY (ASCII, binary little- and big-endian; `vertex` x, y, z and optional nx, ny, nz; `face`
  `vertex_indices`/`vertex_index` lists, polygons fan-triangulated) with small hand-written readers: numpy only, no
  new dependency. `write_ply` writes binary little-endian PLY (the format Mitsuba's `ply` shape reads).
- Front faces are counter-clockwise seen from the front (as in Mitsuba and PLY): the geometric normal of the triangle
  `(v0, v1, v2)` is `normalize(cross(v1 - v0, v2 - v0))`. Normals are flat (per face) unless `smooth=True` and the
  file has vertex normals: then the shading normal is the barycentric interpolation of the vertex normals.
- The BVH (`build_bvh`) is binary, split at the object median along the longest axis of the centroids' bounds, with
  full leaves of `leaf_size` triangles (the last one padded with degenerate triangles that never hit): its depth is
  `ceil(log2(n_leaves))`, so the traversal's stack size is known when the mesh is built. Each node stores its two
  children's boxes, so one traversal step tests both boxes (nearer child first) or one leaf's triangles.
- Ray/triangle intersection is watertight (Woop, Benthin, Wald 2013, "Watertight Ray/Triangle Intersection", JCGT
  2(1)): vertices are sheared into a ray-aligned frame and tested with 2-D edge functions that two triangles sharing
  an edge compute with the same operands, so a ray through a shared edge or vertex hits at least one of them.
- Geometry is fixed (not differentiated): the traversal runs under `stop_gradient` in a `lax.while_loop`, returns the
  hit triangle's slot, and the differentiable quantities (distance along the ray from the hit triangle's plane, its
  normal) are recomputed from that triangle alone, so medium, light and BSDF parameters differentiate in forward and
  reverse mode as in analytic scenes.
"""

from __future__ import annotations

import functools
import math
import os
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._bsdf import AbstractBSDF
from ._math import cross, dot, safe_div, safe_normalize

__all__ = ["Mesh", "MeshError", "MeshData", "read_mesh", "write_ply", "build_bvh", "transform_matrix"]

T_MIN = 1e-4
"""Smallest accepted hit distance (scene units), as for the analytic shapes (`_shapes.T_MIN`)."""

LEAF_SIZE = 4
"""Triangles per BVH leaf (default). Measured in `benchmarks/bench_mesh.py` (4 was faster than 8 on a 2-core CPU)."""

_BOX_SLACK = 1.0 + 4.0 * 2.0**-24 * 3
"""Factor on a box's exit distance: covers the float32 rounding of the slab test (pbrt-v4's `1 + 2 gamma(3)`, with
room), so a box never misses a ray that hits a triangle inside it."""


class MeshError(ValueError):
    """A mesh file is missing, unreadable or invalid; the message names the file."""


class MeshData(NamedTuple):
    """A mesh as read from a file: `vertices` (V, 3) float64, `faces` (F, 3) int64 (counter-clockwise = front),
    `normals` (V, 3) float64 vertex normals, or None when the file has none."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None


# ------------------------------------------------------------------------------------------------------- readers
def _fan(polys) -> list:
    """Fan-triangulate polygons (lists of vertex indices)."""
    tris = []
    for p in polys:
        for k in range(1, len(p) - 1):
            tris.append((p[0], p[k], p[k + 1]))
    return tris


def _read_obj(path: str) -> MeshData:
    verts, norms, polys = [], [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            tag = parts[0]
            try:
                if tag == "v":
                    verts.append([float(x) for x in parts[1:4]])
                    if len(parts) < 4:
                        raise ValueError("a vertex needs 3 coordinates")
                elif tag == "vn":
                    norms.append([float(x) for x in parts[1:4]])
                elif tag == "f":
                    if len(parts) < 4:
                        raise ValueError("a face needs at least 3 vertices")
                    idx = []
                    for tok in parts[1:]:
                        i = int(tok.split("/")[0])
                        if i == 0:
                            raise ValueError("OBJ indices start at 1 (0 is invalid)")
                        idx.append(i - 1 if i > 0 else len(verts) + i)  # negative: relative to the vertices so far
                    polys.append(idx)
            except ValueError as e:
                raise MeshError(f"{path}: line {lineno}: cannot parse {line.strip()!r}: {e}") from None
    v = np.asarray(verts, np.float64).reshape(-1, 3)
    f = np.asarray(_fan(polys), np.int64).reshape(-1, 3)
    n = np.asarray(norms, np.float64).reshape(-1, 3) if len(norms) == len(verts) and norms else None
    return MeshData(v, f, n)


_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def _read_ply(path: str) -> MeshData:
    with open(path, "rb") as fh:
        raw = fh.read()
    if not raw.startswith(b"ply"):
        raise MeshError(f"{path}: not a PLY file (no 'ply' magic)")
    end = raw.find(b"end_header")
    if end < 0:
        raise MeshError(f"{path}: PLY header has no end_header")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []  # elements: [name, count, [(name, dtype) or (name, (count_dtype, item_dtype))]]
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
    data = {}
    if fmt == "ascii":
        tokens = raw[body_start:].split()
        pos = 0
        try:
            for name, count, props in elements:
                rows = []
                for _ in range(count):
                    row = {}
                    for pname, dt in props:
                        if isinstance(dt, tuple):
                            k = int(tokens[pos])
                            row[pname] = [float(x) for x in tokens[pos + 1:pos + 1 + k]]
                            pos += 1 + k
                        else:
                            row[pname] = float(tokens[pos])
                            pos += 1
                    rows.append(row)
                data[name] = rows
        except (IndexError, ValueError):
            raise MeshError(f"{path}: PLY data ends early or holds a non-number") from None
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
            raise MeshError(f"{path}: PLY data ends early or is malformed") from None
        if v is None:
            v = np.zeros((0, 3))
    faces = polys if isinstance(polys, np.ndarray) else np.asarray(_fan(polys), np.int64).reshape(-1, 3)
    return MeshData(np.asarray(v, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3), n)


def _read_binary_lists(buf, pos, count, props, bo):
    """Binary PLY element with list properties. Fast path: every list has the same length as the first record's
    (all triangles); otherwise record by record."""
    out = {}
    # fast path: fixed-length lists, checked afterwards
    fields, k0, p = [], {}, pos
    for pname, dt in props:
        if isinstance(dt, tuple):
            cdt, idt = dt
            k = int(np.frombuffer(buf, bo + cdt, 1, p)[0]) if count else 0
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
    if mesh.normals is not None and not np.all(np.isfinite(mesh.normals)):
        raise MeshError(f"{path}: vertex normals are not finite")


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
    winding so that front faces stay front faces (as Mitsuba does)."""
    m = np.asarray(m, np.float64)
    v = mesh.vertices @ m[:3, :3].T + m[:3, 3]
    n = None
    if mesh.normals is not None:
        n = mesh.normals @ np.linalg.inv(m[:3, :3])
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    f = mesh.faces if np.linalg.det(m[:3, :3]) > 0 else mesh.faces[:, ::-1]
    return MeshData(v, f, n)


# -------------------------------------------------------------------------------------------------------- the BVH
class BVH(NamedTuple):
    """Host BVH arrays. `order` (F,): the input face of each leaf slot (-1 for padding); `child_lo`, `child_hi`
    (N, 2, 3) float32: the boxes of each node's two children; `child` (N, 2) int32: a child reference, `>= 0` an
    internal node, `< 0` the leaf `-(ref + 1)` whose triangles are slots `leaf * leaf_size ...`; `root`: the root's
    reference; `depth`: the deepest leaf's depth (number of internal nodes above it)."""

    order: np.ndarray
    child_lo: np.ndarray
    child_hi: np.ndarray
    child: np.ndarray
    root: int
    depth: int
    leaf_size: int


def build_bvh(tris, leaf_size: int = LEAF_SIZE) -> BVH:
    """Binary BVH over triangles `tris` (F, 3, 3), split at the object median along the longest axis of the
    centroid bounds; leaves hold exactly `leaf_size` slots (the last one padded). Boxes are the float32 bounds
    rounded outward."""
    tris = np.asarray(tris, np.float64)
    F = tris.shape[0]
    lo_t, hi_t = tris.min(axis=1), tris.max(axis=1)
    cen = tris.mean(axis=1)
    n_leaves = -(-F // leaf_size)
    order = np.full(n_leaves * leaf_size, -1, np.int64)
    child_lo, child_hi, child = [], [], []
    leaf_count = [0]

    def bounds(idx):
        lo = np.nextafter(lo_t[idx].min(axis=0).astype(np.float32), np.float32(-np.inf))
        hi = np.nextafter(hi_t[idx].max(axis=0).astype(np.float32), np.float32(np.inf))
        return lo, hi

    def make_leaf(idx):
        leaf = leaf_count[0]
        leaf_count[0] += 1
        order[leaf * leaf_size:leaf * leaf_size + len(idx)] = idx
        return -(leaf + 1)

    # iterative build (explicit stack): internal nodes are numbered in creation order, leaves in depth-first order
    if F <= leaf_size:
        return BVH(order, np.zeros((1, 2, 3), np.float32), np.zeros((1, 2, 3), np.float32),
                   np.full((1, 2), -1, np.int32), make_leaf(np.arange(F)), 0, leaf_size)
    depth = 0
    # node slots are allocated when the node is created; children filled when split
    stack = [(np.arange(F), None, 0, 0)]  # (faces, parent, side, depth)
    root = None
    while stack:
        idx, parent, side, dep = stack.pop()
        if len(idx) <= leaf_size:
            ref = make_leaf(idx)
        else:
            ref = len(child)
            child.append([0, 0])
            child_lo.append(np.zeros((2, 3), np.float32))
            child_hi.append(np.zeros((2, 3), np.float32))
            c = cen[idx]
            axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
            # left gets a whole number of full leaves: only the very last leaf can be partly empty
            n_left = leaf_size * (-(-len(idx) // (2 * leaf_size)))
            part = np.argpartition(c[:, axis], n_left - 1) if n_left < len(idx) else np.arange(len(idx))
            left, right = idx[part[:n_left]], idx[part[n_left:]]
            for s, sub in ((0, left), (1, right)):
                child_lo[ref][s], child_hi[ref][s] = bounds(sub)
            depth = max(depth, dep + 1)
            stack.append((right, ref, 1, dep + 1))
            stack.append((left, ref, 0, dep + 1))
        if parent is None:
            root = ref
        else:
            child[parent][side] = ref
    return BVH(order, np.asarray(child_lo, np.float32), np.asarray(child_hi, np.float32),
               np.asarray(child, np.int32), int(root), int(depth), leaf_size)


# -------------------------------------------------------------------------------------------------------- the Module
class Mesh(eqx.Module):
    """A triangle mesh with its BVH and its `bsdf` (any BSDF; one-sided BSDFs work on the front faces, which are
    counter-clockwise seen from the front).

    Build it with `Mesh.from_arrays(vertices, faces, bsdf, normals=None, smooth=False)` or `Mesh.from_file(path,
    bsdf, to_world=None, smooth=False)`. The geometry is fixed once built (its arrays are the BVH's leaf order and
    are not differentiated); replacing its BSDF values with `eqx.tree_at` is fine.

    **Fields:** `leaves` (leaves, 3 vertices, 3 coordinates, leaf_size): world-space vertices of each leaf's
    triangles, one contiguous row per leaf (slot `s` is leaf `s // leaf_size`, lane `s % leaf_size`; padding slots
    are zero and never hit); each triangle's vertices are sorted by their index in the file, `wind` (leaves,
    leaf_size) is +1 where that kept the file's winding and -1 where it reversed it; `vn`: vertex normals in the
    same layout, or None (flat normals); `boxes` (nodes, 2
    children, lo/hi, 3) and `child` (nodes, 2): the BVH nodes (see `BVH`); `face` (slots,): the file's face index
    of each slot (-1 for padding); static `root`, `stack_size`, `leaf_size`, `n_faces`.
    """

    leaves: Float[Array, "Nl 3 3 L"]
    vn: Float[Array, "Nl 3 3 L"] | None
    wind: Float[Array, "Nl L"]
    boxes: Float[Array, "N 2 2 3"]
    child: Int[Array, "N 2"]
    face: Int[Array, "S"]
    bsdf: AbstractBSDF
    root: int = eqx.field(static=True)
    stack_size: int = eqx.field(static=True)
    leaf_size: int = eqx.field(static=True)
    n_faces: int = eqx.field(static=True)

    @classmethod
    def from_arrays(cls, vertices, faces, bsdf, normals=None, smooth: bool = False,
                    leaf_size: int = LEAF_SIZE, path: str = "<mesh>") -> "Mesh":
        """A mesh from world-space `vertices` (V, 3), `faces` (F, 3) and optional vertex `normals` (V, 3); smooth
        shading normals when `smooth` and normals are given (else flat). Validated (`MeshError`)."""
        data = MeshData(np.asarray(vertices, np.float64).reshape(-1, 3), np.asarray(faces, np.int64).reshape(-1, 3),
                        None if normals is None else np.asarray(normals, np.float64).reshape(-1, 3))
        validate_mesh(data, path)
        if smooth and data.normals is None:
            raise MeshError(f"{path}: smooth shading needs vertex normals, and the mesh has none")
        # vertices of each face sorted by index (so shared edges are evaluated identically, see `triangle_edges`);
        # the winding lost by sorting is kept as +-1 per face (an odd permutation flips the normal)
        perm = np.argsort(data.faces, axis=1, kind="stable")
        faces = np.take_along_axis(data.faces, perm, axis=1)
        wind = np.where((perm[:, 0] < perm[:, 1]) ^ (perm[:, 1] < perm[:, 2]) ^ (perm[:, 0] < perm[:, 2]), 1.0, -1.0)
        tri = data.vertices[faces]
        bvh = build_bvh(tri, leaf_size)
        slot_ok = bvh.order >= 0
        safe = np.where(slot_ok, bvh.order, 0)
        def per_leaf(x):  # (slots, 3, 3) -> (leaves, 3, 3, leaf_size), padding slots zero
            x = np.where(slot_ok[:, None, None], x.astype(np.float32)[safe], 0.0).astype(np.float32)
            return jnp.asarray(np.ascontiguousarray(x.reshape(-1, leaf_size, 3, 3).transpose(0, 2, 3, 1)))

        vn = per_leaf(data.normals[faces]) if smooth else None
        boxes = np.stack([bvh.child_lo, bvh.child_hi], axis=2)
        w = np.where(slot_ok, wind[safe], 1.0).astype(np.float32).reshape(-1, leaf_size)
        return cls(leaves=per_leaf(tri), vn=vn, wind=jnp.asarray(w), boxes=jnp.asarray(boxes),
                   child=jnp.asarray(bvh.child),
                   face=jnp.asarray(bvh.order.astype(np.int32)), bsdf=bsdf, root=bvh.root,
                   stack_size=max(1, bvh.depth + 1), leaf_size=leaf_size, n_faces=int(data.faces.shape[0]))

    @classmethod
    def from_file(cls, path, bsdf, to_world=None, smooth: bool = False, leaf_size: int = LEAF_SIZE) -> "Mesh":
        """A mesh from an OBJ/PLY file, with an optional `to_world` (a 4x4 matrix or a scene file's transform
        dict, see `transform_matrix`)."""
        data = read_mesh_cached(path)
        m = to_world if isinstance(to_world, np.ndarray) else transform_matrix(to_world)
        data = apply_transform(data, m)
        return cls.from_arrays(data.vertices, data.faces, bsdf, data.normals, smooth, leaf_size, os.fspath(path))


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


def _slab(rf_o, inv_d, lo, hi, t_max):
    """Entry distance of the ray into boxes (lo, hi) (..., 3), inf when missed or entered beyond `t_max`."""
    t0 = (lo - rf_o[None, :]) * inv_d[None, :]
    t1 = (hi - rf_o[None, :]) * inv_d[None, :]
    tn = jnp.max(jnp.minimum(t0, t1), axis=-1)
    tf = jnp.min(jnp.maximum(t0, t1), axis=-1) * _BOX_SLACK
    hit = (tn <= tf) & (tf > T_MIN) & (tn < t_max)
    return jnp.where(hit, jnp.maximum(tn, 0.0), jnp.inf)


_EMPTY = np.int32(2**31 - 1)
"""The traversal's 'no node' reference: the stack is empty and the ray is done."""


def _traverse(mesh: Mesh, o, d, t_max, any_hit: bool):
    """Nearest hit (or, with `any_hit`, whether any hit) with `t < t_max`: `(t, slot)`; `slot` -1 on a miss.

    Stack-based traversal in a `lax.while_loop`: the current node reference `cur`; an internal node tests both
    children's boxes and goes to the nearer one hit, pushing the farther; a leaf tests its `leaf_size` triangles;
    then the next reference comes from the stack. Runs on stop-gradient inputs (no derivative flows through it)."""
    o, d, t_max = jax.lax.stop_gradient((o, d, t_max))
    leaves, boxes, child = jax.lax.stop_gradient((mesh.leaves, mesh.boxes, mesh.child))
    rf = ray_frame(o, d)
    tiny = jnp.float32(1e-30)
    inv_d = 1.0 / jnp.where(jnp.abs(d) < tiny, jnp.where(d < 0, -tiny, tiny), d)
    L, S = mesh.leaf_size, mesh.stack_size
    lane = jnp.arange(L, dtype=jnp.int32)
    slots = jnp.arange(S, dtype=jnp.int32)

    def cond(c):
        cur, _, _, t_best, slot = c
        go = cur != _EMPTY
        return go & (slot < 0) if any_hit else go

    def body(c):
        cur, stack, sp, t_best, slot = c
        is_leaf = cur < 0
        node = jnp.maximum(cur, 0)
        leaf = jnp.maximum(-cur - 1, 0)
        # internal node: both children's boxes
        box = boxes[node]
        tn = _slab(o, inv_d, box[:, 0], box[:, 1], t_best)
        h0, h1 = jnp.isfinite(tn[0]), jnp.isfinite(tn[1])
        c0, c1 = child[node, 0], child[node, 1]
        first_is_0 = tn[0] <= tn[1]
        near = jnp.where(first_is_0, c0, c1)
        far = jnp.where(first_is_0, c1, c0)
        # leaf: its triangles
        base = leaf * L
        tt = intersect_triangles(rf, leaves[leaf], t_best)
        k = jnp.argmin(tt)
        t_leaf = tt[k]
        better = is_leaf & (t_leaf < t_best)
        t_best = jnp.where(better, t_leaf, t_best)
        slot = jnp.where(better, base + lane[k], slot)
        # next node
        both = ~is_leaf & h0 & h1
        one = ~is_leaf & (h0 ^ h1)
        # the stack is updated and read with one-hot masks (elementwise; a per-lane scatter is slow under vmap)
        push = both & (sp < S)
        stack = jnp.where(push & (slots == sp), far, stack)
        sp_pushed = jnp.where(push, sp + 1, sp)
        top = jnp.sum(jnp.where(slots == sp_pushed - 1, stack, 0))
        popped = jnp.where(sp_pushed > 0, top, _EMPTY)
        nxt = jnp.where(both, near, jnp.where(one, jnp.where(h0, c0, c1), popped))
        sp_new = jnp.where(both | one, sp_pushed, jnp.maximum(sp_pushed - 1, 0))
        return nxt, stack, sp_new, t_best, slot

    init = (jnp.int32(mesh.root), jnp.zeros(S, jnp.int32), jnp.int32(0), jnp.asarray(t_max, jnp.float32),
            jnp.int32(-1))
    _, _, _, t_best, slot = jax.lax.while_loop(cond, body, init)
    return t_best, slot


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
    L = mesh.leaf_size
    tri = jax.lax.stop_gradient(mesh.leaves[slot // L, :, :, slot % L])
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
