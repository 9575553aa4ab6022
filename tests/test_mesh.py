"""Triangle meshes: the watertight ray/triangle test against float64, no leaks through shared edges and vertices, the
BVH against brute force, a tessellated sphere against the analytic one, a closed box around a light, gradients of a
mesh scene, the readers and one test per loading error."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfog as jf
from helpers import image_and_quadrant_means, jaxfog_and_mitsuba_images
from jaxfog._mesh import (
    WIDTH,
    MeshError,
    _stage_widths,
    brute_force_nearest,
    build_bvh,
    intersect_triangles,
    mesh_nearest,
    mesh_occluded,
    ray_frame,
    read_mesh,
    transform_matrix,
    write_ply,
)

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "data_synthetic"))
from make_mesh_fog import torus_mesh  # noqa: E402


# ------------------------------------------------------------------------------------------------ meshes
def uv_sphere(nu, nv, r=1.0, center=(0.0, 0.0, 0.0)):
    """A closed UV sphere with all vertices on the sphere (inscribed), fans at the poles, counter-clockwise
    outward: vertices (V, 3), faces (F, 3), vertex normals (V, 3)."""
    th = np.linspace(0, np.pi, nv + 1)[1:-1]
    ph = 2 * np.pi * np.arange(nu) / nu
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1).reshape(-1, 3)
    n = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]])
    f = []
    for j in range(nu):
        f.append([0, 1 + (j + 1) % nu, 1 + j])
    for i in range(nv - 2):
        for j in range(nu):
            a, b = 1 + i * nu + j, 1 + i * nu + (j + 1) % nu
            f += [[a, b, b + nu], [a, b + nu, a + nu]]
    last, base = len(n) - 1, 1 + (nv - 2) * nu
    for j in range(nu):
        f.append([last, base + j, base + (j + 1) % nu])
    f = np.asarray(f)
    tri = n[f]
    outward = np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1))
    assert np.all(outward > 0)
    return n * r + np.asarray(center), f, n


def box_mesh(lo, hi, k):
    """A closed axis-aligned box, each face a k x k grid of quads (2 triangles each), counter-clockwise outward."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    verts, faces, index = [], [], {}

    def vid(p):
        key = tuple(np.round(p, 12))
        if key not in index:
            index[key] = len(verts)
            verts.append(p)
        return index[key]

    g = np.linspace(0, 1, k + 1)
    for axis in range(3):
        for side in (0, 1):
            u_ax, v_ax = (axis + 1) % 3, (axis + 2) % 3
            for i in range(k):
                for j in range(k):
                    quad = []
                    for du, dv in ((0, 0), (1, 0), (1, 1), (0, 1)):
                        p = lo.copy()
                        p[axis] = hi[axis] if side else lo[axis]
                        p[u_ax] = lo[u_ax] + g[i + du] * (hi[u_ax] - lo[u_ax])
                        p[v_ax] = lo[v_ax] + g[j + dv] * (hi[v_ax] - lo[v_ax])
                        quad.append(vid(p))
                    a, b, c, d = quad if side else quad[::-1]
                    faces += [[a, b, c], [a, c, d]]
    return np.asarray(verts), np.asarray(faces)


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _per_ray(fn, *args):
    """`fn` over rays one at a time (`lax.map`: the per-ray traversal loop, without the batched walk's stages, each
    one more loop to compile)."""
    return jax.jit(lambda *a: jax.lax.map(lambda x: fn(*x), a))(*args)


# ------------------------------------------------------------------------------------------- ray/triangle
def _reference(o, d, tris):
    """float64 Möller–Trumbore: t (inf on a miss) and the smallest barycentric coordinate (signed margin)."""
    v0, v1, v2 = tris[:, 0], tris[:, 1], tris[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) / det
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", q, d) / det
    t = np.einsum("ij,ij->i", e2, q) / det
    margin = np.minimum(np.minimum(u, v), 1 - u - v)
    return np.where((margin >= 0) & (t > 1e-4), t, np.inf), margin, np.abs(det) / (
        np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))


def test_triangle_hits_agree_with_float64():
    """Random triangles and rays aimed at random points of their planes (inside and outside), 20% of them grazing
    (the direction within 1e-3 rad of the plane): hit/miss agrees with float64 except where the hit point lies
    within 1e-4 of an edge (barycentric margin), and the distances agree to 1e-5 + 2e-6 / |cos| relative (cos:
    between the ray and the normal)."""
    rng = np.random.default_rng(1)
    n = 4000
    tris = rng.normal(size=(n, 3, 3))
    bary = rng.uniform(-0.3, 1.1, size=(n, 2))
    target = tris[:, 0] + bary[:, :1] * (tris[:, 1] - tris[:, 0]) + bary[:, 1:] * (tris[:, 2] - tris[:, 0])
    nrm = _unit(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))
    d = _unit(rng.normal(size=(n, 3)))
    graze = rng.uniform(size=n) < 0.2
    in_plane = _unit(d - np.einsum("ij,ij->i", d, nrm)[:, None] * nrm)
    d = np.where(graze[:, None], _unit(in_plane + rng.uniform(-1e-3, 1e-3, (n, 1)) * nrm), d)
    o = target - rng.uniform(0.5, 3.0, (n, 1)) * d
    # the float32 inputs are the reference's inputs too
    tris, o, d = (np.asarray(x, np.float32).astype(np.float64) for x in (tris, o, d))
    t_ref, margin, _ = _reference(o, d, tris)
    f = jax.jit(jax.vmap(lambda o_, d_, tri: intersect_triangles(ray_frame(o_, d_), tri[:, :, None], jnp.inf)[0]))
    t = np.asarray(f(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32),
                     jnp.asarray(tris, jnp.float32)), np.float64)
    disagree = np.isfinite(t) != np.isfinite(t_ref)
    assert np.all(np.abs(margin[disagree]) < 1e-4), margin[disagree]
    assert disagree.mean() < 0.01
    both = np.isfinite(t) & np.isfinite(t_ref)
    rel = np.abs(t[both] - t_ref[both]) / t_ref[both]
    cos = np.abs(np.einsum("ij,ij->i", d, _unit(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))))[both]
    tol = 1e-5 + 2e-6 / cos  # float32 rounding of the plane distance, amplified by 1 / |cos| at grazing angles
    assert np.all(rel <= tol), (rel / tol).max()
    assert both.sum() > 0.2 * n and (both & graze).sum() > 100


@pytest.fixture(scope="module")
def torus():
    v, f = torus_mesh(48, 16)
    return v, f, jf.Mesh.from_arrays(v, f, jf.Diffuse(0.5))


def test_no_misses_through_shared_edges_and_vertices(torus):
    """A closed torus: rays from inside the tube (its centre circle) and from outside, aimed exactly at every
    vertex and at points on every edge (as float32 numbers: the ray passes through the shared edge or vertex),
    all hit (nearest-hit traversal) and all are occluded (any hit). (With the textbook edge-function order, 2% of
    the rays from inside leaked: see `jaxfog._mesh.triangle_edges`.)"""
    v, f, mesh = torus
    v32 = v.astype(np.float32).astype(np.float64)
    edges = np.unique(np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1), axis=0)
    rng = np.random.default_rng(2)
    s = rng.uniform(0, 1, (len(edges), 1))
    targets = np.concatenate([v32, v32[edges[:, 0]] * (1 - s) + v32[edges[:, 1]] * s,
                              0.5 * (v32[edges[:, 0]] + v32[edges[:, 1]])])
    phi = np.arctan2(targets[:, 2], targets[:, 0])
    inner = np.stack([0.55 * np.cos(phi), 0 * phi, 0.55 * np.sin(phi)], -1)  # on the tube's centre circle
    # from outside, within about 35 degrees of the outward direction from the tube's centre circle (a ray that
    # only touches a silhouette vertex tangentially may miss: that is not a leak)
    out_dir = _unit(_unit(targets - inner) + 0.35 * _unit(rng.normal(size=targets.shape)))
    outer = targets + 2.0 * out_dir
    origins = np.concatenate([inner, outer])
    goal = np.concatenate([targets, targets])
    d = _unit(goal - origins)
    o32, d32 = jnp.asarray(origins, jnp.float32), jnp.asarray(d, jnp.float32)
    t, slot = _per_ray(lambda a, b: mesh_nearest(mesh, a, b), o32, d32)
    assert np.all(np.asarray(slot) >= 0), f"{int(np.sum(np.asarray(slot) < 0))} of {len(d)} rays leaked"
    dist = np.linalg.norm(goal - origins, axis=1) + 1.0
    blocked = _per_ray(lambda a, b, c: mesh_occluded(mesh, a, b, c), o32, d32, jnp.asarray(dist, jnp.float32))
    assert np.all(np.asarray(blocked))


def test_bvh_hits_equal_brute_force(torus):
    """Random rays (through the torus' bounds, and from inside it) with a torus and with a triangle soup: the BVH's
    nearest hit equals brute force over every triangle (same distance; same triangle), and any-hit agrees with
    'brute-force distance < limit' for random limits. (The per-ray walk, one loop to compile; the batched walk that
    renders use is checked equal to it in `test_batched_traversal_equals_the_per_ray_walk`.)"""
    v, f, torus_m = torus
    rng = np.random.default_rng(3)
    soup = rng.uniform(-1, 1, (3000, 1, 3)) + 0.15 * rng.normal(size=(3000, 3, 3))
    soup_m = jf.Mesh.from_arrays(soup.reshape(-1, 3), np.arange(9000).reshape(-1, 3), jf.Diffuse(0.5))
    n = 2048
    o = rng.uniform(-2, 2, (n, 3))
    o[: n // 4] *= 0.2
    d = _unit(rng.uniform(-1.2, 1.2, (n, 3)) - o)
    o, d = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
    limit = jnp.asarray(rng.uniform(0.1, 4.0, n), jnp.float32)
    for mesh in (torus_m, soup_m):
        tb, sb = _per_ray(lambda a, b: mesh_nearest(mesh, a, b), o, d)
        tr, sr = jax.jit(jax.vmap(lambda a, b: brute_force_nearest(mesh, a, b)))(o, d)
        tb, sb, tr, sr = map(np.asarray, (tb, sb, tr, sr))
        assert 0.2 < np.isfinite(tr).mean() < 0.98
        np.testing.assert_array_equal(tb, tr)
        assert np.mean(sb == sr) > 0.999  # exact ties (a ray through a shared edge) may pick either triangle
        occ = np.asarray(_per_ray(lambda a, b, c: mesh_occluded(mesh, a, b, c), o, d, limit))
        np.testing.assert_array_equal(occ, tr < np.asarray(limit))


def test_bvh_structure(torus):
    """The 4-wide SAH BVH: every triangle sits in exactly one leaf slot, every child box holds (in float32) all the
    triangles below it, and the deepest path fits the traversal's stack (3 entries pushed per level at most)."""
    v, f, _ = torus
    tris = v[f]
    bvh = build_bvh(tris)
    assert np.array_equal(np.sort(bvh.order[bvh.order >= 0]), np.arange(len(f)))
    rows, nl = bvh.rows, bvh.n_leaves
    leaf_tris = rows[:nl].reshape(nl, 3, 3, WIDTH)

    def points(r):  # float32 vertices of all triangles below row r
        if r < nl:
            k = np.sum(bvh.order[r * WIDTH:(r + 1) * WIDTH] >= 0)
            return leaf_tris[r, :, :, :k].transpose(2, 0, 1).reshape(-1, 3)
        kids = rows[r, 24:28].astype(int)
        return np.concatenate([points(c) for c in kids if c >= 0])

    def depth(r):
        return 0 if r < nl else 1 + max(depth(c) for c in rows[r, 24:28].astype(int) if c >= 0)

    for r in range(nl, len(rows)):
        for k, c in enumerate(rows[r, 24:28].astype(int)):
            if c < 0:
                continue
            p = points(c)
            lo, hi = rows[r, 0:12].reshape(3, WIDTH)[:, k], rows[r, 12:24].reshape(3, WIDTH)[:, k]
            assert np.all(p >= lo) and np.all(p <= hi)
    assert depth(bvh.root) == bvh.depth
    assert (WIDTH - 1) * bvh.depth >= 1


def test_batched_traversal_equals_the_per_ray_walk(torus):
    """Under `vmap` the traversal runs batched with lane compaction (`custom_vmap`); without `vmap` (`lax.map`) it is
    the per-ray while loop. Both give the same nearest hits and shadow-ray answers, bit for bit, for a batch of
    120 rays (stages of 120 and 30 lanes), with a scalar limit (nearest hits) and per-ray limits (shadow rays);
    a `vmap` over meshes (their arrays batched) takes the plain vectorized walk and agrees too."""
    import equinox as eqx

    v, f, mesh = torus
    assert _stage_widths(120) == [120, 30] and _stage_widths(48) == [48] and _stage_widths(1024)[-1] == 16
    rng = np.random.default_rng(7)
    for n in (120,):
        o = rng.uniform(-2, 2, (n, 3))
        o[: n // 3] *= 0.2
        d = _unit(rng.uniform(-1.2, 1.2, (n, 3)) - o)
        o, d = jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
        limit = jnp.asarray(rng.uniform(0.1, 4.0, n), jnp.float32)
        both = lambda a, b, c: (mesh_nearest(mesh, a, b), mesh_occluded(mesh, a, b, c))  # noqa: E731
        batched = jax.jit(jax.vmap(both))(o, d, limit)
        per_ray = _per_ray(both, o, d, limit)
        for a, b in zip(jax.tree.leaves(batched), jax.tree.leaves(per_ray)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert 0.2 < np.mean(np.asarray(batched[0][1]) >= 0) < 0.98
    two = jnp.stack([mesh.rows, mesh.rows])
    t2, s2 = jax.jit(jax.vmap(lambda r: mesh_nearest(eqx.tree_at(lambda m: m.rows, mesh, r), o[0], d[0])))(two)
    t1, s1 = mesh_nearest(mesh, o[0], d[0])
    assert np.all(np.asarray(t2) == np.asarray(t1)) and np.all(np.asarray(s2) == np.asarray(s1))


# ---------------------------------------------------------------------------------------------------- renders
# slow tier: a 20-s render program of its own (cold compilation cache, 2 cores); the default run checks the mesh's hits
# against brute force (test_bvh_hits_equal_brute_force) and a closed mesh around a light (no leaks)
@pytest.mark.slow
def test_tessellated_sphere_renders_like_the_analytic_sphere():
    """A diffuse sphere under a point light (no fog, single scattering), analytic vs an inscribed UV sphere of
    ~9k flat triangles, with the same keys (common random numbers: the same pixel positions).

    Bound: every face lies within the angle `alpha` (its largest vertex-to-face-normal angle) of its normal, and
    between the spheres of radii `r cos(alpha)` and `r`. For a ray that hits both, the normal differs by at most
    `alpha`, the hit point by at most `delta = r (1 - cos alpha) / cos(incidence)`... bounded here by using only
    pixels whose four corner rays hit the inner sphere at an incidence below 60 degrees (there `delta <=
    2 r (1 - cos alpha)`). With `L = R I cos(theta) / (pi d^2)`: `|dL| <= R I / (pi d_min^2) (alpha + 3 delta /
    d_min)` (cos changes by <= alpha + delta / d_min, 1/d^2 by <= 2 delta / d_min relative). Each such pixel must
    be within that bound; the image mean within it plus the silhouette band (pixels not inside) times the
    largest radiance."""
    r, c = 0.5, np.array([0.0, 0.0, 0.0])
    v, f, _ = uv_sphere(96, 48, r, c)
    tri = (v[f] - c) / r
    fn = _unit(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    alpha = float(np.max(np.arccos(np.clip(np.einsum("fkj,fj->fk", tri, fn), -1, 1))))
    light_p, intensity, refl = np.array([1.2, 1.5, 1.4]), 4.0, 0.6
    cam = jf.Camera(origin=(0.0, 0.3, 2.2), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=32.0, width=24,
                    height=24)
    light = jf.PointLight(tuple(light_p), intensity)
    analytic = jf.Scene(camera=cam, shapes=(jf.Sphere(tuple(c), r, jf.Diffuse(refl)),), lights=(light,), max_depth=2)
    mesh = jf.Scene(camera=cam, shapes=(jf.Mesh.from_arrays(v, f, jf.Diffuse(refl)),), lights=(light,), max_depth=2)
    key = jax.random.key(4)
    a = np.asarray(jf.render(analytic, key, 4), np.float64).mean(-1)
    m = np.asarray(jf.render(mesh, key, 4), np.float64).mean(-1)

    # pixels whose corner rays all hit the inner sphere at incidence < 60 degrees (float64, conventions.md camera)
    o = np.array([0.0, 0.3, 2.2])
    fwd = _unit(-o)
    right = _unit(np.cross(fwd, [0, 1, 0]))
    up = np.cross(right, fwd)
    th = math.tan(math.radians(16.0))
    g = np.arange(25)
    sx, sy = np.meshgrid((2 * g / 24 - 1) * th, (1 - 2 * g / 24) * th)
    dirs = _unit(fwd + sx[..., None] * right + sy[..., None] * up)
    r_in = r * math.cos(alpha)
    b = dirs @ (o - c)
    disc = b**2 - (np.dot(o - c, o - c) - r_in**2)
    tt = -b - np.sqrt(np.maximum(disc, 0))
    p = o + tt[..., None] * dirs
    cos_inc = -np.einsum("ijk,ijk->ij", _unit(p - c), dirs)
    good = (disc > 0) & (cos_inc > 0.5)
    inside = good[:-1, :-1] & good[1:, :-1] & good[:-1, 1:] & good[1:, 1:]
    d_min = np.linalg.norm(light_p - c) - r
    delta = 2 * r * (1 - math.cos(alpha))
    bound = refl * intensity / (math.pi * d_min**2) * (alpha + 3 * delta / d_min)
    assert inside.sum() > 100 and 0 < alpha < 0.06
    diff = np.abs(m - a)
    assert np.all(diff[inside] <= bound), (diff[inside].max(), bound)
    band = (~inside).mean()
    assert abs(m.mean() - a.mean()) <= bound + band * max(a.max(), m.max())
    # and much closer than the bound in practice (flat facets average out)
    assert np.abs(m[inside] - a[inside]).mean() < 0.3 * bound


def test_closed_box_around_a_point_light_leaks_nothing():
    """A closed box (6 faces of 6 x 6 quads, 432 triangles) around a point light, in fog, over a floor, seen from
    outside: nothing of the light reaches the camera (the image is exactly black); with the light moved out of the box
it is not."""
    v, f = box_mesh((-0.5, 0.2, -0.5), (0.5, 1.2, 0.5), 6)
    cam = jf.Camera(origin=(0.3, 1.6, 3.0), target=(0.0, 0.6, 0.0), up=(0.0, 1.0, 0.0), fov=50.0, width=16, height=12)
    floor = jf.Rectangle((0.0, 0.0, 0.0), (8.0, 0.0, 0.0), (0.0, 0.0, -8.0), jf.Diffuse(0.8))
    fog = jf.HomogeneousMedium(sigma_t=0.3, albedo=0.9, phase=jf.HenyeyGreenstein(0.3))
    light = jf.PointLight((0.05, 0.7, -0.03), 20.0)
    box = jf.Mesh.from_arrays(v, f, jf.Diffuse(0.7))
    closed = jf.Scene(camera=cam, shapes=(floor, box), lights=(light,), medium=fog, max_depth=3)
    img = np.asarray(jf.render(closed, jax.random.key(5), 8))
    assert np.all(img == 0.0), (np.count_nonzero(img), img.max())
    import equinox as eqx
    outside = eqx.tree_at(lambda s: s.lights[0].position, closed, jnp.array([0.05, 1.5, 0.9]))  # no recompile
    assert np.asarray(jf.render(outside, jax.random.key(5), 8)).mean() > 1e-3


def _grad_scene(mesh, max_depth):
    cam = jf.Camera(origin=(0.0, 1.2, 2.5), target=(0.0, 0.2, 0.0), up=(0.0, 1.0, 0.0), fov=40.0, width=8, height=6)
    floor = jf.Rectangle((0.0, -0.3, 0.0), (6.0, 0.0, 0.0), (0.0, 0.0, -6.0), jf.Diffuse(0.5))
    return jf.Scene(camera=cam, shapes=(floor, mesh), lights=(jf.PointLight((0.3, 1.5, 0.2), 5.0),),
                    medium=jf.HomogeneousMedium(sigma_t=0.4, albedo=0.8, phase=jf.HenyeyGreenstein(0.3)),
                    max_depth=max_depth)


@pytest.mark.slow
def test_mesh_scene_reverse_mode_gradient(torus):
    """jax.grad of a mesh scene's image mean w.r.t. sigma_t runs (the BVH's while_loop carries no derivative) and is
    finite and negative (denser fog, darker image here); forward = reverse mode is the slow test below."""
    base = _grad_scene(torus[2], 2)
    key = jax.random.key(6)

    def mean(x):
        return jf.render(base.replace_medium(sigma_t=x), key, 2).mean()

    g = float(jax.grad(mean)(jnp.float32(0.4)))
    assert np.isfinite(g) and g < 0


@pytest.mark.slow
def test_mesh_scene_gradients_forward_and_reverse(torus):
    """d(image mean)/d(sigma_t, light intensity, mesh reflectance), max_depth 3: reverse mode equals forward mode,
    all finite and nonzero."""
    import equinox as eqx

    base = _grad_scene(torus[2], 3)
    key = jax.random.key(6)

    def mean(x):
        s = eqx.tree_at(lambda q: (q.lights[0].intensity, q.shapes[1].bsdf.reflectance),
                        base.replace_medium(sigma_t=x[0]), (x[1] * jnp.ones(3), x[2] * jnp.ones(3)))
        return jf.render(s, key, 2).mean()

    x = jnp.array([0.4, 5.0, 0.5], jnp.float32)
    rev = np.asarray(jax.grad(mean)(x))
    fwd = np.asarray(jax.jacfwd(mean)(x))
    assert np.all(np.isfinite(rev)) and np.all(rev != 0)
    np.testing.assert_allclose(rev, fwd, rtol=1e-3)


# ---------------------------------------------------------------------------------------------------- files
def test_obj_reader_fans_polygons_and_takes_negative_indices(tmp_path):
    p = tmp_path / "quad.obj"
    p.write_text("# a unit square and a triangle\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n"
                 "v 0 0 1\nv 1 0 1\nv 0 1 1\nf -3/1 -2/2/2 -1//3\n")
    m = read_mesh(p)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [4, 5, 6]])
    assert m.vertices.shape == (7, 3) and m.normals is None


@pytest.mark.parametrize("fmt", ["ascii", "binary"])
def test_ply_reader_round_trip(tmp_path, fmt):
    v, f, n = uv_sphere(8, 5)
    p = tmp_path / "s.ply"
    if fmt == "binary":
        write_ply(p, v, f, n)
    else:
        lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x", "property float y",
                 "property float z", "property float nx", "property float ny", "property float nz",
                 f"element face {len(f) // 2}", "property list uchar int vertex_indices", "end_header"]
        lines += [" ".join(map(str, list(a) + list(b))) for a, b in zip(v, n)]
        # pairs of triangles written as quads where they share an edge would change the faces: write triangles
        # as polygons of 3 and one quad as a check of the fan
        lines[9] = f"element face {len(f)}"
        lines += ["3 " + " ".join(map(str, t)) for t in f]
        p.write_text("\n".join(lines) + "\n")
    m = read_mesh(p)
    np.testing.assert_array_equal(m.faces, f)
    np.testing.assert_allclose(m.vertices, v, atol=1e-6)
    np.testing.assert_allclose(m.normals, n, atol=1e-6)


def _write_scene(tmp_path, mesh_file, **shape):
    data = {"camera": {"origin": [0, 0, 3], "target": [0, 0, 0], "up": [0, 1, 0], "fov": 40, "width": 4, "height": 4},
            "shapes": [{"type": "mesh", "file": mesh_file, "bsdf": {"type": "diffuse", "reflectance": 0.5}, **shape}],
            "lights": [{"type": "point", "position": [0, 2, 2], "intensity": 1}]}
    p = tmp_path / "scene.json"
    p.write_text(json.dumps(data))
    return p


def test_scene_file_mesh_relative_path_and_transform(tmp_path):
    (tmp_path / "m").mkdir()
    v, f, _ = uv_sphere(8, 5)
    write_ply(tmp_path / "m" / "s.ply", v, f)
    p = _write_scene(tmp_path, "m/s.ply", to_world={"scale": 0.5, "rotate": {"axis": [0, 1, 0], "angle": 90},
                                                    "translate": [1, 0, 0]})
    sf = jf.load_scene(p)
    mesh = sf.scene.shapes[0]
    assert isinstance(mesh, jf.Mesh) and mesh.n_faces == len(f)
    assert sf.data["shapes"][0]["file"] == str(tmp_path / "m" / "s.ply")
    pts = np.asarray(mesh.leaves).transpose(0, 3, 1, 2).reshape(-1, 3, 3)[np.asarray(mesh.face) >= 0].reshape(-1, 3)
    np.testing.assert_allclose(np.linalg.norm(pts - [1, 0, 0], axis=1), 0.5, atol=1e-6)
    m = transform_matrix(sf.data["shapes"][0]["to_world"])
    np.testing.assert_allclose(m @ [0, 0, 1, 1], [1.5, 0, 0, 1], atol=1e-12)  # +z rotated 90 deg about y is +x


def _bad_mesh(tmp_path, kind):
    p = tmp_path / "bad.obj"
    text = {
        "no faces": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
        "non-finite vertex": "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
        "degenerate face": "v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 1 0\nf 1 2 4\nf 1 2 3\n",
        "index out of range": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 5\n",
    }[kind]
    p.write_text(text)
    return p


@pytest.mark.parametrize("kind,message", [
    ("missing file", "mesh file not found"),
    ("no faces", "has no faces"),
    ("non-finite vertex", "not finite"),
    ("degenerate face", "degenerate"),
    ("index out of range", "out of range"),
])
def test_loading_errors_name_the_files(tmp_path, kind, message):
    mesh_file = "nowhere.ply" if kind == "missing file" else _bad_mesh(tmp_path, kind).name
    with pytest.raises(MeshError, match=message):
        read_mesh(tmp_path / mesh_file)
    scene = _write_scene(tmp_path, mesh_file)
    with pytest.raises(jf.SceneError) as e:
        jf.load_scene(scene)
    text = str(e.value)
    assert text.startswith("scene.json: shapes[0].file: ") and mesh_file in text and message in text, text


def test_smooth_needs_vertex_normals_and_transforms_are_checked(tmp_path):
    v, f, _ = uv_sphere(8, 5)
    write_ply(tmp_path / "s.ply", v, f)
    with pytest.raises(jf.SceneError, match="has no vertex normals"):
        jf.load_scene(_write_scene(tmp_path, "s.ply", smooth=True))
    with pytest.raises(jf.SceneError, match="either matrix or"):
        jf.load_scene(_write_scene(tmp_path, "s.ply", to_world={"matrix": np.eye(4).tolist(), "scale": 2}))
    with pytest.raises(jf.SceneError, match="singular"):
        jf.load_scene(_write_scene(tmp_path, "s.ply", to_world={"matrix": np.diag([1, 0, 1, 1.0]).tolist()}))


def test_mesh_code_is_traced_only_for_mesh_scenes(torus):
    """A scene without meshes has no while loop in its program; with a mesh it has (the BVH traversal)."""
    from test_render_properties import primitive_counts

    cam = jf.Camera(origin=(0.0, 1.0, 3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=40.0, width=4, height=3)
    floor = jf.Rectangle((0.0, -0.3, 0.0), (6.0, 0.0, 0.0), (0.0, 0.0, -6.0), jf.Diffuse(0.5))
    light = (jf.PointLight((0.3, 1.5, 0.2), 5.0),)
    plain = jf.Scene(camera=cam, shapes=(floor,), lights=light, max_depth=2)
    meshy = jf.Scene(camera=cam, shapes=(floor, torus[2]), lights=light, max_depth=2)
    assert primitive_counts(plain)["while"] == 0
    assert primitive_counts(meshy)["while"] >= 2  # nearest hit and shadow ray


@pytest.mark.slow
def test_mesh_fog_agrees_with_mitsuba():
    """The shipped mesh_fog scene (21504 flat triangles, PLY) at 16 x 16, max_depth 4, against Mitsuba 3's `ply`
    shape with face normals: 16 independent 8-spp images from each renderer; the image mean and the four quadrant
    means agree within 5 combined standard errors (as tests/test_mitsuba.py for spot_fog)."""
    try:
        from jaxfog._mitsuba import import_mitsuba

        import_mitsuba()
    except ImportError as e:
        pytest.skip(str(e))
    path = REPO / "data_synthetic" / "scenes" / "mesh_fog.json"
    over = ["camera.width=16", "camera.height=16", "integrator.max_depth=4"]
    n, spp = 16, 8
    ours, theirs = jaxfog_and_mitsuba_images(path, over, n, spp)

    (m_j, se_j), (m_m, se_m) = image_and_quadrant_means(ours), image_and_quadrant_means(theirs)
    z = (m_j - m_m) / np.sqrt(se_j**2 + se_m**2)
    print("jaxfog", m_j, "+-", se_j, "\nMitsuba", m_m, "+-", se_m, "\nz", z)
    assert m_j[0] > 0 and np.all(np.abs(z) < 5), f"jaxfog {m_j} +- {se_j}, Mitsuba {m_m} +- {se_m}, z {z}"
