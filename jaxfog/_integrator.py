"""The volumetric path tracer for one camera path: written for one ray, `vmap`-ed once in `_render`.

The bounce body reads as its stages: intersect -> free flight (medium or surface branch) -> direct light along the
segment (equiangular, MIS with the free-flight vertex) -> direct light at the vertex (NEE to every light) -> scatter
(phase function or BSDF) -> update `PathState`. What a scene lacks (fog, glass, area lights, delta lights) is decided
in Python and never compiled.

Estimators (see `_medium` and `docs/estimators.md`) change only the *sampling* parameters `Proposal(sigma_hat, g_hat)`:
detached (`stop_gradient` of the medium's values), a caller's fixed proposal, or the medium's own values
(reparameterized: sampled distances and directions move with the parameters). Every weight is `f(theta) / pdf`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import _medium as M
from ._bsdf import cosine_cos, fresnel_dielectric, reflect, refract
from ._lights import AreaLight, SpotLight, delta_light_radiant_intensity
from ._math import INV_PI, PI, cross, dot, one_minus_cos_between, safe_div, safe_normalize, safe_sqrt
from ._phase import hg_pdf, hg_sample
from ._math import atan2, direction_from_cos, sincos, tan
from ._scene import DIFFUSE, EMITTER, GLASS, MIRROR, Packed, Scene
from ._shapes import intersect_rectangles, intersect_spheres

EPS_OFFSET = 1e-4
"""Offset (scene units) of rays leaving a surface, along the normal on the side they leave to."""

ESTIMATORS = ("detached", "reparam", "proposal")


class Proposal(NamedTuple):
    """Sampling parameters: `sigma_hat` (scalar sampling extinction, 1/scene unit) and `g_hat` (HG g used to sample)."""

    sigma_hat: Float[Array, ""]
    g_hat: Float[Array, ""]


class Options(NamedTuple):
    """Static integrator options (hashable): estimator name; equiangular sampling on/off; `light_lobe`: probability
    of sampling a scattering direction from the light-angle lobe instead of the phase function / cosine lobe
    (0 disables it; never used by the "reparam" estimator, whose directions must move with g); `distance_mix`:
    probability of placing the path's medium vertex by equiangular sampling instead of free flight (needs
    `equiangular`; not used by "reparam")."""

    estimator: str = "detached"
    equiangular: bool = True
    light_lobe: float = 0.3
    distance_mix: float = 0.15


class PathState(NamedTuple):
    o: Float[Array, "3"]
    d: Float[Array, "3"]
    beta: Float[Array, "3"]  # throughput, RGB
    L: Float[Array, "3"]  # accumulated radiance, RGB
    alive: Array  # bool
    specular: Array  # bool: last direction came from the camera or a delta BSDF (emitter hits get MIS weight 1)
    pdf_dir: Float[Array, ""]  # solid-angle pdf of the last sampled direction (for MIS with area lights)
    in_medium: Array  # bool: outside glass objects, so in the fog


def n_dims(scene: Scene) -> int:
    """Uniform random numbers one bounce consumes."""
    return 8 + 2 * len(scene.area_lights) + len(scene.delta_lights)


def n_iterations(scene: Scene) -> int:
    """Segments to trace: the last segment (number max_depth) only matters when it can hit an area light."""
    return scene.max_depth if scene.area_lights else scene.max_depth - 1


def make_proposal(scene: Scene, options: Options, proposal=None) -> Proposal:
    """Sampling parameters for the chosen estimator (see module docstring); `proposal` is a medium for "proposal"."""
    med = scene.medium
    if med is None:
        return Proposal(jnp.float32(1.0), jnp.float32(0.0))
    if options.estimator == "reparam":
        return Proposal(M.sampling_extinction(med.sigma_t), med.g)
    if options.estimator == "detached":
        return jax.lax.stop_gradient(Proposal(M.sampling_extinction(med.sigma_t), med.g))
    if options.estimator == "proposal":
        if proposal is None:
            raise ValueError('estimator="proposal" needs proposal=<HomogeneousMedium with reference sigma_t and g>')
        return jax.lax.stop_gradient(Proposal(M.sampling_extinction(proposal.sigma_t), proposal.g))
    raise ValueError(f"estimator must be one of {ESTIMATORS}, got {options.estimator!r}")


# ----------------------------------------------------------------------------------------------------------- geometry
def _hit_distances(pk: Packed, o, d):
    """Hit distances (> T_MIN, else inf) of the ray `o + t d` with every shape, in global shape order; None if none."""
    ts = []
    if pk.n_spheres:
        ts.append(intersect_spheres(o, d, pk.sph_center, pk.sph_radius))
    if pk.rect_center.shape[0]:
        ts.append(intersect_rectangles(o, d, pk.rect_center, pk.rect_u, pk.rect_v, pk.rect_normal))
    return jnp.concatenate(ts) if ts else None


def intersect(pk: Packed, o, d):
    """Nearest hit: `(t, index, normal)`; `t = inf` and index 0 on a miss. The normal is the geometric front normal."""
    t_all = _hit_distances(pk, o, d)
    if t_all is None:
        return jnp.float32(jnp.inf), jnp.int32(0), jnp.array([0.0, 0.0, 1.0], jnp.float32)
    idx = jnp.argmin(t_all)
    t = t_all[idx]
    p = o + jnp.where(jnp.isfinite(t), t, 0.0) * d
    normals = []
    if pk.n_spheres:
        normals.append(safe_normalize(p[None, :] - pk.sph_center))
    if pk.rect_center.shape[0]:
        normals.append(pk.rect_normal)
    n = jnp.concatenate(normals)[idx]
    return t, idx, n


def occluded(pk: Packed, o, d, dist) -> Array:
    """Whether anything blocks the segment from `o` along unit `d` before distance `dist` (slightly shortened)."""
    t_all = _hit_distances(pk, o, d)
    if t_all is None:
        return jnp.bool_(False)
    return jnp.min(t_all) < dist * (1.0 - 1e-4)


def power_heuristic(a, b):
    """MIS weight `a^2 / (a^2 + b^2)` (0 where both are 0)."""
    return safe_div(a * a, a * a + b * b)


# --------------------------------------------------------------------------------------------------------- lighting
def delta_incident(light, p):
    """Unoccluded, untransmitted irradiance factor from a point/spot light at `p`: `(wl, dist, I(-wl) / dist^2)`."""
    v = light.position - p
    dist2 = dot(v, v)
    dist = safe_sqrt(dist2)
    wl = safe_normalize(v)
    intensity = delta_light_radiant_intensity(light, -wl)
    return wl, dist, safe_div(intensity, dist2)


def area_sample(light: AreaLight, p, u):
    """Uniform point on an area light seen from `p`: `(wl, dist, Le (front face only), pdf over solid angle)`."""
    y = light.center + (u[0] - 0.5) * light.edge_u + (u[1] - 0.5) * light.edge_v
    v = y - p
    dist2 = dot(v, v)
    dist = safe_sqrt(dist2)
    wl = safe_normalize(v)
    cos_l = -dot(wl, light.normal)
    front = cos_l > 0
    pdf = jnp.where(front, safe_div(dist2, light.area * cos_l), 0.0)
    return wl, dist, jnp.where(front, light.radiance, 0.0), pdf


def area_pdf_hit(light: AreaLight, d, dist):
    """Solid-angle pdf with which `area_sample` would have produced the direction `d` hitting the light at `dist`."""
    cos_l = -dot(d, light.normal)
    return jnp.where(cos_l > 0, safe_div(dist * dist, light.area * cos_l), 0.0)


def spot_cone_interval(light: SpotLight, o, d):
    """Interval `[t0, t1]` (possibly empty: t0 > t1; possibly infinite) where the line `o + t d` is inside the spot's
    cutoff cone (the forward nappe). Outside it the spot sends no light, so equiangular samples are kept inside."""
    a = light.direction
    c2 = jnp.cos(jnp.deg2rad(light.cutoff_angle)) ** 2
    w = o - light.position
    da, wa = dot(d, a), dot(w, a)
    A = da * da - c2
    B = 2.0 * (da * wa - c2 * dot(d, w))
    C = wa * wa - c2 * dot(w, w)
    disc = B * B - 4.0 * A * C
    sq = safe_sqrt(disc)
    A_safe = jnp.where(jnp.abs(A) > 1e-12, A, 1e-12)
    r1 = (-B - sq) / (2.0 * A_safe)
    r2 = (-B + sq) / (2.0 * A_safe)
    lo, hi = jnp.minimum(r1, r2), jnp.maximum(r1, r2)
    inf = jnp.inf
    # A < 0: inside between the roots (one nappe; check which). A > 0: outside the roots, the nappe d points into.
    mid = 0.5 * (lo + hi)
    mid_fwd = (wa + mid * da) >= 0
    t0_neg = jnp.where((disc >= 0) & mid_fwd, lo, inf)
    t1_neg = jnp.where((disc >= 0) & mid_fwd, hi, -inf)
    t0_pos = jnp.where(disc >= 0, jnp.where(da > 0, hi, -inf), jnp.where(wa >= 0, -inf, inf))
    t1_pos = jnp.where(disc >= 0, jnp.where(da > 0, inf, lo), jnp.where(wa >= 0, inf, -inf))
    neg = A < 0
    return jnp.where(neg, t0_neg, t0_pos), jnp.where(neg, t1_neg, t1_pos)


def equiangular_setup(light, o, d, s):
    """Kulla–Fajardo equiangular sampling of `t` in `[ta, tb]` (a sub-interval of `[0, s]`) toward a light's
    position: returns `(delta, D, theta_a, theta_b, valid)`. For spot lights the interval is clipped to the cone."""
    c = light.position
    delta = dot(c - o, d)
    D = safe_norm_floor(c - o - delta * d)
    ta, tb = jnp.float32(0.0), s
    if isinstance(light, SpotLight):
        c0, c1 = spot_cone_interval(light, o, d)
        ta, tb = jnp.maximum(ta, c0), jnp.minimum(tb, c1)
    valid = tb > ta
    ta = jnp.where(valid, ta, 0.0)
    tb = jnp.where(valid, tb, 1.0)
    # float32(pi/2) is above pi/2, where tan flips sign: keep the angles strictly inside (-pi/2, pi/2)
    half_pi = 1.5707962
    th_a = jnp.clip(atan2(ta - delta, D), -half_pi, half_pi)
    th_b = jnp.clip(atan2(tb - delta, D), -half_pi, half_pi)
    valid = valid & (th_b > th_a)
    return delta, D, th_a, th_b, valid


def safe_norm_floor(v, floor=1e-7):
    return jnp.maximum(safe_sqrt(dot(v, v)), floor)


def equiangular_pdf(t, delta, D, th_a, th_b, valid):
    r = t - delta
    th = atan2(r, D)  # compare angles, not tan(theta) * D, which overflows for rays grazing the light
    inside = valid & (th >= th_a - 1e-6) & (th <= th_b + 1e-6)
    return jnp.where(inside, D / (jnp.where(valid, th_b - th_a, 1.0) * (D * D + r * r)), 0.0)


def light_lobe_cos(u, x, light_pos):
    """Polar part of `light_lobe_sample`: `(1 - cos alpha, 1 + cos alpha, axis)` for `alpha = pi (1 - sqrt(1 - u))`,
    u in [0, 1): the inverse of the lobe's polar cdf `1 - (1 - alpha / pi)^2`."""
    sin_h, cos_h = sincos(0.5 * PI * (1.0 - safe_sqrt(1.0 - u)))
    return 2.0 * sin_h * sin_h, 2.0 * cos_h * cos_h, safe_normalize(light_pos - x)


def light_lobe_sample(u, x, light_pos):
    """Direction from `x` at angle alpha to the direction toward `light_pos`, with density `2 (pi - alpha) / pi^2`
    in alpha (u[0]) and uniform in azimuth (phi = 2 pi u[1])."""
    omc, opc, a = light_lobe_cos(u[0], x, light_pos)
    return direction_from_cos(omc, opc, 2.0 * PI * u[1], a)


def light_lobe_pdf(w, x, light_pos):
    """Solid-angle pdf of `light_lobe_sample`: `(pi - alpha) / (pi^3 sin alpha)` (1/sr; its limit 1/pi^3 at
    alpha = pi; 0 at exactly alpha = 0, where it is infinite, a direction the sampler produces with probability 0).

    It is the angular profile of the light a point light sends into a line: a ray from `x` leaving at angle alpha
    to the light passes it at `D = r sin alpha` and, unattenuated and isotropically scattered, collects light
    `(pi - alpha) / D` (the angle the ray subtends at the light over D). So the lobe cancels the `1/D` of the light
    scattered along a segment passing near a point light (docs/estimators.md), for any direction the mixture produces."""
    a = safe_normalize(light_pos - x)
    omc = one_minus_cos_between(w, a)
    sin_a = safe_sqrt(omc * jnp.maximum(2.0 - omc, 0.0))
    beta = atan2(sin_a, omc - 1.0)  # pi - alpha, accurate near alpha = pi
    # double where: beta / sin(beta) -> 1 at beta = 0 (alpha = pi); beta = pi with sin_a = 0 (alpha = 0) gives 0
    ok = sin_a > 0
    ratio = jnp.where(ok, beta / jnp.where(ok, sin_a, 1.0), jnp.where(beta < 1.0, 1.0, 0.0))
    return ratio / PI ** 3


# ------------------------------------------------------------------------------------------------------- the tracer
def trace_path(scene: Scene, pk: Packed, prop: Proposal, options: Options, o, d, U) -> Float[Array, "3"]:
    """Radiance (RGB) arriving at the camera along the ray `(o, d)`; `U` holds `(n_iterations, n_dims)` uniforms."""
    med = scene.medium
    has_medium = med is not None
    kinds = pk.has
    has_glass = GLASS in kinds
    delta_lights = scene.delta_lights
    area_lights = scene.area_lights
    n_area = len(area_lights)
    use_equiangular = options.equiangular and has_medium and bool(delta_lights)
    reparam = options.estimator == "reparam"
    lam = float(options.light_lobe) if (delta_lights and not reparam) else 0.0
    n_delta = len(delta_lights)
    lam_d = float(options.distance_mix) if (use_equiangular and not reparam) else 0.0
    max_depth = scene.max_depth
    if has_medium:
        sigma_t, sigma_s, g = med.sigma_t, med.sigma_s, med.g
    area_emitter_index = {j: pk.kinds.shape[0] - n_area + j for j in range(n_area)}

    def transmit(dist):
        return M.transmittance(sigma_t, dist) if has_medium else jnp.ones(3, jnp.float32)

    def nee(p, shadow_o, response, dir_pdf, beta, ok, U_b, eq_mis=None):
        """Light sampling from the path vertex `p` (medium or surface; one shadow ray per light).

        `response(wl) -> RGB`: phase value or BRDF x cosine; `dir_pdf(wl)`: pdf with which the vertex's own direction
        sampling picks `wl` (MIS with area lights); `eq_mis = (setups, t, ff_pdf, is_med)`: balance-heuristic weight
        against the equiangular technique of the segment, for medium vertices only."""
        L = jnp.zeros(3, jnp.float32)
        for i, light in enumerate(delta_lights):
            wl, dist, E = delta_incident(light, p)
            vis = ~occluded(pk, shadow_o, wl, dist)
            c = beta * response(wl) * E * transmit(dist)
            if eq_mis is not None:
                setups, t_v, ff_pdf, is_med = eq_mis
                p_eq = equiangular_pdf(t_v, *setups[i])
                c = c * jnp.where(is_med, safe_div(ff_pdf, ff_pdf + p_eq), 1.0)
            L = L + jnp.where(ok & vis, c, 0.0)
        for j, light in enumerate(area_lights):
            wl, dist, Le, pdf = area_sample(light, p, U_b[8 + 2 * j : 10 + 2 * j])
            vis = ~occluded(pk, shadow_o, wl, dist)
            w = power_heuristic(pdf, dir_pdf(wl))
            c = beta * response(wl) * Le * transmit(dist) * safe_div(w, pdf)
            L = L + jnp.where(ok & vis & (pdf > 0), c, 0.0)
        return L

    def pick(values, u):
        """`values[i]` for the light `i = floor(u n)` drawn uniformly; no per-lane gather (slow on a CPU) when there
        is one light."""
        if len(values) == 1:
            return values[0]
        i = jnp.minimum((u * len(values)).astype(jnp.int32), len(values) - 1)
        return jnp.stack(values)[i]

    def lobe_pdf(w, x):
        return sum(light_lobe_pdf(w, x, lt.position) for lt in delta_lights) / len(delta_lights)

    def body(state: PathState, xs):
        b, U_b = xs
        nee_ok = state.alive & (b + 2 <= max_depth)
        s_hit, idx, n = intersect(pk, state.o, state.d)
        hit = jnp.isfinite(s_hit)
        L = state.L

        # ---- equiangular set-up of the segment toward each delta light (distances do not depend on the medium)
        if has_medium:
            active = state.in_medium
            s = jnp.minimum(s_hit, med.extent)
        eq_setups, eq_t = [], []
        if use_equiangular:
            for i, light in enumerate(delta_lights):
                setup = equiangular_setup(light, state.o, state.d, s)
                delta, D, th_a, th_b, valid = setup
                th = th_a + U_b[8 + 2 * n_area + i] * (th_b - th_a)
                te = jnp.clip(jnp.where(valid, delta + D * tan(th), 0.0), 0.0, s)
                eq_setups.append(setup)
                eq_t.append(te)

        # ---- free flight: medium branch (vertex at t) or surface branch
        if has_medium:
            q, log1mq = M.branch_probability(prop.sigma_hat, s, jnp.where(hit, M.Q_MAX_SURFACE, 1.0))
            q = jnp.where(active, q, 0.0)
            u = U_b[0]
            is_med = active & (u < q)
            x = jnp.where(is_med, safe_div(u, q), 0.0)  # double where: x >= 1 off the medium branch gives log(<0)
            t = M.sample_truncated_exponential(x, prop.sigma_hat, s)
            if lam_d > 0:
                # the vertex distance is drawn from a mixture: truncated exponential, or equiangular toward a light
                # (the path then continues from near the light often enough to make the 1/r light there cheap)
                te_i = pick(eq_t, U_b[7])
                valid_i = pick([st[4] for st in eq_setups], U_b[7])
                t = jnp.where((U_b[6] < lam_d) & valid_i, te_i, t)
            t = jnp.where(is_med, t, 0.0)

            def vertex_pdf(tt):
                """Density of the medium vertex at distance tt on this segment (branch probability included)."""
                p_exp = M.medium_pdf(tt, prop.sigma_hat, s, q)
                if lam_d == 0:
                    return p_exp
                p_eq = sum(jnp.where(st[4], equiangular_pdf(tt, *st), M.medium_pdf(tt, prop.sigma_hat, s, 1.0))
                           for st in eq_setups) / n_delta
                return (1.0 - lam_d) * p_exp + lam_d * q * p_eq

            if lam_d > 0:
                # sigma_s exp(-sigma_t t) / vertex_pdf(t), with exp(sigma_t t) clamped where the weight is ~0 anyway
                p_v = vertex_pdf(t)
                w_med = sigma_s * safe_div(jnp.exp(-sigma_t * t), p_v)
            else:
                w_med = M.medium_weight(sigma_t, sigma_s, prop.sigma_hat, t, s, jnp.where(is_med, q, 1.0))
            # double where: on a segment that escapes (no surface) the surface branch is never used, and
            # exp(-(sigma_t - sigma_hat) s) at s = extent overflows for a proposal with sigma_hat > sigma_t (0 * inf)
            on_surf = active & hit
            w_surf = jnp.where(on_surf, M.surface_weight(sigma_t, jnp.where(on_surf, s, 0.0),
                                                         jnp.where(on_surf, log1mq, 0.0)), 1.0)
            ff_pdf = vertex_pdf(t)
        else:
            is_med = jnp.bool_(False)
            w_surf = jnp.ones(3, jnp.float32)

        # ---- direct light along the segment: equiangular samples, MIS (balance) with the path's medium vertex
        if use_equiangular:
            seg_ok = nee_ok & active
            for i, light in enumerate(delta_lights):
                setup, te = eq_setups[i], eq_t[i]
                valid = setup[4]
                p_eq = equiangular_pdf(te, *setup)
                xe = state.o + te * state.d
                wl, dist, E = delta_incident(light, xe)
                vis = ~occluded(pk, xe, wl, dist)
                f = sigma_s * jnp.exp(-sigma_t * te) * hg_pdf(one_minus_cos_between(state.d, wl), g)
                use = seg_ok & valid & vis & (p_eq > 0)
                # double where: an unused sample's MIS denominator can be ~1e-30 (dense fog), whose 1/x^2 overflows
                c = state.beta * f * E * transmit(dist) * safe_div(1.0, jnp.where(use, p_eq + vertex_pdf(te), 1.0))
                L = L + jnp.where(use, c, 0.0)
        eq_setups = eq_setups or None

        new = {}
        p_s = state.o + jnp.where(hit, s_hit, 0.0) * state.d
        if has_medium:
            p_m = state.o + t * state.d
        # ---- the scattering direction: one `direction_from_cos` per lane, whichever technique drew it (the medium's
        #      HG lobe around d, the diffuse cosine lobe around n, or the light-angle lobe around the light). All draw
        #      the polar angle from U_b[1] and the azimuth from U_b[2]; only the lane's (1 -+ cos, axis) differ.
        cands = []  # (1 - cos, 1 + cos, axis), the last one the default
        if has_medium:
            omc_h, opc_h = hg_sample(U_b[1], prop.g_hat)
            cands.append((is_med, omc_h, opc_h, state.d))
        if DIFFUSE in kinds:
            omc_cos, opc_cos = cosine_cos(U_b[1])
            cands.append((None, omc_cos, opc_cos, n))
        if lam > 0:
            p_lobe = jnp.where(is_med, p_m, p_s) if has_medium else p_s
            take_lobe = U_b[4] < lam
            omc_l, opc_l, axis_l = light_lobe_cos(U_b[1], p_lobe, pick([lt.position for lt in delta_lights], U_b[5]))
            cands.insert(0, (take_lobe, omc_l, opc_l, axis_l))
        if cands:
            _, omc_v, opc_v, axis_v = cands[-1]
            for mask, omc_c, opc_c, axis_c in reversed(cands[:-1]):
                omc_v, opc_v = jnp.where(mask, omc_c, omc_v), jnp.where(mask, opc_c, opc_v)
                axis_v = jnp.where(mask, axis_c, axis_v)
            wo_v = direction_from_cos(omc_v, opc_v, 2.0 * PI * U_b[2], axis_v)
        if lam > 0:
            lobe_p = lobe_pdf(wo_v, p_lobe)

        # ---- medium vertex
        if has_medium:
            beta_m = state.beta * w_med

            wo_m = wo_v
            if reparam:  # the direction carries d/dg; its weight p_g / p_g is 1
                pdf_m = hg_pdf(omc_h, prop.g_hat)
                beta_m_next = beta_m
            elif lam > 0:
                omc = jnp.where(take_lobe, one_minus_cos_between(state.d, wo_m), omc_h)
                pdf_m = (1.0 - lam) * hg_pdf(omc, prop.g_hat) + lam * lobe_p
                beta_m_next = beta_m * hg_pdf(omc, g) / pdf_m
            else:
                pdf_m = hg_pdf(omc_h, prop.g_hat)
                beta_m_next = beta_m * hg_pdf(omc_h, g) / pdf_m
            new["med"] = (p_m, wo_m, beta_m_next, pdf_m)

        # ---- surface vertex
        beta_s = state.beta * w_surf
        surf = state.alive & ~is_med & hit
        kind = jnp.asarray(pk.kinds)[idx] if pk.kinds.shape[0] else jnp.int32(-1)
        cos_d = dot(state.d, n)
        front = cos_d < 0
        alive_s = surf  # refined below per kind
        wo_s, beta_s_next, spec_s, pdf_s = state.d, beta_s, jnp.bool_(True), jnp.float32(0.0)
        in_medium_s = state.in_medium

        if EMITTER in kinds:
            is_em = surf & (kind == EMITTER) & front
            Le = pk.emission[idx]
            w_em = jnp.float32(0.0)
            for j, light in enumerate(area_lights):
                pdf_l = area_pdf_hit(light, state.d, s_hit)
                w_j = jnp.where(state.specular, 1.0, power_heuristic(state.pdf_dir, pdf_l))
                w_em = jnp.where(idx == area_emitter_index[j], w_j, w_em)
            L = L + jnp.where(is_em, beta_s * Le * w_em, 0.0)
            alive_s = alive_s & (kind != EMITTER)

        if DIFFUSE in kinds:
            is_diff = kind == DIFFUSE
            R = pk.reflectance[idx]

            surf_nee_ok = surf & is_diff & front
            wo_d = wo_v
            if lam > 0:
                cos_o = jnp.maximum(dot(n, wo_d), 0.0)
                pdf_d = (1.0 - lam) * cos_o * INV_PI + lam * lobe_p
                beta_d = beta_s * R * safe_div(cos_o * INV_PI, pdf_d)
            else:
                pdf_d = (opc_cos - 1.0) * INV_PI  # cos theta / pi
                beta_d = beta_s * R
            wo_s = jnp.where(is_diff, wo_d, wo_s)
            beta_s_next = jnp.where(is_diff, beta_d, beta_s_next)
            spec_s = jnp.where(is_diff, False, spec_s)
            pdf_s = jnp.where(is_diff, pdf_d, pdf_s)
            alive_s = alive_s & ~(is_diff & ~front)

        if MIRROR in kinds:
            is_mir = kind == MIRROR
            wo_s = jnp.where(is_mir, reflect(state.d, n), wo_s)
            beta_s_next = jnp.where(is_mir, beta_s * pk.reflectance[idx], beta_s_next)

        if has_glass:
            is_gl = kind == GLASS
            int_ior, ext_ior = pk.ior[idx, 0], pk.ior[idx, 1]
            entering = cos_d < 0
            n_i = jnp.where(entering, n, -n)
            eta = jnp.where(entering, int_ior / ext_ior, ext_ior / int_ior)
            F, cos_t = fresnel_dielectric(jnp.abs(cos_d), eta)
            refl = U_b[3] < F
            wo_g = jnp.where(refl, reflect(state.d, n_i), safe_normalize(refract(state.d, n_i, eta, cos_t)))
            scale = jnp.where(refl, 1.0, 1.0 / (eta * eta))  # radiance compression across the interface
            wo_s = jnp.where(is_gl, wo_g, wo_s)
            beta_s_next = jnp.where(is_gl, beta_s * scale, beta_s_next)
            in_medium_s = jnp.where(is_gl & ~refl, ~entering, in_medium_s)

        # ---- direct light at the vertex: one NEE for the medium or the (diffuse) surface vertex
        if has_medium or DIFFUSE in kinds:
            R_v = pk.reflectance[idx] if DIFFUSE in kinds else jnp.zeros(3, jnp.float32)
            med_v = is_med if has_medium else jnp.bool_(False)
            ok_v = nee_ok & (med_v | surf_nee_ok) if DIFFUSE in kinds else nee_ok & med_v
            p_v = jnp.where(med_v, p_m, p_s) if has_medium else p_s
            shadow_o = jnp.where(med_v, p_v, p_s + EPS_OFFSET * n)
            beta_v = jnp.where(med_v, beta_m, beta_s) if has_medium else beta_s

            def response(wl):
                brdf = R_v * INV_PI * jnp.maximum(dot(n, wl), 0.0)
                if not has_medium:
                    return brdf
                return jnp.where(med_v, hg_pdf(one_minus_cos_between(state.d, wl), g), brdf)

            def dir_pdf(wl):
                cos_pdf = jnp.maximum(dot(n, wl), 0.0) * INV_PI
                if has_medium:
                    pdf = jnp.where(med_v, hg_pdf(one_minus_cos_between(state.d, wl), prop.g_hat), cos_pdf)
                else:
                    pdf = cos_pdf
                if lam > 0:
                    pdf = (1.0 - lam) * pdf + lam * lobe_pdf(wl, p_v)
                return pdf

            eq_mis = (eq_setups, t, ff_pdf, med_v) if use_equiangular else None
            L = L + nee(p_v, shadow_o, response, dir_pdf, beta_v, ok_v, U_b, eq_mis=eq_mis)

        # rays leave a surface from the side they go to
        side = jnp.where(dot(wo_s, n) >= 0, 1.0, -1.0)
        o_s = p_s + side * EPS_OFFSET * n

        # ---- update the path state
        if has_medium:
            p_m, wo_m, beta_m_next, pdf_m = new["med"]
            o_next = jnp.where(is_med, p_m, o_s)
            d_next = jnp.where(is_med, wo_m, wo_s)
            beta_next = jnp.where(is_med, beta_m_next, beta_s_next)
            spec_next = jnp.where(is_med, False, spec_s)
            pdf_next = jnp.where(is_med, pdf_m, pdf_s)
            alive_next = state.alive & (is_med | alive_s)
        else:
            o_next, d_next, beta_next, spec_next, pdf_next = o_s, wo_s, beta_s_next, spec_s, pdf_s
            alive_next = alive_s
        in_med_next = jnp.where(is_med, state.in_medium, in_medium_s)
        new_state = PathState(o_next, d_next, jnp.where(alive_next, beta_next, 0.0), L, alive_next,
                              spec_next, pdf_next, in_med_next)
        return new_state, None

    init = PathState(
        o=o, d=d, beta=jnp.ones(3, jnp.float32), L=jnp.zeros(3, jnp.float32), alive=jnp.bool_(True),
        specular=jnp.bool_(True), pdf_dir=jnp.float32(0.0), in_medium=jnp.bool_(True),
    )
    n_iter = U.shape[0]
    if n_iter == 0:
        return init.L
    final, _ = jax.lax.scan(jax.checkpoint(body), init, (jnp.arange(n_iter), U))
    return final.L
