"""Paths of any length (`max_depth = -1`): the regenerating loop and its derivatives (forward mode and path replay).

The work items' paths form one queue (path `q` is row `q % chunk` of item `q // chunk`); `chunk` lanes trace one
bounce each per iteration, and a lane whose path ended (absorbed, escaped, or stopped by Russian roulette)
scatter-adds its radiance to its pixel and takes the next path of the queue. The work is the sum of the paths'
lengths (plus the last paths' tail), not lanes x the longest path. Path `(layer, row)` draws bounce `b`'s uniforms
from the same hash table as the fixed-depth tracer (row `row`, columns `b K .. b K + K - 1`), so the image depends
only on the scene, the key and spp.

Derivatives (`docs/estimators.md`, "Paths of any length"):

- forward mode (`jax.jvp`, `jax.jacfwd`): the loop's own tangents;
- reverse mode (`jax.grad`, `jax.vjp`): *path replay* (Vicini, Speierer, Jakob 2021). With the "detached" and
  "proposal" estimators a sampled path does not move with the medium's, the lights' radiometric values or the
  BSDFs' reflectances (`replayable`), and each bounce `j` updates `L_{j+1} = L_j + beta_j c_j(theta)`,
  `beta_{j+1} = beta_j w_j(theta)` (per channel; Russian roulette divides by a survival probability that carries
  no derivative). So `dL = sum_j beta_j dc_j + (dw_j / w_j) (L - L_{j+1})`: the forward pass stores each path's
  total `L` (one RGB value per path of the queue: 12 bytes), and a second pass traces the same paths again and,
  at each bounce, pulls the image's cotangent at the path's pixel back through the bounce with its incoming state
  held fixed. Memory does not grow with the path length. Leaves that can move a path (camera, geometry, light
  positions, directions and cones, glass indices of refraction) get their cotangent from forward mode instead, one
  tangent per scalar (`MAX_FORWARD_SCALARS` at most), so `jax.grad` over a whole Scene is exact but costs more
  than over its radiometric values only. The "reparam" estimator (sampled distances and directions move with the
  medium) has no replay: reverse mode raises, forward mode works.

Forward and reverse mode meet in a primitive (`_tangent_p`, built with `equinox.internal`'s primitive helpers, as
`lineax` builds its linear solve): a custom JVP whose tangent is that primitive, which forward mode evaluates as the
loop's JVP and reverse mode transposes into the replay.
"""

from __future__ import annotations


import equinox as eqx
import equinox.internal as eqxi
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jax.interpreters import ad
from jaxtyping import Array

from ._integrator import (SamplingOptions, Uniforms, bounce, computed_once, make_tracer, n_dims, russian_roulette,
                          start_path)
from ._medium import path_replay
from ._random import hashed_uniforms
from ._scene import Scene, pack

RADIOMETRIC_FIELDS = ("intensity", "radiance", "irradiance", "reflectance")
"""Light and BSDF fields that scale the light a path carries without moving it (with the medium's fields, for the
"detached" and "proposal" estimators): reverse mode replays the paths for these (`replayable`)."""

MAX_FORWARD_SCALARS = 256
"""Most scalars of path-moving leaves (camera, geometry, light positions, ...) reverse mode differentiates by forward
mode (one tangent each, traced together); beyond it (e.g. a mesh's vertices) it raises instead."""

BETA_MIN = 1e-30
"""Throughputs below it are treated as 0 when the replay divides the future radiance by the throughput: such a
path's future carries less than 1e-30 of the radiance scale, and the quotient of a float32 cancellation error by a
denormal throughput would overflow."""


# ------------------------------------------------------------------------------------------------ the loop
def _run(scene: Scene, words, chunk_ids, valid, options: SamplingOptions, proposal, chunk: int, n_ch: int,
         step, extra):
    """The regenerating loop over the queue of the items' paths; `step(tracer, extra, state, row, qid, b, U) ->
    (extra, new_state)` traces one bounce of every lane (`qid`: each lane's queue index). Returns `extra`."""
    cam = scene.camera
    n_pix = cam.height * cam.width
    K = n_dims(scene)
    total = jnp.sum(valid.astype(jnp.int32)) * chunk  # valid items come first
    cols = jnp.arange(K, dtype=jnp.uint32)
    tracer = make_tracer(scene, pack(scene), options, proposal)

    def start(q):
        """Camera path number `q` of the queue: its row and start state (dead if it is a padding row)."""
        item, j = q // chunk, (q % chunk).astype(jnp.uint32)
        row = chunk_ids[item] * chunk + j
        y, x = jnp.divmod(row % n_pix, cam.width)
        jitter = hashed_uniforms(words[item, 0], row, jnp.arange(2, dtype=jnp.uint32))
        o, d = cam.generate_ray(jnp.stack([x, y]).astype(jnp.float32) + jitter)
        return row, start_path(o, d)._replace(alive=row < n_pix)

    def body(c):
        extra, state, row, qid, b, next_q = c
        need = ~state.alive
        q = next_q + jnp.cumsum(need) - 1
        take = need & (q < total)
        q = jnp.minimum(q, total - 1)
        row_n, st_n = jax.vmap(start)(q)
        pick = lambda a, b_: jnp.where(take.reshape(take.shape + (1,) * (a.ndim - 1)), a, b_)
        state = jax.tree.map(pick, st_n, state)
        row, qid, b = pick(row_n, row), pick(q, qid), pick(jnp.zeros_like(b), b)
        U = jax.vmap(lambda qq, r, bb: hashed_uniforms(words[qq // chunk, 1], r, bb.astype(jnp.uint32) * K + cols)
                     )(qid, row, b)
        # the refilled lanes and their uniforms computed once (`computed_once`): the bounce's stages all read them;
        # the barriers' guard is the queue position, a loop-carried value XLA cannot fold
        tr = tracer._replace(guard=next_q >= 0)
        state, U = computed_once(tr, (state, U))
        extra, new = step(tr, extra, state, row, qid, b, U)
        return extra, new, row, qid, b + 1, next_q + jnp.sum(take.astype(jnp.int32))

    def cond(c):
        return jnp.any(c[1].alive) | (c[5] < total)

    dead = jax.vmap(lambda q: start(q)[1])(jnp.zeros(chunk, jnp.int32))._replace(alive=jnp.zeros(chunk, bool))
    zero = jnp.zeros(chunk, jnp.uint32)
    init = (extra, dead, zero, jnp.zeros(chunk, jnp.int32), zero, jnp.int32(0))
    return jax.lax.while_loop(cond, body, init)[0]


def _lanes(tracer, state, b, U):
    """One bounce of every lane, then Russian roulette."""
    def one(st, bb, cols):
        u = Uniforms(cols)
        return russian_roulette(tracer, bounce(tracer, st, bb, u), bb, u)

    return jax.vmap(one)(state, b, tuple(U[:, k] for k in range(U.shape[1])))


def _forward(scene, words, chunk_ids, valid, proposal, *, options, chunk, n_ch):
    """`(acc, L_path)`: the items' radiance summed per row, `(n_ch * chunk, 3)`, and each queued path's radiance,
    `(items * chunk, 3)` (0 for paths never traced)."""
    n_rows, n_queue = n_ch * chunk, words.shape[0] * chunk

    def step(tracer, extra, state, row, qid, b, U):
        acc, L_path = extra
        new = _lanes(tracer, state, b, U)
        ended = state.alive & ~new.alive
        L_end = jnp.where(ended[:, None], new.L, 0.0)
        acc = acc.at[jnp.where(ended, row, n_rows)].add(L_end, mode="drop")
        L_path = L_path.at[jnp.where(ended, qid, n_queue)].set(L_end, mode="drop")
        return (acc, L_path), new

    zeros = (jnp.zeros((n_rows, 3), jnp.float32), jnp.zeros((n_queue, 3), jnp.float32))
    return _run(scene, words, chunk_ids, valid, options, proposal, chunk, n_ch, step, zeros)


def moments(scene, words, chunk_ids, valid, proposal, *, options, chunk, n_ch):
    """`(acc, acc_sq)`: the items' radiance and its square summed per row, `(n_ch * chunk, 3)` each (for
    `render(..., variance=True)`): the same paths as `trace_items_unbounded`, by the plain loop, so forward mode
    only (a `lax.while_loop` has no reverse mode)."""
    n_rows = n_ch * chunk

    def step(tracer, extra, state, row, qid, b, U):
        new = _lanes(tracer, state, b, U)
        ended = state.alive & ~new.alive
        L_end = jnp.where(ended[:, None], new.L, 0.0)
        slot = jnp.where(ended, row, n_rows)
        return tuple(a.at[slot].add(x, mode="drop") for a, x in zip(extra, (L_end, L_end * L_end))), new

    zeros = (jnp.zeros((n_rows, 3), jnp.float32),) * 2
    return _run(scene, words, chunk_ids, valid, options, proposal, chunk, n_ch, step, zeros)


# ---------------------------------------------------------------------------------------------- the replay
def replayable(scene: Scene):
    """A pytree like `scene` (bool leaves): True where reverse mode replays the paths (the medium's fields and the
    lights' and BSDFs' `RADIOMETRIC_FIELDS`), False where a leaf can move a path (it is differentiated by forward
    mode). Only for the "detached" and "proposal" estimators, whose sampled paths do not follow the medium."""

    def radiometric(path, _):
        names = [k.name for k in path if isinstance(k, jax.tree_util.GetAttrKey)]
        return bool(names) and (names[0] == "medium" or (names[-1] in RADIOMETRIC_FIELDS and (
            names[0] == "lights" or "bsdf" in names)))

    return jax.tree_util.tree_map_with_path(radiometric, scene)


def _replay(scene, words, chunk_ids, valid, proposal, L_path, ct, th_mask, *, options, chunk, n_ch):
    """The cotangent of the leaves selected by `th_mask` (a pytree like `scene`, True where differentiated, all of
    them `replayable`) for the output cotangent `ct` `(n_ch * chunk, 3)`: the same paths traced again."""
    th, rest = eqx.partition(scene, th_mask)
    ct = jnp.concatenate([ct, jnp.zeros((1, 3), ct.dtype)])  # row n_rows: dead lanes

    def step(tracer, g, state, row, qid, b, U):
        def lanes(th_):
            sc = eqx.combine(th_, rest)
            tr = make_tracer(sc, pack(sc), options, proposal)
            with path_replay():  # a grid's ratio tracking: its own replay (`_grid.ratio_tracking`)
                new_ = _lanes(tr, state, b, U)
            return (new_.L - state.L, new_.beta), new_

        _, pull, new = jax.vjp(lanes, th, has_aux=True)
        delta = ct[jnp.where(state.alive, row, ct.shape[0] - 1)]
        future = L_path[qid] - new.L
        ok = new.beta > BETA_MIN  # double where: no 0/0, and no overflow of a rounding error over a denormal
        per_beta = jnp.where(ok, future / jnp.where(ok, new.beta, 1.0), 0.0)
        (g_b,) = pull((delta, delta * per_beta))
        return jax.tree.map(jnp.add, g, g_b), new

    g0 = jax.tree.map(jnp.zeros_like, th)
    return _run(scene, words, chunk_ids, valid, options, proposal, chunk, n_ch, step, g0)


# ---------------------------------------------------------------------------- forward and reverse mode meet
def _tangent_impl(scene, words, chunk_ids, valid, proposal, L_path, t_scene, options, chunk, n_ch):
    """Forward mode: the loop's JVP along `t_scene` (a pytree like `scene`, None where not differentiated)."""
    del L_path
    f = lambda sc: _forward(sc, words, chunk_ids, valid, proposal, options=options, chunk=chunk, n_ch=n_ch)[0]
    return (eqx.filter_jvp(f, (scene,), (t_scene,))[1],)


def _tangent_abstract_eval(scene, words, chunk_ids, valid, proposal, L_path, t_scene, options, chunk, n_ch):
    return (jax.core.ShapedArray((n_ch * chunk, 3), jnp.float32),)


def _tangent_jvp(primals, tangents, **params):
    raise NotImplementedError("second derivatives of an unbounded render (max_depth = -1) are not supported")


def _tangent_transpose(inputs, cts_out):
    """Reverse mode: path replay for the replayable leaves, forward mode (one tangent per scalar) for the rest."""
    scene, words, chunk_ids, valid, proposal, L_path, t_scene, options, chunk, n_ch = inputs
    (ct,) = cts_out
    none = lambda tree: jax.tree.map(lambda _: None, tree, is_leaf=lambda x: isinstance(x, ad.UndefinedPrimal))
    out = lambda g: (none(scene), none(words), none(chunk_ids), none(valid), none(proposal), none(L_path), g,
                     none(options), None, None)
    if ct is None:
        return out(none(t_scene))
    if options.estimator == "reparam" and scene.medium is not None:
        raise ValueError('reverse-mode derivatives of an unbounded render (max_depth = -1) need estimator="detached" '
                         'or "proposal": with "reparam" the sampled paths move with the medium, which path replay '
                         'cannot follow. Use forward mode (jax.jvp, jax.jacfwd) or a fixed max_depth.')
    perturbed = jax.tree.map(lambda x: x is not None, t_scene,
                             is_leaf=lambda x: x is None or isinstance(x, ad.UndefinedPrimal))
    moves = jax.tree.map(lambda r: not r, replayable(scene))
    replay_mask = jax.tree.map(lambda p, r: p and r, perturbed, replayable(scene))
    forward_mask = jax.tree.map(lambda p, m: p and m, perturbed, moves)
    kw = dict(options=options, chunk=chunk, n_ch=n_ch)
    grads = None
    if any(jax.tree.leaves(replay_mask)):
        grads = _replay(scene, words, chunk_ids, valid, proposal, L_path, ct, replay_mask, **kw)
    if any(jax.tree.leaves(forward_mask)):
        mv, _ = eqx.partition(scene, forward_mask)
        flat, unravel = ravel_pytree(mv)
        if flat.size > MAX_FORWARD_SCALARS:
            raise ValueError(
                f"reverse mode of an unbounded render (max_depth = -1) differentiates leaves that move the paths "
                f"(camera, geometry, light positions/directions/cones, glass IOR: {flat.size} scalars here) by "
                f"forward mode, at most {MAX_FORWARD_SCALARS}; differentiate only the medium, the lights' "
                f"intensities and the BSDFs' reflectances (e.g. jax.grad of a function of the medium), or use "
                f"forward mode (jax.jacfwd)")

        def along(e):
            t = unravel(e)
            f = lambda sc: _forward(sc, words, chunk_ids, valid, proposal, **kw)[0]
            return jnp.vdot(ct, eqx.filter_jvp(f, (scene,), (t,))[1])

        g_mv = unravel(jax.vmap(along)(jnp.eye(flat.size, dtype=flat.dtype)))
        grads = g_mv if grads is None else eqx.combine(grads, g_mv)
    return out(grads)


_tangent_p = eqxi.create_vprim(
    "jaxfog_unbounded_tangent",
    eqxi.filter_primitive_def(_tangent_impl),
    eqxi.filter_primitive_def(_tangent_abstract_eval),
    eqxi.filter_primitive_jvp(_tangent_jvp),
    eqxi.filter_primitive_transpose(_tangent_transpose),
)


@eqx.filter_custom_jvp
def _trace(scene, words, chunk_ids, valid, proposal, *, options, chunk, n_ch):
    return _forward(scene, words, chunk_ids, valid, proposal, options=options, chunk=chunk, n_ch=n_ch)[0]


@_trace.def_jvp
def _trace_jvp(primals, tangents, *, options, chunk, n_ch):
    scene, words, chunk_ids, valid, proposal = primals
    acc, L_path = _forward(scene, words, chunk_ids, valid, proposal, options=options, chunk=chunk, n_ch=n_ch)
    if not jax.tree.leaves(tangents[0]):  # only the proposal is perturbed: it only samples (no derivative)
        return acc, jnp.zeros_like(acc)
    (t_acc,) = eqxi.filter_primitive_bind(_tangent_p, scene, words, chunk_ids, valid, proposal, L_path,
                                          tangents[0], options, chunk, n_ch)
    return acc, t_acc


def trace_items_unbounded(scene: Scene, words: Array, chunk_ids: Array, valid: Array, options: SamplingOptions,
                          proposal, chunk: int, n_ch: int) -> Array:
    """Sum of every row's radiance over the work items, `(n_ch * chunk, 3)`, for `max_depth = -1`. `words`:
    `(items, 2, 3)` uint32, each item's hash keys (pixel jitter, path); `chunk_ids[i]`: item i's chunk; items where
    `valid` is False (they come last) add nothing. Differentiable in forward and reverse mode (module docstring)."""
    return _trace(scene, words, chunk_ids, valid, proposal, options=options, chunk=chunk, n_ch=n_ch)
