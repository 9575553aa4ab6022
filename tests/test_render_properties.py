"""Structural properties of `jaxfog.render`: determinism, batch-size independence, no recompilation for new physical
values, and "model only what a scene needs" (the traced program of a simpler scene is a strict subset)."""

from __future__ import annotations

import collections
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.monitoring
import numpy as np
import pytest
from jax.extend import core as jex_core

import jaxfog as jf

from helpers import FLOOR_CAMERA, assert_same_render_up_to_rounding, make_floor

def fog_scene(sigma_t=(0.4, 0.5, 0.6), albedo=0.8, g=0.3, intensity=5.0):
    """Floor + point light in RGB fog, max_depth 3: free flight, equiangular sampling, NEE, phase and BRDF sampling.

    The same structure, resolution and batching as `test_render_analytic.test_absorbing_fog_is_beer_lambert`, so
    in a full run this file compiles only the padded-batch variant."""
    return jf.Scene(
        camera=FLOOR_CAMERA.build(),
        shapes=(make_floor(),),
        lights=(jf.PointLight((0.8, 1.5, 0.4), intensity),),
        medium=jf.HomogeneousMedium(sigma_t=sigma_t, albedo=albedo, phase=jf.HenyeyGreenstein(g)),
        max_depth=3,
    )


N_PIX = FLOOR_CAMERA.width * FLOOR_CAMERA.height
SPP = 16
BATCH = N_PIX * SPP  # one compiled call for all SPP layers


# ------------------------------------------------------------------------------------------------ determinism
def test_same_key_same_image_different_key_different_image():
    scene = fog_scene()
    a = np.asarray(jf.render(scene, jax.random.key(3), SPP, batch_paths=BATCH))
    b = np.asarray(jf.render(scene, jax.random.key(3), SPP, batch_paths=BATCH))
    c = np.asarray(jf.render(scene, jax.random.key(4), SPP, batch_paths=BATCH))
    assert a.shape == (FLOOR_CAMERA.height, FLOOR_CAMERA.width, 3) and a.dtype == np.float32
    assert np.all(np.isfinite(a)) and a.max() > 0
    np.testing.assert_array_equal(a, b)
    assert np.mean(a != c) > 0.5  # most pixels differ with another key


@pytest.mark.parametrize("max_depth", [3, pytest.param(-1, marks=pytest.mark.slow)])
def test_variance_is_the_samples_variance_over_spp(max_depth):
    """`render(..., variance=True)` returns the image and the per-pixel sample variance (ddof 1) of its `spp`
    samples over spp. Exact check, not statistical: sample j of every pixel is fixed by (key, j), so the renders at
    1..spp samples give the samples themselves, `x_j = j m_j - (j - 1) m_{j-1}`. Tolerance: float32 rounding of the
    sums (`ROUNDING_RTOL` of the largest sample squared, as the variance is a difference of second moments), and
    the differently compiled programs may flip a path's branch (`assert_same_render_up_to_rounding`)."""
    scene = dataclasses.replace(fog_scene(), max_depth=max_depth)
    key, spp = jax.random.key(11), 4
    means = [np.asarray(jf.render(scene, key, k, batch_paths=N_PIX), np.float64) for k in range(1, spp + 1)]
    x = np.stack([means[0]] + [(j + 1) * means[j] - j * means[j - 1] for j in range(1, spp)])
    img, var = (np.asarray(a, np.float64) for a in jf.render(scene, key, spp, batch_paths=N_PIX, variance=True))
    assert_same_render_up_to_rounding(img, means[-1], spp=spp, label="image with variance=True")
    expected = x.var(axis=0, ddof=1) / spp
    tol = 1e-4 * np.max(x * x, axis=0) * (1 + spp) + 1e-12
    bad = (np.abs(var - expected) > tol).reshape(-1, 3).any(axis=1)
    assert np.all(np.isfinite(var)) and np.all(var >= 0)
    assert bad.sum() <= max(1, int(0.05 * bad.size)), (bad.sum(), np.abs(var - expected).max())
    assert var.max() > 0
    with pytest.raises(ValueError, match="spp >= 2"):
        jf.render(scene, key, 1, variance=True)


def test_image_does_not_depend_on_batch_paths():
    """Sample k of every pixel uses fold_in(key, k), whatever the batching: 16 spp in one batch, or in batches of 6
    layers (the last one padded), give the same image up to float32 rounding: two compiled programs, so the
    tolerance (and its derivation) is `helpers.assert_same_render_up_to_rounding`'s."""
    scene = fog_scene()
    key = jax.random.key(5)
    one = np.asarray(jf.render(scene, key, SPP, batch_paths=BATCH))
    done = []
    padded = np.asarray(jf.render(scene, key, SPP, batch_paths=N_PIX * 6, progress=lambda d, n: done.append((d, n))))
    assert done == [(6, SPP), (12, SPP), (16, SPP)]
    assert_same_render_up_to_rounding(padded, one, spp=SPP, label="batches of 6 layers vs one batch")
    # and they are not trivially equal: a different spp gives a different image
    assert not np.allclose(np.asarray(jf.render(scene, key, SPP - 1, batch_paths=N_PIX * 6)), one, rtol=1e-3)


def _side_by_side(forward_mode: bool):
    """`(one layer per pass, 4 layers per pass)` renders of `fog_scene` at 10 spp with `variance=True` (batches of
    1 layer, the program of `test_variance_is_the_samples_variance_over_spp`, and of 4 layers: 4 + 4 + 2, the last
    pass half padding): each `(image, variance)`, or with `forward_mode` `((image, variance), (d image,
    d variance))` by `jax.jvp` in sigma_t."""
    from jaxfog._render import layers_per_chunk

    scene, key, spp = fog_scene(), jax.random.key(7), 10
    assert layers_per_chunk(scene, spp, batch_paths=N_PIX) == 1
    assert layers_per_chunk(scene, spp, batch_paths=4 * N_PIX) == 4
    if not forward_mode:
        return [jf.render(scene, key, spp, variance=True, batch_paths=b) for b in (N_PIX, 4 * N_PIX)]
    f = lambda b: lambda s: jf.render(scene.replace_medium(sigma_t=s), key, spp, variance=True, batch_paths=b)
    return [jax.jvp(f(b), (0.5,), (1.0,)) for b in (N_PIX, 4 * N_PIX)]


def test_layers_side_by_side_give_the_same_image():
    """An image of fewer pixels than `chunk_paths` is traced with several sample layers side by side in one
    vectorized pass (`_render.layers_per_chunk`; the fit's 8 x 8 views: 16 layers per 1024-path pass). Each path
    keeps its random numbers (a function of its layer and pixel), so the image and its variance equal those of one
    layer per pass up to float32 rounding (two compiled programs: `helpers.assert_same_render_up_to_rounding`).
    10 spp in passes of 4 layers: the last pass has two padding layers, which must add nothing (counted, they
    would raise the image by ~20%)."""
    (img1, var1), (img4, var4) = _side_by_side(False)
    assert_same_render_up_to_rounding(img4, img1, spp=10, label="4 layers per pass vs 1")
    assert_same_render_up_to_rounding(var4, var1, spp=10, label="variance, 4 layers per pass vs 1")


@pytest.mark.slow
def test_layers_side_by_side_give_the_same_derivative():
    """The same in forward mode (`jax.jvp` in sigma_t, as the fit's `jax.jacfwd`): the derivative images agree up
    to float32 rounding (~20 s: two forward-mode programs to compile)."""
    ((img1, _), (d1, dv1)), ((img4, _), (d4, dv4)) = _side_by_side(True)
    assert_same_render_up_to_rounding(img4, img1, spp=10, label="image, 4 layers per pass vs 1")
    assert_same_render_up_to_rounding(d4, d1, spp=10, scale=d1, label="d image / d sigma_t, 4 vs 1")
    assert_same_render_up_to_rounding(dv4, dv1, spp=10, scale=dv1, label="d variance / d sigma_t, 4 vs 1")


# ------------------------------------------------------------------------------------------------ no recompilation
class CompileCounter:
    """Counts XLA backend compilations (jax.monitoring duration events) while active."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self):
        self.count = 0
        self.active = False
        jax.monitoring.register_event_duration_secs_listener(self._listener)

    def _listener(self, event, duration, **kwargs):
        if self.active and event == self.EVENT:
            self.count += 1

    def __enter__(self):
        self.count, self.active = 0, True
        return self

    def __exit__(self, *exc):
        self.active = False


@pytest.fixture(scope="module")
def compile_counter():
    return CompileCounter()


def test_new_physical_values_do_not_recompile(compile_counter):
    """Medium sigma_t / albedo / g (via `replace_medium` and via new Modules), light intensity, BSDF reflectance,
    geometry, camera placement and the key are traced values: rendering with new ones compiles nothing. (Positive
    control: a new jitted function is counted.) A new Module keeps the base's chromatic extinction: whether a
    medium is grey is structure (a grey one, known when it is built, compiles no spectral MIS), and
    `replace_medium` keeps it whatever the new values."""
    base = fog_scene()
    variants = [
        base.replace_medium(sigma_t=0.9),
        base.replace_medium(albedo=(0.2, 0.5, 0.99), g=-0.4),
        base.replace_medium(sigma_t=(0.0, 0.0, 0.0)),
        base.replace_medium(g=np.float32(0.5), sigma_t=np.float64(0.7)),  # numpy scalars, other dtypes
        base.replace_medium(g=jax.numpy.asarray(0.1)),
        fog_scene(sigma_t=(2.0, 1.5, 1.0), albedo=0.1, g=0.95, intensity=(1.0, 2.0, 3.0)),
        eqx.tree_at(lambda s: s.shapes[0].bsdf.reflectance, base, jax.numpy.array([0.1, 0.2, 0.3])),
        eqx.tree_at(lambda s: (s.lights[0].position, s.camera.origin), base,
                    (jax.numpy.array([0.0, 0.7, 0.1]), jax.numpy.array([0.2, 1.7, 2.5]))),
    ]
    keys = [jax.random.key(i) for i in range(len(variants) + 1)]
    jf.render(base, keys[-1], SPP, batch_paths=BATCH).block_until_ready()  # compile once
    jf.render(base, keys[0], SPP, batch_paths=BATCH).block_until_ready()  # warm any eager helper ops
    with compile_counter as cc:
        images = [jf.render(s, k, SPP, batch_paths=BATCH).block_until_ready() for s, k in zip(variants, keys)]
    assert cc.count == 0, f"{cc.count} compilations for new physical values"
    # the new values were really used
    means = [float(np.mean(np.asarray(im))) for im in images]
    assert len(set(np.round(means, 6))) == len(means)

    with compile_counter as cc:
        jax.jit(lambda x: x * 3.0 + 1.0)(jax.numpy.ones(7)).block_until_ready()
    assert cc.count >= 1


# ------------------------------------------------------------------------------------------------ program size
def primitive_counts(scene: jf.Scene) -> collections.Counter:
    """Primitive counts of the traced render program (jaxpr), recursing into every sub-jaxpr (scan bodies,
    checkpoint, pjit/filter_jit calls, conds): a measure of how much code the scene compiles."""

    def visit(jaxpr, counts):
        for eqn in jaxpr.eqns:
            counts[eqn.primitive.name] += 1
            for param in eqn.params.values():
                for sub in param if isinstance(param, (tuple, list)) else (param,):
                    if isinstance(sub, jex_core.ClosedJaxpr):
                        visit(sub.jaxpr, counts)
                    elif isinstance(sub, jex_core.Jaxpr):
                        visit(sub, counts)
        return counts

    key = jax.random.key(0)
    closed = jax.make_jaxpr(lambda s: jf.render(s, key, 1))(scene)
    return visit(closed.jaxpr, collections.Counter())


def test_program_contains_only_what_the_scene_needs():
    """A diffuse floor under a point light traces to a program whose primitive multiset is contained in that of the
    same scene plus fog, plus a glass sphere (vs. a diffuse sphere), or plus an area light, and strictly smaller:
    features a scene lacks add no operations."""
    cam = dataclasses.replace(FLOOR_CAMERA, width=4, height=3).build()
    floor = make_floor()
    point = jf.PointLight((-0.5, 2.0, 0.5), 5.0)
    medium = jf.HomogeneousMedium(sigma_t=0.5, albedo=0.8, phase=jf.HenyeyGreenstein(0.3))
    diffuse_sphere = jf.Sphere((0.3, 0.5, -0.2), 0.5, jf.Diffuse(0.5))
    glass_sphere = jf.Sphere((0.3, 0.5, -0.2), 0.5, jf.Glass())
    area = jf.AreaLight((0.0, 2.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), 3.0)

    def scene(shapes, lights, med=None):
        return jf.Scene(camera=cam, shapes=shapes, lights=lights, medium=med, max_depth=4)

    pairs = {
        "medium": (scene((floor,), (point,)), scene((floor,), (point,), medium)),
        "glass": (scene((floor, diffuse_sphere), (point,)), scene((floor, glass_sphere), (point,))),
        "area light": (scene((floor,), (point,)), scene((floor,), (point, area))),
    }
    for name, (small, big) in pairs.items():
        cs, cb = primitive_counts(small), primitive_counts(big)
        fewer = {p: (n, cb[p]) for p, n in cs.items() if cb[p] < n}
        assert not fewer, f"adding {name} removed operations: {fewer}"
        assert sum(cb.values()) > sum(cs.values()) * 1.05, (name, sum(cs.values()), sum(cb.values()))


def test_phase_function_code_is_compiled_only_where_used():
    """Rayleigh sampling solves a cubic (`cbrt`): an HG scene's program has no `cbrt`, a Rayleigh scene's has."""
    cam = dataclasses.replace(FLOOR_CAMERA, width=4, height=3).build()
    point = jf.PointLight((-0.5, 2.0, 0.5), 5.0)

    def scene(phase):
        medium = jf.HomogeneousMedium(sigma_t=0.5, albedo=0.8, phase=phase)
        return jf.Scene(camera=cam, shapes=(make_floor(),), lights=(point,), medium=medium, max_depth=3)

    assert primitive_counts(scene(jf.HenyeyGreenstein(0.3)))["cbrt"] == 0
    assert primitive_counts(scene(jf.Rayleigh()))["cbrt"] > 0


def test_uniforms_give_each_dimension_and_slices_of_the_bounce_row():
    """`Uniforms` (a bounce's random numbers as one array per dimension, contiguous over the lanes under `vmap`)
    reads the same numbers as the row of the uniform table it was split from: single dimensions, slices (a light's
    or a BSDF's few dimensions, in order) and empty slices (a light with no dimensions)."""
    from jaxfog._integrator import Uniforms

    table = np.asarray(jax.random.uniform(jax.random.key(3), (5, 7)), np.float32)  # 5 lanes x 7 dimensions
    cols = tuple(table[:, k] for k in range(table.shape[1]))
    one = jax.vmap(lambda c: Uniforms(c)[4])(cols)
    some = jax.vmap(lambda c: Uniforms(c)[2:5])(cols)
    none = jax.vmap(lambda c: Uniforms(c)[6:6])(cols)
    np.testing.assert_array_equal(np.asarray(one), table[:, 4])
    np.testing.assert_array_equal(np.asarray(some), table[:, 2:5])
    assert none.shape == (5, 0)


# slow tier: compiles whole tracers with and without the barrier (25 s on 2 cores)
@pytest.mark.slow
def test_computed_once_changes_no_value_or_derivative_and_stays_in_the_program():
    """`computed_once` (the tracer's fusion barrier on the CPU) returns its operand's values, passes derivatives
    through in both modes and under `vmap`, keeps bool and int leaves, and survives XLA's optimizations as a
    conditional (the reason it exists: an optimization barrier would be removed)."""
    from jaxfog._integrator import computed_once, make_tracer, SamplingOptions
    from jaxfog._scene import pack

    scene = fog_scene()
    tr = make_tracer(scene, pack(scene), SamplingOptions())
    assert tr.barriers == (jax.default_backend() == "cpu")

    def f(x):
        y, flag, k = computed_once(tr, (jnp.sin(x) * x, x > 0.5, jnp.int32(3)))
        return jnp.where(flag, y, -y) * k

    def g(x):
        return jnp.where(x > 0.5, jnp.sin(x) * x, -jnp.sin(x) * x) * 3

    xs = jnp.linspace(-1.0, 2.0, 7)
    np.testing.assert_array_equal(np.asarray(jax.vmap(f)(xs)), np.asarray(jax.vmap(g)(xs)))
    np.testing.assert_allclose(np.asarray(jax.vmap(jax.grad(f))(xs)), np.asarray(jax.vmap(jax.grad(g))(xs)),
                               rtol=1e-6)
    t_f = jax.jvp(f, (jnp.float32(0.7),), (jnp.float32(1.0),))[1]
    t_g = jax.jvp(g, (jnp.float32(0.7),), (jnp.float32(1.0),))[1]
    assert float(t_f) == pytest.approx(float(t_g), rel=1e-6)
    if tr.barriers:  # in `render` the scene's arrays are arguments of the compiled program, so the predicate is too
        arrays, static = eqx.partition(scene, eqx.is_array)

        def traced(a, x):
            sc = eqx.combine(a, static)
            t = make_tracer(sc, pack(sc), SamplingOptions())
            return jax.vmap(lambda v: computed_once(t, jnp.sin(v) * v) * 3)(x)

        hlo = jax.jit(traced).lower(arrays, xs).compile().as_text()
        assert "conditional" in hlo
        # a scene that is a constant of the program (closed over by the caller's jit): render's own guard keeps it
        hlo = jax.jit(lambda k: jf.render(scene, k, 1)).lower(jax.random.key(0)).compile().as_text()
        assert "conditional" in hlo


# slow tier: two tracers (with and without the skip) compiled per scene and differentiated, 65-80 s each on 2 cores
@pytest.mark.slow
@pytest.mark.parametrize("scene_name", ["fog", "area"])
def test_skipping_the_last_segments_continuation_changes_no_radiance_or_derivative(scene_name):
    """On the CPU the tracer skips the continuation (direction, throughput) of a path's last segment, which no
    radiance reads (`bounce(..., last=...)`). The radiance of a batch of paths and its derivative in sigma_t equal
    those of the tracer without the skip (and without fusion barriers) up to float32 rounding; with an area light
    (whose last segment only matters when it hits the light) as well as with a point light in fog."""
    from jaxfog._integrator import make_tracer, n_dims, n_iterations, trace_path
    from jaxfog._scene import pack

    if scene_name == "fog":
        scene = fog_scene()
    else:
        scene = jf.load_scene("data_synthetic/scenes/area_light.json", ["integrator.max_depth=3"]).scene
    n_iter, K = n_iterations(scene), n_dims(scene)
    U = jax.random.uniform(jax.random.key(4), (256, n_iter, K), jnp.float32)
    cam = scene.camera
    pix = jax.random.uniform(jax.random.key(5), (256, 2)) * jnp.array([[cam.width, cam.height]], jnp.float32)

    def radiance(sc, barriers):
        tr = make_tracer(sc, pack(sc), jf.SamplingOptions())._replace(barriers=barriers, guard=U[0, 0, 0] >= 0)
        return jax.vmap(lambda p, u: trace_path(tr, *sc.camera.generate_ray(p), u))(pix, U)

    def total(scale, barriers):
        sc = scene.replace_medium(sigma_t=scene.medium.sigma_t * scale) if scene.medium is not None else scene
        return radiance(sc, barriers).sum()

    a, b = radiance(scene, True), radiance(scene, False)
    assert float(jnp.abs(a).max()) > 0
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-4 * float(jnp.abs(b).max()))
    if scene.medium is not None:
        ga = jax.grad(total)(jnp.float32(1.0), True)
        gb = jax.grad(total)(jnp.float32(1.0), False)
        assert float(gb) != 0.0
        assert float(ga) == pytest.approx(float(gb), rel=1e-4)
    hlo = jax.jit(lambda u: radiance(scene, True)).lower(U).compile().as_text()
    assert "conditional" in hlo
