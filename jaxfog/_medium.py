"""Participating media behind one interface, and the homogeneous medium's free-flight math.

A medium (`AbstractMedium`) gives the tracer everything it needs along a ray segment: free-flight sampling
(`sample_free_flight`, `free_flight_pdf`), the path weights of its two branches (`collision_weight`,
`surface_weight`), `transmittance(o, d, t)` for shadow rays, its scattering coefficient at a point
(`scattering`), and its phase function. Position-dependent media implement the same methods; the tracer does not
change.

Free-flight sampling is one formula for every gradient estimator (`docs/estimators.md`). A segment of length `s` (to
the next surface, or to the medium's `extent` for a ray that escapes) is split into two branches chosen with a
probability `q` that never carries a derivative:

- medium branch (probability `q`): `t` from the free-flight density truncated to [0, s]; the path weight is
  `sigma_s(t) T(t) / (q p(t))`;
- surface branch (probability `1 - q`): weight `T(s) / (1 - q)`.

Sampling and weighting use two media of the same kind: the *sampler* (whose values decide `t`, `q` and the phase
function's sample) and the medium itself (whose values make the weights). The estimators differ only in the sampler:
`stop_gradient(medium)` ("detached"), a caller's fixed reference ("proposal"), or the medium itself ("reparam": `t`
then moves with `sigma_t`, and the branch, decided by `u < q` with a detached `q`, does not jump).

For the homogeneous medium, with sampling rate `sh`: `t = -log(1 - x (1 - exp(-sh s))) / sh`, `x = u / q`; with
`q = 1 - exp(-sh s)` this *is* ordinary free-flight sampling `t = -log(1 - u) / sh`. `q` is floored at `Q_MIN` so
that very thin fog (even `sigma_t = 0`) still samples medium vertices that carry the derivative w.r.t. `sigma_t`.

RGB media: one-sample spectral MIS (`docs/estimators.md`, "Chromatic media"). Each channel `c` is a technique with
rate `sh_c = max(sigma_t_c, SIGMA_HAT_MIN)` and branch probability `q_c`; the medium branch is taken with the
channel-averaged `q = mean_c q_c` (one uniform, `u < q`, exactly as for grey fog), its channel is drawn uniformly
with a second uniform (`u_channel`), and `t` from that channel's truncated exponential with `x = u / q`. The
vertex density is the balance-heuristic mixture `q mean_c p_c(t)`, and the surface branch has `1 - q =
mean_c (1 - q_c)`: no channel's weight divides by a starved density. When the three channels are equal, `q`, `t`
and every decision are bitwise those of the grey scheme and the weights reduce to its formulas (the means are
written so that equal entries give exactly that entry). `spectral_mis=False` samples every channel at the smallest
one's rate: for a grey medium the same distances at a third of the pdf's cost, and the default there
(`default_spectral_mis`).
"""


import abc
import contextlib
import contextvars
from typing import Callable, NamedTuple

import equinox as eqx
from equinox import AbstractVar
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ._fields import concrete, rgb
from ._math import finite_or, one_minus_exp_neg
from ._phase import AbstractPhaseFunction, HenyeyGreenstein
from ._sampling import sample_truncated_exponential
from ._validate import NON_NEGATIVE, UNIT, check_range

# ------------------------------------------------------------------------------------ values shared along a ray
_SHARED: contextvars.ContextVar[dict | None] = contextvars.ContextVar("jaxfog_shared_ray_values", default=None)


@contextlib.contextmanager
def shared_ray_values():
    """Within this block, `shared(fn, *args)` computes `fn(*args)` once for the same arguments (a medium's per-ray
    work that several of its methods need: a density grid's profile, `_grid.GridMedium.profile`), so the tracer's
    many calls on one segment (free flight, its pdf, the weights, the equiangular transmittance) build it once: XLA
    does not merge the copies (docs/results/grid.md, "The cost").

    The tracer opens it around the stages of one bounce that read the segment (`_integrator.bounce`), inside one
    trace: a value cached there is read only in that trace, or captured by a branch or loop traced inside it, which
    JAX allows. Outside a block nothing is cached. Values are keyed by the arguments' identity (traced arrays have
    no value to compare), and the block keeps them alive, so an identity is never reused within it."""
    token = _SHARED.set({})
    try:
        yield
    finally:
        _SHARED.reset(token)


_REPLAY: contextvars.ContextVar[bool] = contextvars.ContextVar("jaxfog_path_replay", default=False)


@contextlib.contextmanager
def path_replay():
    """Within this block (the replay's trace of a bounce in reverse mode, `_unbounded._replay`), a medium whose
    estimate runs an unbounded loop (`_grid.ratio_tracking`) traces the loop's own reverse mode (drawing the same
    points again) instead of the plain loop, which only forward mode differentiates. A trace-time switch."""
    token = _REPLAY.set(True)
    try:
        yield
    finally:
        _REPLAY.reset(token)


def replaying() -> bool:
    """True inside `path_replay`."""
    return _REPLAY.get()


def shared(fn: Callable, *args):
    """`fn(*args)`, computed once per `shared_ray_values` block for the same `fn` and the same argument objects;
    outside a block, computed at every call."""
    cache = _SHARED.get()
    if cache is None:
        return fn(*args)
    key = (fn, *map(id, args))
    hit = cache.get(key)
    if hit is not None and all(a is b for a, b in zip(hit[0], args)):
        return hit[1]
    out = fn(*args)
    cache[key] = (args, out)
    return out


Q_MIN = 0.05
"""Smallest probability of choosing the medium branch on a segment (no derivative; a variance/cost trade-off)."""

Q_MAX_SURFACE = 0.75
"""Largest probability of the medium branch on a view segment (from the camera or after a specular bounce) that ends
on a surface (variance trade-off, no bias). The tracer applies it to view segments only: on the segments of long
paths its weights `albedo m / q > 1` compound into heavy tails (docs/results/unbounded, section 4)."""

SIGMA_HAT_MIN = 1e-6
"""Smallest sampling extinction (1/scene unit); below it the truncated exponential is uniform on [0, s] anyway."""


class FlightSample(NamedTuple):
    """A free-flight decision on one segment: `t` (scene units; meaningful where `scattered`), `scattered` (the
    medium branch was chosen), `q` (its probability, 0 outside the medium) and `log_one_minus_q` (exact where no
    clamp is active, so surface weights never underflow to 0/0)."""

    t: Float[Array, ""]
    scattered: Bool[Array, ""]
    q: Float[Array, ""]
    log_one_minus_q: Float[Array, ""]


class AbstractMedium(eqx.Module):
    """A participating medium filling all space outside the objects, or (where the medium has `bounds`) an
    axis-aligned box of it.

    Methods are called either on the medium (weights, transmittance, scattering) or on the *sampler*, a medium of
    the same kind whose values are the sampling parameters (`sample_free_flight`, `free_flight_pdf`, its `phase`'s
    sampling). Segments start at `o` with unit direction `d` and have length `s` (finite: the tracer clips escaping
    rays at `extent`).
    """

    phase: AbstractVar[AbstractPhaseFunction]
    extent: AbstractVar[float]
    bounds: AbstractVar[tuple[Float[Array, "3"], Float[Array, "3"]] | None]
    """The axis-aligned box `(box_min, box_max)` (scene units) the fog fills, or None: it fills space (static
    structure: a medium with a box compiles the box test, one without compiles none)."""

    @abc.abstractmethod
    def sample_free_flight(self, o, d, s, ends_on_surface, active, u, u_channel) -> FlightSample:
        """On the sampler: choose the branch with `u` in [0, 1) and, for the medium branch, a distance in [0, s).
        `ends_on_surface`: the segment ends on a surface whose branch gets probability >= 1 - Q_MAX_SURFACE (the
        tracer passes it for view segments only);
        `active`: the path is in the medium (outside glass objects; otherwise q = 0); `u_channel` in [0, 1): the
        spectral channel whose density draws `t` (RGB media; the branch itself must not depend on it, because the
        tracer gives the same uniform to a surface vertex's discrete BSDF choice, `Layout.channel`)."""

    @abc.abstractmethod
    def free_flight_pdf(self, o, d, s, q, t) -> Float[Array, ""]:
        """On the sampler: density (1/scene unit) of a medium vertex at `t` in [0, s], the branch probability `q`
        included: `q` times the density of `t` given the medium branch (for RGB media the channel mixture: the
        MIS partner of equiangular sampling)."""

    @abc.abstractmethod
    def collision_weight(self, sampler, o, d, s, q, t) -> Float[Array, "3"]:
        """Path weight `sigma_s(t) T(t) / sampler.free_flight_pdf(..., q, t)` of a medium vertex, RGB, without
        underflow."""

    @abc.abstractmethod
    def surface_weight(self, o, d, s, log_one_minus_q) -> Float[Array, "3"]:
        """Path weight `T(s) / (1 - q)` of reaching the surface at the end of the segment, RGB."""

    @abc.abstractmethod
    def transmittance(self, o, d, t) -> Float[Array, "3"]:
        """Transmittance over `[0, t]` along the ray, RGB in [0, 1]; `t` may be inf (finite gradient)."""

    @abc.abstractmethod
    def scattering(self, p) -> Float[Array, "3"]:
        """Scattering coefficient `sigma_s` at the point `p`, RGB, 1/scene unit."""

    @abc.abstractmethod
    def supports_estimator(self, estimator: str) -> bool:
        """Whether the gradient estimator `estimator` ("detached", "reparam", "proposal") is defined for this
        medium (static: decided by its structure)."""

    @abc.abstractmethod
    def fog_interval(self, o, d, s) -> tuple[Float[Array, ""], Float[Array, ""]]:
        """The part `[a, b]` of the segment `[0, s]` where there is fog (`a >= b`: none); `(0, s)` for a medium
        that fills space. The tracer clips its equiangular samples to it."""


def check_phase_and_extent(owner: str, phase, extent) -> None:
    """A medium's `phase` is a phase function and its `extent` (static) a finite number > 0 (scene units)."""
    if not isinstance(phase, AbstractPhaseFunction):
        raise TypeError(f"{owner}.phase must be a phase function, got {type(phase).__name__}")
    if not (isinstance(extent, (int, float)) and 0 < extent < float("inf")):
        raise ValueError(f"{owner}.extent = {extent!r} must be a finite number > 0")


class HomogeneousMedium(AbstractMedium):
    """A homogeneous medium.

    **Fields:**
    - `sigma_t`: extinction coefficient, RGB, in 1/scene unit, >= 0 (0 means no fog). A scalar sets all channels.
    - `albedo`: single-scattering albedo `sigma_s / sigma_t`, RGB, in [0, 1].
    - `phase`: the phase function (any `AbstractPhaseFunction`; `HenyeyGreenstein(g)` in the shipped scenes).
    - `extent`: static; a ray that travels this far (scene units) without meeting a surface leaves the fog.
      Default 1000: light scattered beyond it is below `sigma_s * I / extent` and negligible for the shipped scenes.
    - `bounds`: `None` (default: the fog fills space) or `(box_min, box_max)`, two 3-vectors in scene units with
      `box_min < box_max`: the fog fills only that axis-aligned box (Mitsuba's medium inside a `cube` with a `null`
      BSDF); outside it rays travel in vacuum. Camera, lights and surfaces may be inside or outside the box. Glass
      objects must lie wholly inside or wholly outside it. Structure: a medium with bounds compiles the box test,
      one without compiles none.
    - `spectral_mis`: static; sample distances with one-sample spectral MIS over the three channels (module
      docstring); False samples every channel at the smallest one's rate (`sampling_extinction`, one channel's
      pdf instead of three). Default (None): decided once, here, from `sigma_t` (`default_spectral_mis`): False
      for a grey medium whose `sigma_t` is known (concrete, all channels equal: a scene file's `"sigma_t": 0.5`),
      True otherwise (RGB, or traced: a medium built inside `jit` without the flag). For a grey medium the two
      schemes sample the same distances and give the same image up to float32 rounding, and False is cheaper per
      sample (spot_fog at 64 x 64, 512 spp, interleaved pairs on 2 busy cores: spectral MIS took 1.2x the CPU time
      of a render). It is structure, not a value: a new `sigma_t` never recompiles and never changes it
      (`Scene.replace_medium` keeps it), so a grey medium that will be fitted per channel asks for
      `spectral_mis=True` when it is built.
    """

    sigma_t: Float[Array, "3"] = eqx.field(converter=rgb)
    albedo: Float[Array, "3"] = eqx.field(converter=rgb)
    phase: AbstractPhaseFunction
    extent: float = eqx.field(static=True, default=1000.0)
    spectral_mis: bool = eqx.field(static=True, default=True)
    bounds: tuple[Float[Array, "3"], Float[Array, "3"]] | None = None

    def __init__(self, sigma_t, albedo, phase, extent=1000.0, spectral_mis=None, bounds=None):
        self.sigma_t = rgb(sigma_t)  # converted here already: the default of spectral_mis reads it
        self.albedo = albedo
        self.phase = phase
        self.extent = extent
        self.spectral_mis = default_spectral_mis(self.sigma_t) if spectral_mis is None else bool(spectral_mis)
        self.bounds = None if bounds is None else check_bounds("HomogeneousMedium", bounds)

    def __check_init__(self):
        check_range("HomogeneousMedium", "sigma_t", self.sigma_t, NON_NEGATIVE)
        check_range("HomogeneousMedium", "albedo", self.albedo, UNIT)
        check_phase_and_extent("HomogeneousMedium", self.phase, self.extent)

    @property
    def sigma_s(self) -> Float[Array, "3"]:
        """Scattering coefficient `albedo * sigma_t`, RGB, 1/scene unit."""
        return self.albedo * self.sigma_t

    @property
    def g(self) -> Float[Array, ""]:
        """The Henyey–Greenstein `g` of the phase function (AttributeError for other phase functions)."""
        if not isinstance(self.phase, HenyeyGreenstein):
            raise AttributeError(f"the medium's phase function is {type(self.phase).__name__}, which has no g")
        return self.phase.g

    # A bounded medium runs the same formulas on the fog's part [a, a + L] of the segment (`_fog_part`): distances
    # inside it are shifted by a, and a segment that misses the box has L = 0 and no medium branch.
    def fog_interval(self, o, d, s):
        if self.bounds is None:
            return 0.0, s
        t0, t1 = box_interval(self.bounds[0], self.bounds[1], o, d)
        return jnp.clip(t0, 0.0, s), jnp.clip(t1, 0.0, s)

    def supports_estimator(self, estimator: str) -> bool:
        return True

    def _fog_part(self, o, d, s):
        """`(a, L)`: where the fog starts on the segment and its length there (`(0, s)` without bounds)."""
        a, b = self.fog_interval(o, d, s)
        return a, (jnp.maximum(b - a, 0.0) if self.bounds is not None else s)

    def sample_free_flight(self, o, d, s, ends_on_surface, active, u, u_channel) -> FlightSample:
        a, s = self._fog_part(o, d, s)
        if self.bounds is not None:
            active = active & (s > 0)
        q_max = jnp.where(ends_on_surface, Q_MAX_SURFACE, 1.0)
        if self.spectral_mis:
            sh = channel_rates(self.sigma_t)
            q, log1mq = mis_branch_probability(sh, s, q_max)
            sh_t = pick_channel(sh, u_channel)
        else:
            sh_t = sampling_extinction(self.sigma_t)
            q, log1mq = branch_probability(sh_t, s, q_max)
        q = jnp.where(active, q, 0.0)
        if self.bounds is not None:  # no fog on the segment: the surface is reached with weight exactly 1
            log1mq = jnp.where(s > 0, log1mq, 0.0)
        scattered = active & (u < q)
        x = jnp.where(scattered, u / jnp.where(scattered, q, 1.0), 0.0)  # double where: x >= 1 gives log(< 0)
        return FlightSample(a + sample_truncated_exponential(x, sh_t, s), scattered, q, log1mq)

    def free_flight_pdf(self, o, d, s, q, t):
        a, s = self._fog_part(o, d, s)
        inside = None if self.bounds is None else (t >= a) & (t <= a + s) & (s > 0)
        if inside is not None:  # double where: outside the fog (or with none on the segment) the density is 0
            t, s = jnp.where(inside, t - a, 0.0), jnp.where(inside, s, 1.0)
        if self.spectral_mis:
            p = mis_medium_pdf(t, channel_rates(self.sigma_t), s, q)
        else:
            p = medium_pdf(t, sampling_extinction(self.sigma_t), s, q)
        return p if inside is None else jnp.where(inside, p, 0.0)

    def collision_weight(self, sampler, o, d, s, q, t):
        a, s = self._fog_part(o, d, s)  # t comes from this segment's own free flight: inside the fog
        if self.bounds is not None:
            ok = s > 0
            t, s = jnp.where(ok, t - a, 0.0), jnp.where(ok, s, 1.0)
        if sampler.spectral_mis:
            return mis_medium_weight(self.sigma_t, self.sigma_s, channel_rates(sampler.sigma_t), t, s, q)
        return medium_weight(self.sigma_t, self.sigma_s, sampling_extinction(sampler.sigma_t), t, s, q)

    def surface_weight(self, o, d, s, log_one_minus_q):
        return surface_weight(self.sigma_t, self._fog_part(o, d, s)[1], log_one_minus_q)

    def transmittance(self, o, d, t):
        if self.bounds is None:
            return transmittance(self.sigma_t, t)
        t0, t1 = box_interval(self.bounds[0], self.bounds[1], o, d)
        # the fog's length on [0, t]; t may be inf, the box's exit distance is finite (d is a unit vector)
        return transmittance(self.sigma_t, jnp.maximum(jnp.minimum(t, t1) - jnp.maximum(t0, 0.0), 0.0))

    def scattering(self, p):
        if self.bounds is None:
            return self.sigma_s
        return jnp.where(inside_box(self.bounds[0], self.bounds[1], p), self.sigma_s, 0.0)


def default_spectral_mis(sigma_t) -> bool:
    """Whether a medium with this `sigma_t` (as given to the constructor) needs spectral MIS by default: False
    when it is concrete and grey (a scalar, or three equal float32 values), True when the channels differ or the
    value is traced (its channels are not known when the program's structure is decided)."""
    import numpy as np

    try:
        v = concrete(rgb(sigma_t))
    except (TypeError, ValueError):  # not an RGB value: the field's converter says what is wrong
        return True
    return v is None or not bool(np.all(v == v[0]))


def check_bounds(owner: str, bounds) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """`bounds` as two float32 3-vectors `(box_min, box_max)`: finite, `box_min < box_max` in every axis."""
    import numpy as np

    try:
        lo, hi = bounds
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.bounds must be (box_min, box_max), two 3-vectors, got {bounds!r}") from None
    lo_c, hi_c = concrete(lo), concrete(hi)
    if lo_c is None or hi_c is None:  # traced (e.g. a medium rebuilt inside jit): checked where it was made
        return jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)
    try:
        lo_np, hi_np = (np.asarray(x, dtype=np.float64) for x in (lo_c, hi_c))
    except (TypeError, ValueError):
        raise ValueError(f"{owner}.bounds must be (box_min, box_max), two 3-vectors, got {bounds!r}") from None
    if lo_np.shape != (3,) or hi_np.shape != (3,) or not (np.all(np.isfinite(lo_np)) and np.all(np.isfinite(hi_np))):
        raise ValueError(f"{owner}.bounds must be two finite 3-vectors, got {bounds!r}")
    if not np.all(lo_np < hi_np):
        raise ValueError(f"{owner}.bounds: box_min {lo_np.tolist()} must be below box_max {hi_np.tolist()} in every axis")
    return jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)


def box_interval(box_min, box_max, o, d) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Ray parameters `(t0, t1)` where the line `o + t d` enters and leaves the axis-aligned box (slab method;
    `t0 > t1`: it misses). Scene units. An axis with `d = 0` (double where, no 0 * inf) leaves the interval
    unbounded if `o` lies within the slab and empty otherwise."""
    nz = d != 0
    inv = 1.0 / jnp.where(nz, d, 1.0)
    ta, tb = (box_min - o) * inv, (box_max - o) * inv
    inside = (o >= box_min) & (o <= box_max)
    near = jnp.where(nz, jnp.minimum(ta, tb), jnp.where(inside, -jnp.inf, jnp.inf))
    far = jnp.where(nz, jnp.maximum(ta, tb), jnp.where(inside, jnp.inf, -jnp.inf))
    return jnp.max(near), jnp.min(far)


def inside_box(box_min, box_max, p) -> Bool[Array, ""]:
    """Whether the point `p` lies in the closed box."""
    return jnp.all((p >= box_min) & (p <= box_max))


def sampling_extinction(sigma_t: Float[Array, "3"]) -> Float[Array, ""]:
    """The scalar rate used to sample distances for an RGB medium: the smallest channel, floored at SIGMA_HAT_MIN.

    The smallest channel keeps every channel's weight ratio `exp(-(sigma_c - sh) t)` at most 1 (bounded variance).
    """
    return jnp.maximum(jnp.min(sigma_t), SIGMA_HAT_MIN)


def channel_rates(sigma_t: Float[Array, "3"]) -> Float[Array, "3"]:
    """The three channels' sampling rates of spectral MIS: `sigma_t` floored at SIGMA_HAT_MIN (1/scene unit)."""
    return jnp.maximum(sigma_t, SIGMA_HAT_MIN)


def mean3(x: Float[Array, "3"]) -> Float[Array, ""]:
    """The mean of three values written as `x0 + ((x1 - x0) + (x2 - x0)) / 3`: exactly `x0` when all are equal
    (so an RGB medium with equal channels reproduces the grey formulas bit for bit), within an ulp of the plain
    mean otherwise (the two differences are exact or rounded once, and small against x0 where they matter)."""
    return x[0] + ((x[1] - x[0]) + (x[2] - x[0])) / 3.0


def log_mean3_exp(a: Float[Array, "3"]) -> Float[Array, ""]:
    """`log(mean(exp(a)))` without overflow or underflow (max shift); exactly `a0` when all entries are equal."""
    m = jnp.max(a)
    return m + jnp.log(mean3(jnp.exp(a - m)))


def pick_channel(x: Float[Array, "3"], u: Float[Array, ""]) -> Float[Array, ""]:
    """`x[c]` for the channel `c = floor(3 u)` drawn uniformly by `u` in [0, 1) (selects, no gather)."""
    return jnp.where(u < 1.0 / 3.0, x[0], jnp.where(u < 2.0 / 3.0, x[1], x[2]))


def mis_branch_probability(sh: Float[Array, "3"], s, q_max=1.0) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Spectral MIS: the medium branch's channel-averaged probability `q = mean_c q_c` (each `q_c` as
    `branch_probability`) and `log(1 - q) = log(mean_c (1 - q_c))` from the exact per-channel logs, never
    differentiated. For equal channels both are bitwise those of `branch_probability`."""
    q_c, log1mq_c = branch_probability(sh, s, q_max)
    return mean3(q_c), log_mean3_exp(log1mq_c)


def mis_medium_pdf(t, sh: Float[Array, "3"], s, q) -> Float[Array, ""]:
    """Density of a medium vertex at `t` under spectral MIS (1/scene unit): `q mean_c p_c(t)`, the branch
    probability times the uniform mixture of the three truncated exponentials (`medium_pdf` per channel)."""
    return mean3(medium_pdf(t, sh, s, q))


def mis_medium_weight(sigma_t, sigma_s, sh: Float[Array, "3"], t, s, q) -> Float[Array, "3"]:
    """Path weight of a medium vertex at `t` under spectral MIS: `sigma_s^j exp(-sigma_t^j t) / mis_medium_pdf(t)`
    for each channel j (the balance heuristic over the three channel techniques), without overflow or underflow.

    Written as `medium_weight` at channel j's own rate times `p_j(t) / mean_c p_c(t) = exp(-log mean_c r_jc)`,
    `log r_jc = log(p_c(t) / p_j(t)) = log(sh_c / sh_j) - (sh_c - sh_j) t + log(m_j / m_c)` (`m = 1 - exp(-sh s)`),
    in log space: a channel whose density is negligible at `t` gets a weight that tends to 0, never 0 * inf. For
    equal channels every `log r` is exactly 0 and the weight is exactly `medium_weight`."""
    m = jnp.maximum(one_minus_exp_neg(sh * s), 1e-30)  # > 0 for s > 0; the floor only guards s = 0 (log 0)
    log_p = jnp.log(sh) - sh * t - jnp.log(m)  # log of each channel's density up to the common q
    log_r = log_p[None, :] - log_p[:, None]  # [j, c] = log(p_c / p_j)
    own = medium_weight(sigma_t, sigma_s, sh, t, s, q)
    return own * jnp.exp(-jax.vmap(log_mean3_exp)(log_r))


def branch_probability(
    sh: Float[Array, ""], s: Float[Array, ""], q_max: float | Float[Array, ""] = 1.0
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Probability `q` of the medium branch on a segment of finite length `s`, and `log(1 - q)`; never differentiated.

    `q = clip(1 - exp(-sh s), Q_MIN, q_max)`. The integrator passes `q_max = Q_MAX_SURFACE` when a view segment
    (from the camera or after a specular bounce) ends on a surface, so that a surface behind optically thick fog is still reached by a fixed share of the paths (with
    weight `exp(-sigma_t s) / (1 - q) < 1`) instead of by a rare, heavy one. `log(1 - q)` is exact (`-sh s`) where
    no clamp is active, so surface weights `exp(-sigma_t s) / (1 - q)` never underflow to 0/0 in deep fog.
    """
    sh = jax.lax.stop_gradient(sh)
    m = one_minus_exp_neg(sh * s)
    floored = m < Q_MIN
    capped = m > q_max
    q = jnp.where(floored, Q_MIN, jnp.where(capped, q_max, m))
    log_one_minus_q = jnp.where(floored, jnp.log1p(-Q_MIN), jnp.where(capped, jnp.log1p(-q_max), -sh * s))
    return q, log_one_minus_q


def medium_pdf(t, sh, s, q) -> Float[Array, ""]:
    """Density of sampling a medium vertex at `t` on the segment (1/scene unit): `q sh exp(-sh t) / (1 - exp(-sh s))`."""
    return q * sh * jnp.exp(-sh * t) / one_minus_exp_neg(sh * s)


def medium_weight(sigma_t, sigma_s, sh, t, s, q) -> Float[Array, "3"]:
    """Path weight of a medium vertex at `t`: `sigma_s exp(-sigma_t t) / medium_pdf(t)`, RGB, computed without underflow."""
    return sigma_s / sh * jnp.exp(-(sigma_t - sh) * t) * (one_minus_exp_neg(sh * s) / q)


def surface_weight(sigma_t, s, log_one_minus_q) -> Float[Array, "3"]:
    """Path weight of reaching the surface at finite `s`: `exp(-sigma_t s) / (1 - q)`, RGB, as one exponential."""
    return jnp.exp(-sigma_t * s - log_one_minus_q)


def transmittance(sigma_t: Float[Array, "3"], d: Float[Array, ""]) -> Float[Array, "3"]:
    """Beer–Lambert transmittance `exp(-sigma_t d)` over a distance `d` >= 0 (may be inf: 0 where sigma_t > 0, 1 where
    sigma_t = 0), RGB; the gradient is finite (zero) at d = inf."""
    fin = jnp.isfinite(d)
    tr = jnp.exp(-sigma_t * finite_or(d, 0.0))
    return jnp.where(fin, tr, jnp.where(sigma_t > 0, 0.0, 1.0))
