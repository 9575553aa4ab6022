"""The volumetric path tracer for one camera path: written for one ray, `vmap`-ed once in `_render`.

A bounce is a list of stages, each a module-level function of named structs:

    intersect -> free_flight -> direct_on_segment -> next_direction -> medium_vertex / surface_vertex
              -> direct_at_vertex -> update

The stages talk to the scene only through the interfaces of its parts: the shapes (`AbstractShape.intersect`,
`surface`, `any_hit`, over the groups of `_scene.pack`), the medium (`AbstractMedium`: free flight, weights,
transmittance, scattering, phase function, `fog_interval`, `bounds`), the lights (every light's
`AbstractLight.sample_li` / `pdf_li`; the point-like lights' `lit_interval` and `position` for equiangular sampling
and the light-angle lobe; area lights' `emitted`), the BSDFs (`sample` / `eval` / `pdf`) and the warps of
`_sampling`. What a scene lacks (fog, a kind of BSDF or shape, area or point lights) is decided in Python and never
compiled.

Estimators (`docs/estimators.md`) change only the *sampler*, the medium whose values decide where paths go
(`sampling_medium`): a detached copy of the medium, a caller's fixed proposal, or the medium itself (reparameterized:
sampled distances and directions move with the parameters). Every weight is `f(theta) / pdf`.

Random numbers: each bounce reads its uniforms through a `Layout` of named dimensions built from the scene's
structure; no stage uses a numeric slot.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._bsdf import AbstractLobeBSDF
from ._math import RGB, dot, one_minus_cos_between, safe_div, safe_mul, safe_normalize, where_rgb
from ._medium import AbstractMedium, shared_ray_values
from ._sampling import (
    Polar,
    equiangular_pdf,
    equiangular_sample,
    equiangular_setup,
    light_lobe_cos,
    light_lobe_pdf,
    power_heuristic,
    to_direction,
)
from ._scene import EMITTER_KIND, Packed, Scene
from ._shapes import ShapeHit

EPS_OFFSET = 1e-4
"""Offset (scene units) of rays leaving a surface, along the normal on the side they leave to."""

ESTIMATORS = ("detached", "reparam", "proposal")

BETA_MAX = 1e20
"""Largest path throughput (per channel) a path continues with. A larger one (NaN and inf included) ends the path:
it arises only where the sampler is far from the medium (the "proposal" estimator with a reference of g = 0 for a
medium of g = 1 - 1e-7 multiplies the throughput by ~1e14 per forward scattering), and the next vertex's light
sample (its phase value up to ~1e14 in float32, the light's 1/r^2) would overflow float32 (3.4e38) into inf and, times
a zero, NaN. Paths of a throughput below it are unchanged; the image of any practical sampler is too."""


# ----------------------------------------------------------------------------------------------------- options
class SamplingOptions(eqx.Module):
    """How paths are sampled (static: each combination compiles its own program; values are checked when built).

    **Fields:**
    - `estimator`: how derivatives are estimated (values agree in expectation): `"detached"` (default; detached
      sampling, attached weights), `"reparam"` (reparameterized free flight and phase sampling), `"proposal"`
      (sampling from a fixed reference medium passed to `render(proposal=...)`). See `docs/estimators.md`.
    - `equiangular`: equiangular sampling of each segment toward point and spot lights, MIS-combined with free
      flight (default True).
    - `light_lobe`: probability in [0, 1) of sampling a scattering direction from the light-angle lobe (density
      `2 (pi - alpha) / pi^2` in the angle alpha to a point/spot light) instead of from the phase function / BSDF
      lobe (default 0.3; 0 disables it; never used by "reparam", whose directions must move with the parameters).
    - `distance_mix`: probability in [0, 1) of placing the path's medium vertex by equiangular sampling instead of
      free flight (default 0.15; needs `equiangular`; not used by "reparam").
    - `phase_lobe`: the fraction in [0, 1] of the light-angle lobe's directions drawn from the medium's phase
      function about the direction to the light (its forward peak aimed at the light) instead of from the lobe's
      angle profile; the lobe's density is then the mixture of the two. It is for sharply peaked phase functions:
      a path scattered toward the light meets, at its next vertex, the light's next-event estimate with the phase
      function near its peak (p(0) = 345/sr for 8 um droplets), which the angle profile (~1/alpha) samples too
      rarely (docs/results/fit_models.md). None (default): `PEAKED_PHASE_LOBE` where the medium's phase function
      has `sharp_forward_peak` (`Droplet`), else 0 (the other phase functions' images unchanged). Used only with
      the light-angle lobe (`light_lobe` > 0) in a scene with fog.
    """

    estimator: str = eqx.field(static=True, default="detached")
    equiangular: bool = eqx.field(static=True, default=True)
    light_lobe: float = eqx.field(static=True, default=0.3)
    distance_mix: float = eqx.field(static=True, default=0.15)
    phase_lobe: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"SamplingOptions.estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if not isinstance(self.equiangular, bool):
            raise TypeError(f"SamplingOptions.equiangular must be True or False, got {self.equiangular!r}")
        for name in ("light_lobe", "distance_mix"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise TypeError(f"SamplingOptions.{name} must be a number in [0, 1), got {type(v).__name__} {v!r}")
            if not 0.0 <= v < 1.0:  # also refuses NaN
                raise ValueError(f"SamplingOptions.{name} must be in [0, 1), got {v!r}")
        v = self.phase_lobe
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise TypeError(f"SamplingOptions.phase_lobe must be None or a number in [0, 1], "
                                f"got {type(v).__name__} {v!r}")
            if not 0.0 <= v <= 1.0:  # also refuses NaN
                raise ValueError(f"SamplingOptions.phase_lobe must be None or in [0, 1], got {v!r}")


PEAKED_PHASE_LOBE = 0.5
"""`SamplingOptions.phase_lobe` by default for a phase function with `sharp_forward_peak`: half the lobe's
directions from the phase function about the light, half from the angle profile (which also serves a segment
passing near the light, and surface vertices). Measured on droplet_fit_side at max_depth 3 (d = 8 um): the variance of
the image mean at equal spp 5.6x lower than with the angle profile alone (docs/results/fit_models.md)."""


def sampling_medium(medium: AbstractMedium | None, options: SamplingOptions, proposal=None):
    """The sampler for the chosen estimator: the medium whose values decide distances, branches and phase samples."""
    if medium is None:
        return None
    if not medium.supports_estimator(options.estimator):
        raise ValueError(f'estimator="{options.estimator}" is not defined for this {type(medium).__name__} '
                         f'(its docstring says which are); use "detached" or "proposal"')
    if options.estimator == "reparam":
        return medium
    if options.estimator == "detached":
        return jax.lax.stop_gradient(medium)
    if proposal is None:
        raise ValueError('estimator="proposal" needs proposal=<a medium of the same kind with reference values>')
    if type(proposal) is not type(medium):
        raise TypeError(f"proposal must be a {type(medium).__name__} like the scene's medium, "
                        f"got {type(proposal).__name__}")
    box = medium.bounds
    if (box is None) != (proposal.bounds is None):
        raise ValueError("proposal must have bounds exactly where the scene's medium has them (its values sample; "
                         "the fog's box is the scene's)")
    if box is not None:  # the proposal's values sample the distances; the fog's geometry is the scene's
        proposal = eqx.tree_at(lambda m: m.bounds, proposal, box)
    return jax.lax.stop_gradient(proposal)


# -------------------------------------------------------------------------------------------- random-number layout
@dataclasses.dataclass(frozen=True)
class Layout:
    """Which uniform of a bounce's row feeds which decision (static, built from the scene's structure).

    Fixed dimensions: `free_flight` (branch and distance), `polar` and `azimuth` (the scattering direction, shared
    by every technique), `choice` (a BSDF's discrete choice: Fresnel reflection or refraction), `channel` (the same
    column as `choice`: the spectral channel whose density draws a medium vertex's distance; a medium vertex has no
    BSDF choice, and the branch decision does not read it, so a surface vertex still sees it uniform), `lobe` and
    `lobe_light` (take the light-angle lobe; which light), `mix` and `mix_light` (place the vertex by equiangular
    sampling; toward which light). Then `lights[i]`: the first of light i's `n_dims` uniforms (scene order),
    `equiangular[j]`: one per point-like light, and `rr` (Russian roulette; only for `max_depth = -1`, else None).
    """

    lights: tuple
    equiangular: tuple
    n_dims: int
    rr: int | None = None
    free_flight: int = 0
    polar: int = 1
    azimuth: int = 2
    choice: int = 3
    channel: int = 3
    lobe: int = 4
    lobe_light: int = 5
    mix: int = 6
    mix_light: int = 7


N_FIXED_DIMS = 8


def layout(scene: Scene) -> Layout:
    """The bounce layout of `scene`: 8 fixed dimensions, each light's own, one per point-like light."""
    starts, k = [], N_FIXED_DIMS
    for light in scene.lights:
        starts.append(k)
        k += light.n_dims
    eq = tuple(range(k, k + len(scene.point_lights)))
    k += len(eq)
    if scene.max_depth == -1:
        return Layout(lights=tuple(starts), equiangular=eq, n_dims=k + 1, rr=k)
    return Layout(lights=tuple(starts), equiangular=eq, n_dims=k)


def n_dims(scene: Scene) -> int:
    """Uniform random numbers one bounce consumes."""
    return layout(scene).n_dims


def n_iterations(scene: Scene) -> int:
    """Segments to trace for a fixed `max_depth`: the last segment (number max_depth) only matters when it can hit
    an area light. (Unbounded paths, `max_depth = -1`, are traced by `_render`'s regenerating loop instead.)"""
    if scene.max_depth == -1:
        raise ValueError("n_iterations: a scene with max_depth = -1 has no fixed number of segments")
    return scene.max_depth if scene.area_lights else scene.max_depth - 1


# ---------------------------------------------------------------------------------------------------- structs
class Tracer(NamedTuple):
    """What every stage needs: the scene and its packed geometry, the medium and its sampler, the layout, and the
    static switches derived from the options and the scene (`lobe`, `mix`: probabilities, 0 when unused)."""

    scene: Scene
    pk: Packed
    medium: AbstractMedium | None
    sampler: AbstractMedium | None
    layout: Layout
    reparam: bool
    equiangular: bool
    lobe: float
    mix: float
    phase_lobe: float = 0.0
    barriers: bool = False
    guard: Array | None = None  # a traced scalar for `computed_once`'s predicate (None: the camera's fov)


def make_tracer(scene: Scene, pk: Packed, options: SamplingOptions, proposal=None) -> Tracer:
    has_points = bool(scene.point_lights)
    reparam = options.estimator == "reparam"
    eq = options.equiangular and scene.medium is not None and has_points
    lobe = float(options.light_lobe) if (has_points and not reparam) else 0.0
    phase_lobe = 0.0
    if lobe > 0 and scene.medium is not None:
        phase_lobe = float(options.phase_lobe if options.phase_lobe is not None else
                           PEAKED_PHASE_LOBE if type(scene.medium.phase).sharp_forward_peak else 0.0)
    return Tracer(
        scene=scene, pk=pk, medium=scene.medium, sampler=sampling_medium(scene.medium, options, proposal),
        layout=layout(scene), reparam=reparam, equiangular=eq, lobe=lobe,
        mix=float(options.distance_mix) if (eq and not reparam) else 0.0, phase_lobe=phase_lobe,
        barriers=jax.default_backend() == "cpu",
    )


class PathState(NamedTuple):
    o: Float[Array, "3"]
    d: Float[Array, "3"]
    beta: Float[Array, "3"]  # throughput, RGB
    L: Float[Array, "3"]  # accumulated radiance, RGB
    alive: Array  # bool
    specular: Array  # bool: last direction came from the camera or a delta BSDF (emitter hits get MIS weight 1)
    pdf_dir: Float[Array, ""]  # solid-angle pdf of the last sampled direction (for MIS with area lights)
    in_medium: Array  # bool: outside glass objects, so in the fog


class Hit(NamedTuple):
    """The nearest surface along the ray: distance `t` (inf on a miss), shape index `idx`, front normal `n`,
    `found`, and the point `p` (the ray origin on a miss)."""

    t: Float[Array, ""]
    idx: Array
    n: Float[Array, "3"]
    found: Bool[Array, ""]
    p: Float[Array, "3"]


class Segment(NamedTuple):
    """The free-flight decision on the segment to the hit: its length `s`, the equiangular samplers `eq` and
    samples `t_eq` (one per point-like light), the equiangular densities `p_eq` at the vertex distance `t` (one per
    point-like light), the branch probability `q`, `scattered`, the medium vertex's distance `t` and point `p`, its
    density `pdf` (all techniques), and the two branch weights."""

    s: Float[Array, ""]
    eq: tuple
    t_eq: tuple
    p_eq: tuple
    q: Float[Array, ""]
    scattered: Bool[Array, ""]
    t: Float[Array, ""]
    p: Float[Array, "3"]
    pdf: Float[Array, ""]
    w_med: RGB
    w_surf: RGB


class Direction(NamedTuple):
    """The bounce's scattering direction `wo` (one construction, whichever technique drew it), the phase sampler's
    polar sample `phase`, whether the light-angle lobe drew it (`take_lobe`), the lobe's point `x_lobe` and its pdf
    at `wo` (`lobe_pdf`)."""

    wo: Float[Array, "3"]
    phase: Polar | None
    take_lobe: Bool[Array, ""] | None
    x_lobe: Float[Array, "3"] | None
    lobe_pdf: Float[Array, ""] | None


class Next(NamedTuple):
    """A vertex's continuation: origin, direction, throughput, specular flag, direction pdf, alive, in_medium."""

    o: Float[Array, "3"]
    d: Float[Array, "3"]
    beta: RGB
    specular: Bool[Array, ""]
    pdf: Float[Array, ""]
    alive: Bool[Array, ""]
    in_medium: Bool[Array, ""]


def rgb_safe_div(x, b) -> RGB:
    """`safe_div(x, b)` per channel of `x` (an RGB value) by the scalar `b`."""
    return RGB(*(safe_div(c, b) for c in RGB.of(x)))


def rgb_safe_mul(x, y) -> RGB:
    """`safe_mul(x, y)` per channel: `x * y`, exactly 0 with a zero derivative in the channels where `y` (a
    transmittance, RGB or a scalar) is 0."""
    return RGB(*(safe_mul(a, b) for a, b in zip(RGB.of(x), RGB.of(y))))


# -------------------------------------------------------------------------------------------------- geometry
NO_NORMAL = (0.0, 0.0, 1.0)
"""The normal a ray that meets nothing gets (never used: the path ends)."""


def intersect(pk: Packed, o, d) -> Hit:
    """Nearest hit of the ray `(o, d)` over every shape, in two steps (`AbstractShape.intersect`, then `surface` of
    the hit): the stacked groups' nearest hit by `argmin` (`vmap` of each class's `intersect` over its stack) and
    their surface there (every stacked shape's `surface` at that distance, the hit one's kept: one vector operation
    per group), then each other shape's hit and surface where it is nearer (it may stop its search at the distance
    found so far). The normal is the shape's front normal (a smooth mesh's: its shading normal)."""
    groups = [g for g in pk.groups if g.stacked]
    if groups:
        hits = [jax.vmap(lambda s: s.intersect(o, d, jnp.float32(jnp.inf)))(g.shapes) for g in groups]
        t_all = jnp.concatenate([h.t for h in hits])
        idx = jnp.argmin(t_all)
        t = t_all[idx]
        hit = ShapeHit(t, jnp.isfinite(t), jnp.concatenate([h.prim for h in hits])[idx])
        surfaces = [jax.vmap(lambda s: s.surface(o, d, hit))(g.shapes) for g in groups]
        n = jnp.concatenate([sp.n for sp in surfaces])[idx]  # (a stacked shape's surface keeps hit.t)
    else:
        t, idx, n = jnp.float32(jnp.inf), jnp.int32(0), jnp.array(NO_NORMAL, jnp.float32)
    for g in pk.groups:
        if not g.stacked:
            h = g.shapes.intersect(o, d, jax.lax.stop_gradient(t))
            sp = g.shapes.surface(o, d, h)
            t, idx, n = jnp.where(h.found, sp.t, t), jnp.where(h.found, g.start, idx), jnp.where(h.found, sp.n, n)
    found = jnp.isfinite(t)
    p = o + jnp.where(found, t, 0.0) * d
    return Hit(t, idx, n, found, p)


def occluded(pk: Packed, o, d, dist) -> Array:
    """Whether any shape blocks the segment from `o` along unit `d` before distance `dist` (slightly shortened):
    `AbstractShape.any_hit`, `vmap`-ed over each stacked group."""
    limit = dist * (1.0 - 1e-4)
    stacked = [jax.vmap(lambda s: s.any_hit(o, d, limit))(g.shapes) for g in pk.groups if g.stacked]
    blocked = jnp.any(jnp.concatenate(stacked)) if stacked else jnp.bool_(False)
    for g in pk.groups:
        if not g.stacked:
            blocked = blocked | g.shapes.any_hit(o, d, limit)
    return blocked


def pick(values, u):
    """`values[i]` for the light `i = floor(u n)` drawn uniformly; no per-lane gather (slow on a CPU) for one."""
    if len(values) == 1:
        return values[0]
    i = jnp.minimum((u * len(values)).astype(jnp.int32), len(values) - 1)
    return jnp.stack(values)[i]


# ---------------------------------------------------------------------------------------------- free flight
def vertex_pdf(tr: Tracer, o, d, s, q, eqs, t, p_eqs):
    """Density of the path's medium vertex at distance `t` on the segment: the free-flight density (branch
    probability `q` included), mixed with the equiangular densities `p_eqs` (each light's `equiangular_pdf` at `t`,
    computed by the caller, who needs them too) when the distance mixture is on."""
    p_ff = tr.sampler.free_flight_pdf(o, d, s, q, t)
    if tr.mix == 0:
        return p_ff
    p_eq = sum(jnp.where(e.valid, pe, tr.sampler.free_flight_pdf(o, d, s, 1.0, t))
               for e, pe in zip(eqs, p_eqs)) / len(eqs)
    return (1.0 - tr.mix) * p_ff + tr.mix * q * p_eq


def free_flight(tr: Tracer, state: PathState, hit: Hit, U) -> Segment:
    """Medium branch (a vertex at `t`) or surface branch; the equiangular set-up of the segment toward each
    point-like light (its distances do not depend on the medium)."""
    ly, med, o, d = tr.layout, tr.medium, state.o, state.d
    s = jnp.minimum(hit.t, med.extent)
    eqs, t_eq = [], []
    if tr.equiangular:
        a, b = med.fog_interval(o, d, s)  # (0, s) for fog that fills space
        for j, light in enumerate(tr.scene.point_lights):
            t0, t1 = computed_once(tr, light.lit_interval(o, d))  # (a spot's cone: ~35 operations)
            e = equiangular_setup(light.position, o, d, jnp.maximum(a, t0), jnp.minimum(b, t1), once=barrier(tr))
            eqs.append(e)
            t_eq.append(equiangular_sample(e, U[ly.equiangular[j]], s))
        # every later value of the segment reads the samplers (the spot cone's interval, two arctangents)
        eqs, t_eq = computed_once(tr, (eqs, t_eq))
    # the surface branch's share is kept >= 1 - Q_MAX_SURFACE only on view segments (from the camera or a specular
    # chain), where it lets the camera see surfaces behind thick fog; on the other segments it would multiply a long
    # path's weight by albedo m / q > 1 at every vertex near a surface and make the weights heavy-tailed
    cap = hit.found & state.specular
    fl = computed_once(tr, tr.sampler.sample_free_flight(o, d, s, cap, state.in_medium, U[ly.free_flight],
                                                         U[ly.channel]))  # every channel's weight reads it
    t = fl.t
    if tr.mix > 0:
        # the vertex distance is drawn from a mixture: free flight, or equiangular toward a light (the path then
        # continues from near the light often enough to make the 1/r light there cheap)
        use_eq = (U[ly.mix] < tr.mix) & pick([e.valid for e in eqs], U[ly.mix_light])
        t = jnp.where(use_eq, pick(t_eq, U[ly.mix_light]), t)
    t = jnp.where(fl.scattered, t, 0.0)
    p = o + t * d
    p_eq = tuple(equiangular_pdf(e, t) for e in eqs)
    pdf = computed_once(tr, vertex_pdf(tr, o, d, s, fl.q, eqs, t, p_eq))  # every channel's weight reads it
    if tr.mix > 0:
        w_med = RGB.of(med.scattering(p)) * rgb_safe_div(med.transmittance(o, d, t), pdf)
    else:
        w_med = RGB.of(med.collision_weight(tr.sampler, o, d, s, jnp.where(fl.scattered, fl.q, 1.0), t))
    # double where: on a segment that escapes (no surface) the surface branch is never used, and its weight at
    # s = extent overflows for a proposal that samples more densely than the medium (0 * inf)
    on_surf = state.in_medium & hit.found
    w_surf = where_rgb(on_surf, med.surface_weight(o, d, jnp.where(on_surf, s, 0.0),
                                                   jnp.where(on_surf, fl.log_one_minus_q, 0.0)), 1.0)
    return Segment(s, tuple(eqs), tuple(t_eq), p_eq, fl.q, fl.scattered, t, p, pdf, w_med, w_surf)


def no_flight(hit: Hit) -> Segment:
    """The segment of a scene without fog: always the surface branch, weight 1."""
    z, one = jnp.float32(0.0), RGB.of(jnp.float32(1.0))
    return Segment(hit.t, (), (), (), z, jnp.bool_(False), z, hit.p, z, one, one)


# ----------------------------------------------------------------------------------------------- direct light
def light_uniforms(tr: Tracer, i: int, U):
    """The uniforms light `i` (in `scene.lights` order) gives its `sample_li`: its `n_dims` dimensions of the
    bounce's row (`Layout.lights`)."""
    return U[tr.layout.lights[i]:tr.layout.lights[i] + tr.scene.lights[i].n_dims]


def direct_on_segment(tr: Tracer, state: PathState, seg: Segment, ok, U) -> RGB:
    """Light scattered toward the camera along the segment from each point-like light (`sample_li` at its
    equiangular sample); MIS (balance heuristic) with the path's own medium vertex."""
    med, pk, o, d = tr.medium, tr.pk, state.o, state.d
    L = RGB.of(jnp.float32(0.0))
    scene_index = {id(lt): i for i, lt in enumerate(tr.scene.lights)}
    for j, (light, e, te) in enumerate(zip(tr.scene.point_lights, seg.eq, seg.t_eq)):
        p_eq = equiangular_pdf(e, te)
        p_eqs = tuple(p_eq if k == j else equiangular_pdf(ek, te) for k, ek in enumerate(seg.eq))
        xe = o + te * d
        ls = light.sample_li(xe, light_uniforms(tr, scene_index[id(light)], U))  # a delta light: pdf 1
        wi, dist, rgb, k = ls.wi, ls.dist, ls.rgb, ls.scale  # the light's value is rgb * k
        live = ok & state.in_medium & e.valid & (p_eq > 0)
        # double where: an unused sample's MIS denominator can be ~1e-30 (dense fog), whose 1/x^2 overflows
        p_all = jnp.where(live, p_eq + vertex_pdf(tr, o, d, seg.s, seg.q, seg.eq, te, p_eqs), 1.0)
        use = live & ~occluded(pk, xe, wi, dist)
        # what every channel reads (the shadow ray, the light's profile, the phase function, the MIS weight),
        # computed once; the factors are kept apart and multiplied in the order of the radiometry (their product
        # alone can overflow where the whole contribution does not: a peaked phase function next to a light)
        ph, inv_p, k, wi, dist, use = computed_once(
            tr, (med.phase.eval(d, wi), safe_div(1.0, p_all), k, wi, dist, use))
        f = RGB.of(med.scattering(xe)) * med.transmittance(o, d, te) * ph
        # a shadow ray's transmittance that underflows to 0 (dense fog) zeroes the contribution and its derivative:
        # the derivative of the factors before it can overflow float32 where their value does not (the score of a
        # peaked phase function, ~1/(1 - g) a vertex), and inf * 0 is NaN
        c = rgb_safe_mul(state.beta * f * (rgb * k), med.transmittance(xe, wi, dist)) * inv_p
        L = L + where_rgb(use, c, 0.0)
    return L


def nee(tr: Tracer, U, p, shadow_o, response: Callable, dir_pdf: Callable, beta: RGB, ok, seg: Segment | None) -> RGB:
    """Next-event estimation from the vertex `p` (one shadow ray per light, from `shadow_o`).

    `response(wi) -> RGB`: phase value or BSDF x cosine; `dir_pdf(wi)`: the density with which the vertex's own
    direction sampling picks `wi` (MIS with area lights); `seg`: for a medium vertex with equiangular segments, the
    balance-heuristic weight against the equiangular technique toward each point-like light."""
    scene = tr.scene
    L = RGB.of(jnp.float32(0.0))
    point_index = {id(lt): j for j, lt in enumerate(scene.point_lights)}  # their equiangular techniques
    order = [i for i, lt in enumerate(scene.lights) if lt.is_delta] + [i for i, lt in enumerate(scene.lights)
                                                                       if not lt.is_delta]
    for i in order:
        light = scene.lights[i]
        # the value as rgb * scale (a spot's profile and 1 / dist^2: a scalar)
        wi, dist, rgb, scale, pdf = light.sample_li(p, light_uniforms(tr, i, U))
        vis = ~occluded(tr.pk, shadow_o, wi, dist)
        if light.is_delta:
            weight, use = jnp.float32(1.0), ok & vis
            if seg is not None and id(light) in point_index:
                p_eq = seg.p_eq[point_index[id(light)]]
                weight = jnp.where(seg.scattered, safe_div(seg.pdf, seg.pdf + p_eq), 1.0)
        else:
            weight = safe_div(power_heuristic(pdf, dir_pdf(wi)), pdf)
            use = ok & vis & (pdf > 0)
        # what every channel reads (the shadow ray, the response, the light's profile, the MIS weight), computed once
        resp, scale, weight, wi, dist, use = computed_once(tr, (response(wi), scale, weight, wi, dist, use))
        tr_l = tr.medium.transmittance(p, wi, dist) if tr.medium is not None else 1.0
        c = rgb_safe_mul(beta * resp * (rgb * scale), tr_l) * weight  # as in direct_on_segment: no inf * 0
        L = L + where_rgb(use, c, 0.0)
    return L


# ------------------------------------------------------------------------------------------ scattering direction
def next_direction(tr: Tracer, state: PathState, hit: Hit, seg: Segment, U) -> Direction:
    """The scattering direction, built once from whichever technique drew it: the sampler's phase function around
    `d` (medium vertex), a lobe BSDF around the normal (its kind), or the light-angle lobe around the direction to
    a light (probability `tr.lobe`). All draw the polar angle from `polar` and the azimuth from `azimuth`."""
    ly, pk = tr.layout, tr.pk
    cands = []  # (mask, polar, axis); the last one is the default
    ph = tr.sampler.phase.sample_polar(U[ly.polar]) if tr.medium is not None else None
    if tr.lobe > 0:
        x_lobe = jnp.where(seg.scattered, seg.p, hit.p) if tr.medium is not None else hit.p
        take_lobe = U[ly.lobe] < tr.lobe
        target = pick([lt.position for lt in tr.scene.point_lights], U[ly.lobe_light])
        polar = light_lobe_cos(U[ly.polar])
        if tr.phase_lobe > 0:  # part of the lobe: the phase function's own polar law about the light's direction
            use_ph = U[ly.lobe] < tr.lobe * tr.phase_lobe
            polar = Polar(*(jnp.where(use_ph, a, b) for a, b in zip(ph, polar)))
        cands.append((take_lobe, polar, safe_normalize(target - x_lobe)))
    if tr.medium is not None:
        cands.append((seg.scattered, ph, state.d))
    kind = jnp.asarray(pk.bsdf_kind)[hit.idx] if pk.n_shapes else None
    for k, t in enumerate(pk.bsdf_types):
        if issubclass(t, AbstractLobeBSDF):
            bsdf = jax.tree.map(lambda x: x[hit.idx], pk.bsdfs[k])
            cands.append((kind == k, bsdf.sample_polar(U[ly.polar]), hit.n))
    if not cands:
        return Direction(state.d, None, None, None, None)
    _, polar, axis = cands[-1]
    omc, opc = polar
    for mask, (omc_c, opc_c), axis_c in reversed(cands[:-1]):
        omc, opc, axis = jnp.where(mask, omc_c, omc), jnp.where(mask, opc_c, opc), jnp.where(mask, axis_c, axis)
    omc, opc, axis = computed_once(tr, (omc, opc, axis))  # the chosen technique's polar sample and axis
    wo = to_direction(Polar(omc, opc), U[ly.azimuth], axis)
    if tr.lobe == 0:
        return Direction(wo, ph, None, None, None)
    return Direction(wo, ph, take_lobe, x_lobe, lobe_pdf(tr, wo, x_lobe))


def lobe_pdf(tr: Tracer, w, x):
    """Density of the light-angle lobe at `w` from `x`, averaged over the point-like lights (with `phase_lobe`, the
    mixture of the angle profile and the sampler's phase function about the direction to the light)."""
    def one(light):
        p = light_lobe_pdf(w, x, light.position, once=barrier(tr))
        if tr.phase_lobe == 0:
            return p
        q = tr.sampler.phase.pdf_polar(one_minus_cos_between(w, safe_normalize(light.position - x)))
        return (1.0 - tr.phase_lobe) * p + tr.phase_lobe * q

    lights = tr.scene.point_lights
    return sum(one(lt) for lt in lights) / len(lights)


def mix_lobe(tr: Tracer, pdf, lobe_p):
    """The direction density of the technique `pdf` mixed with the light-angle lobe (if on)."""
    return pdf if tr.lobe == 0 else (1.0 - tr.lobe) * pdf + tr.lobe * lobe_p


# --------------------------------------------------------------------------------------------------- vertices
def medium_vertex(tr: Tracer, state: PathState, seg: Segment, dr: Direction) -> Next:
    """Continuation from the medium vertex: the phase function's value over the mixture's density."""
    phase, sphase = tr.medium.phase, tr.sampler.phase
    beta = state.beta * seg.w_med
    omc = dr.phase.one_minus_cos
    if tr.reparam:  # the direction carries the derivative; sampling is exact, so the weight p / p is 1
        pdf = sphase.pdf_polar(omc)
        if phase.sampled_exactly:
            beta_next = beta
        else:
            value, pdf = computed_once(tr, (phase.eval_polar(omc), pdf))  # every channel reads them
            beta_next = beta * value / pdf
    else:
        if tr.lobe > 0:
            omc = jnp.where(dr.take_lobe, one_minus_cos_between(state.d, dr.wo), omc)
        pdf = mix_lobe(tr, sphase.pdf_polar(omc), dr.lobe_pdf)
        value, pdf = computed_once(tr, (phase.eval_polar(omc), pdf))  # every channel reads them
        beta_next = beta * value / pdf
    t, f = jnp.bool_(True), jnp.bool_(False)
    return Next(seg.p, dr.wo, beta_next, f, pdf, t, state.in_medium)


def emission(tr: Tracer, state: PathState, hit: Hit, seg: Segment) -> RGB:
    """Emission of an area light hit by the path on its surface branch (MIS with the light's sampling; weight 1
    after a specular direction), RGB."""
    L = RGB.of(jnp.float32(0.0))
    surf = state.alive & ~seg.scattered & hit.found
    for light, shape in zip(tr.scene.area_lights, tr.pk.emitter_shape):
        w = jnp.where(state.specular, 1.0, power_heuristic(state.pdf_dir, light.pdf_li(state.o, state.d, hit.t)))
        w = computed_once(tr, w)  # every channel reads it
        L = L + where_rgb(surf & (hit.idx == shape), state.beta * seg.w_surf * light.emitted(state.d, hit.n) * w, 0.0)
    return L


def surface_vertex(tr: Tracer, state: PathState, hit: Hit, seg: Segment, dr: Direction, U) -> Next:
    """The BSDF's continuation from the surface vertex (a path that hits an area light ends there)."""
    pk, ly, d, n = tr.pk, tr.layout, state.d, hit.n
    beta = state.beta * seg.w_surf
    surf = state.alive & ~seg.scattered & hit.found
    front = dot(d, n) < 0
    wo, beta_next, spec, pdf, alive, in_med = d, beta, jnp.bool_(True), jnp.float32(0.0), surf, state.in_medium
    if pk.n_shapes == 0:
        return Next(hit.p, wo, beta_next, spec, pdf, alive, in_med)
    kind = jnp.asarray(pk.bsdf_kind)[hit.idx]
    if tr.scene.area_lights:
        alive = alive & (kind != EMITTER_KIND)
    for k, t in enumerate(pk.bsdf_types):
        is_k = kind == k
        bsdf = jax.tree.map(lambda x: x[hit.idx], pk.bsdfs[k])
        if issubclass(t, AbstractLobeBSDF):  # one-sided: a path arriving at the back ends
            cos_o = dot(n, dr.wo)
            pdf_k = mix_lobe(tr, bsdf.pdf_cos(cos_o), dr.lobe_pdf)
            value, pdf_k = computed_once(tr, (bsdf.eval_cos(-dot(d, n), cos_o), pdf_k))  # every channel reads them
            beta_k = beta * rgb_safe_div(value, pdf_k)
            wo, beta_next = jnp.where(is_k, dr.wo, wo), where_rgb(is_k, beta_k, beta_next)
            spec, pdf = jnp.where(is_k, False, spec), jnp.where(is_k, pdf_k, pdf)
            alive = alive & ~(is_k & ~front)
        else:
            bs = bsdf.sample(d, n, U[ly.polar:ly.choice + 1])
            wo, beta_next = jnp.where(is_k, bs.wo, wo), where_rgb(is_k, beta * bs.weight, beta_next)
            in_med = jnp.where(is_k & bs.transmitted, ~front, in_med)
    side = jnp.where(dot(wo, n) >= 0, 1.0, -1.0)  # rays leave a surface from the side they go to
    return Next(hit.p + side * EPS_OFFSET * n, wo, beta_next, spec, pdf, alive, in_med)


def direct_at_vertex(tr: Tracer, state: PathState, hit: Hit, seg: Segment, ok, U) -> RGB:
    """NEE from the bounce's vertex: the medium vertex (phase function) or the surface vertex (a lobe BSDF on its
    front face); delta BSDFs see no light sample."""
    pk, d, n = tr.pk, state.d, hit.n
    lobe_kinds = [k for k, t in enumerate(pk.bsdf_types) if issubclass(t, AbstractLobeBSDF)]
    if tr.medium is None and not lobe_kinds:
        return RGB.of(jnp.float32(0.0))
    med_v = seg.scattered
    kind = jnp.asarray(pk.bsdf_kind)[hit.idx] if pk.n_shapes else None
    on_lobe = sum((kind == k).astype(jnp.int32) for k in lobe_kinds) > 0 if lobe_kinds else jnp.bool_(False)
    surf_ok = state.alive & ~med_v & hit.found & (dot(d, n) < 0) & on_lobe
    ok_v = ok & (med_v | surf_ok)
    p_v = jnp.where(med_v, seg.p, hit.p)
    shadow_o = jnp.where(med_v, p_v, hit.p + EPS_OFFSET * n)
    beta_v = state.beta * where_rgb(med_v, seg.w_med, seg.w_surf)
    bsdfs = [(kind == k, jax.tree.map(lambda x: x[hit.idx], pk.bsdfs[k])) for k in lobe_kinds]

    def response(wi):
        r = RGB.of(jnp.float32(0.0))
        for is_k, b in bsdfs:
            r = where_rgb(is_k, b.eval(d, wi, n), r)
        return where_rgb(med_v, tr.medium.phase.eval(d, wi), r) if tr.medium is not None else r

    def dir_pdf(wi):
        pdf = jnp.float32(0.0)
        for is_k, b in bsdfs:
            pdf = jnp.where(is_k, b.pdf(d, wi, n), pdf)
        if tr.medium is not None:
            pdf = jnp.where(med_v, tr.sampler.phase.pdf(d, wi), pdf)
        return mix_lobe(tr, pdf, lobe_pdf(tr, wi, p_v) if tr.lobe > 0 else None)

    return nee(tr, U, p_v, shadow_o, response, dir_pdf, beta_v, ok_v, seg if tr.equiangular else None)


# ------------------------------------------------------------------------------------------------- the tracer
def update(state: PathState, seg: Segment, L: RGB, med: Next | None, surf: Next) -> PathState:
    """The next path state: the medium vertex's continuation where the path scattered, else the surface's; a path
    whose throughput exceeds `BETA_MAX` ends."""
    if med is None:
        nxt, alive = surf, surf.alive
    else:
        nxt = Next(*(where_rgb(seg.scattered, a, b) if isinstance(a, RGB) else jnp.where(seg.scattered, a, b)
                     for a, b in zip(med, surf)))
        alive = state.alive & (seg.scattered | surf.alive)
    b = nxt.beta
    alive = alive & (b.r <= BETA_MAX) & (b.g <= BETA_MAX) & (b.b <= BETA_MAX)  # (NaN compares False)
    return PathState(nxt.o, nxt.d, where_rgb(alive, nxt.beta, 0.0).array(), L.array(), alive, nxt.specular, nxt.pdf,
                     nxt.in_medium)


def computed_once(tr: Tracer, x):
    """`x` (a pytree of arrays) unchanged, computed once: a fusion barrier for XLA's CPU backend (speed only).

    XLA's CPU fusion copies cheap producers (arithmetic, selects, comparisons) into every kernel that consumes them,
    so a value that several later stages read (a segment's distances, weights and densities; the scattering
    direction) is recomputed inside each of their kernels, and the kernels grow until LLVM spills them.
    `lax.optimization_barrier` does not prevent it (the CPU pipeline removes barriers before fusion). A `lax.cond`
    on an unbatched, traced predicate is kept, and its operands are then computed once, into buffers, by the
    kernels before it. Both branches return `x`'s values (the second adds zeros, so XLA cannot merge the two), so
    the predicate decides nothing; it must only be a value XLA cannot fold to a constant: `tr.guard`, which the
    render loops set from their own traced data (a uniform of the work item; the regenerating loop's queue
    position), else whether the camera's fov is finite (a constant, and the barrier gone, when the scene is a
    constant of the compiled program). Only on the CPU backend (`tr.barriers`); elsewhere `x` is returned as it
    is. Where it pays is measured: `docs/results/bench/PROFILE.md`, "A sample at Mitsuba's cost"."""
    if not tr.barriers:
        return x
    pred = tr.guard if tr.guard is not None else jnp.isfinite(tr.scene.camera.fov)
    return jax.lax.cond(pred, lambda v: v, lambda v: jax.tree.map(lambda a: a + jnp.zeros_like(a), v), x)


def barrier(tr: Tracer) -> Callable:
    """`x -> computed_once(tr, x)`: the `once` argument of the pure functions that take one."""
    return lambda x: computed_once(tr, x)


def bounce(tr: Tracer, state: PathState, b, U, last=None) -> PathState:
    """One segment of the path and its vertex: the stages in order (the segment and the direction each computed
    once, `computed_once`: every later stage reads them).

    `last`: None, or a traced, unbatched bool that is True on the path's last segment, whose continuation (the
    scattering direction and the vertex's throughput) nothing reads: it is then skipped (`lax.cond`), and the
    state keeps its direction and throughput, with the new radiance. The radiance is the same either way."""
    nee_ok = state.alive if tr.scene.max_depth == -1 else state.alive & (b + 2 <= tr.scene.max_depth)
    state_in, state = state, state._replace(beta=RGB.of(state.beta), L=RGB.of(state.L))  # channels inside a bounce
    hit = intersect(tr.pk, state.o, state.d)
    with shared_ray_values():  # a medium's per-ray work on the segment, done once for all of its stages
        seg = computed_once(tr, free_flight(tr, state, hit, U) if tr.medium is not None else no_flight(hit))
        L = state.L
        if tr.equiangular:
            L = L + direct_on_segment(tr, state, seg, nee_ok, U)
        L = L + emission(tr, state, hit, seg) + direct_at_vertex(tr, state, hit, seg, nee_ok, U)

    def continuation(L):
        dr = computed_once(tr, next_direction(tr, state, hit, seg, U))
        med = medium_vertex(tr, state, seg, dr) if tr.medium is not None else None
        return update(state, seg, L, med, surface_vertex(tr, state, hit, seg, dr, U))

    if last is None:
        return continuation(L)
    return jax.lax.cond(last, lambda L: state_in._replace(L=L.array()), continuation, L)


def start_path(o, d) -> PathState:
    """The state of a camera path leaving `o` along `d`."""
    return PathState(
        o=o, d=d, beta=jnp.ones(3, jnp.float32), L=jnp.zeros(3, jnp.float32), alive=jnp.bool_(True),
        specular=jnp.bool_(True), pdf_dir=jnp.float32(0.0), in_medium=jnp.bool_(True),
    )


RR_MAX_SURVIVAL = 0.95
"""Largest Russian-roulette survival probability (Mitsuba's rule: `min(max_c beta_c, 0.95)`)."""


def russian_roulette(tr: Tracer, state: PathState, b, U) -> PathState:
    """After the bounce `b` (0-based), from vertex `rr_depth` on: the path survives with probability
    `q = min(max_c beta_c, 0.95)` (a sampling decision: never differentiated) and its throughput is divided by q.
    Mitsuba also multiplies by the squared relative IOR of the glass the path is in; jaxfog does not (any q > 0
    is unbiased; the choice only moves variance)."""
    q = jax.lax.stop_gradient(jnp.minimum(jnp.max(state.beta), RR_MAX_SURVIVAL))
    apply = b + 1 >= tr.scene.rr_depth
    survive = ~apply | (U[tr.layout.rr] < q)
    beta = jnp.where(apply, state.beta / jnp.where(q > 0, q, 1.0), state.beta)
    alive = state.alive & survive
    return state._replace(beta=jnp.where(alive, beta, 0.0), alive=alive)


def trace_path(tr: Tracer, o, d, U) -> Float[Array, "3"]:
    """Radiance (RGB) arriving at the camera along the ray `(o, d)` for a fixed `max_depth`; `U` holds
    `(n_iterations, n_dims)` uniforms."""
    init = start_path(o, d)
    if U.shape[0] == 0:
        return init.L
    n = U.shape[0]
    # the last segment's continuation is skipped where conditionals are cheap (the CPU backend, `tr.barriers`)
    last = (lambda b: b == n - 1) if tr.barriers else (lambda b: None)
    body = jax.checkpoint(lambda state, xs: (bounce(tr, state, xs[0], Uniforms(xs[1]), last(xs[0])), None))
    final, _ = jax.lax.scan(body, init, (jnp.arange(U.shape[0]), tuple(U[:, k] for k in range(U.shape[1]))))
    return final.L


class Uniforms:
    """A bounce's uniforms as one scalar per dimension (`U[k]`; a slice gives a small array): under `vmap`, each
    dimension is then a contiguous array over the lanes, not a strided column of a `(lanes, n_dims)` table."""

    def __init__(self, cols):
        self.cols = tuple(cols)

    def __getitem__(self, i):
        if isinstance(i, slice):
            cols = self.cols[i]
            return jnp.stack(cols) if cols else jnp.zeros((0,), jnp.float32)
        return self.cols[i]
