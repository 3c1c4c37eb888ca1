"""How often the SUT violates a requirement: failure-rate estimates with confidence intervals.

One concern: failure-rate estimation (its estimators, their intervals and
the estimate job).

The rate is the probability that a concrete scenario drawn from the logical scenario violates
the requirement (:mod:`jaxfalsify.core.requirements`), every concrete scenario of the discretised
space being equally likely (the space's values are drawn from its declared distributions, so
this is the distribution the space defines). Two estimators:

* ``mc`` — naive Monte Carlo: uniform draws; the interval is Wilson's score interval.
* ``exact`` — every scenario evaluated (:func:`exact_rate`; spaces up to 2**31 - 1).
* ``is`` — importance sampling with a cross-entropy proposal (Rubinstein's multilevel
  cross-entropy method, as O'Kelly et al., NeurIPS 2018, use it for AV crash rates): a mixture
  of ``ce_components`` products of one categorical distribution per parameter (a product alone
  cannot hold several failure clusters), fitted by weighted EM over levels to the draws whose
  robustness is below the level's ``ce_quantile`` (weighted by p/q), until enough draws
  violate the requirement; then to those. Each level's EM (``ce_iterations``) starts from the
  previous level's mixture (its heaviest components where the fit has fewer), so its
  components keep the parts of the failure set they cover.
  The final draws come from a defensive mixture ``(1 - defensive) q + defensive * uniform``,
  so every weight ``p/q`` is at most ``1 / defensive``; the estimate is the mean of
  ``w * 1[violated]`` and its interval the normal one on its sample variance. The proposal's
  probabilities are exact (products of table entries), so the weights are too.

Both stop once the interval's half-width is at most ``target_rel_error`` of the estimate
(with at least ``MIN_VIOLATIONS`` violating draws) or after ``samples`` draws beyond the
proposal's fitting. The draws of the cross-entropy levels count in the estimate, each
weighted by p/q of the proposal it came from (:class:`Tally`; the first level's are uniform,
Monte Carlo's), but for those of the first ``ce_burn_in`` share of the levels run: at a rare
rate the first levels' proposals are still broad, and their draws carry most of the
variance (a uniform draw's relative variance is ``1/p``). Each batch is one compiled call
(draw, simulate on lanes refilled as episodes end, requirement, weights); the host keeps the
sums in float64.
:func:`exact_rate` evaluates every scenario of a space small enough to sweep (the oracle).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.base import config as cfg
from jaxfalsify.base.progress import Clock, Progress
from jaxfalsify.core import requirements as req_lib
from jaxfalsify.core import sim
from jaxfalsify.engine.lifecycle import Status, sut_raised
from jaxfalsify.engine.problem import (
    SEED_LIMIT,
    Problem,
    check_int,
    check_mapping,
    check_space_sut,
    fixed_sut_params,
)
from jaxfalsify.io import cache, store
from jaxfalsify.io.files import write_atomic, write_json
from jaxfalsify.scenario.space import MAX_SIZE, Space
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "EstimateConfig", "Proposal", "exact_rate", "estimate", "execute", "summary_lines",
    "METHODS", "uniform_proposal", "wilson", "normal_interval", "fit_mixture", "Tally",
    "cross_entropy"
]

METHODS = ("mc", "is", "exact")
MIN_VIOLATIONS = 10  # violating draws before the stopping rule may stop
PER_COMPONENT = 200  # elite draws per mixture component, at least
ELITE_MIN = 100  # violating draws of a cross-entropy level that end the levels (fit to them)


@dataclasses.dataclass(frozen=True)
class EstimateConfig(Problem):
    """What an estimate needs. ``samples``: most draws of the final stage; ``batch``: draws per
    compiled call; ``ce_*``: the cross-entropy stage (draws per level, the elite quantile, the
    most levels, the mixture's components, EM iterations per level, the share of the levels,
    the first ones, whose draws the estimate leaves out); ``defensive``: the uniform share of
    the final proposal."""

    requirement: str = req_lib.DEFAULT
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)
    method: str = "is"
    samples: int = 10_000_000
    batch: int = 65536
    target_rel_error: float = 0.1
    confidence: float = 0.95
    seed: int = 0
    ce_samples: int = 65536
    ce_quantile: float = 0.5
    ce_levels: int = 40
    ce_components: int = 16
    ce_iterations: int = 10
    ce_burn_in: float = 0.25
    defensive: float = 0.1

    def check(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method {self.method!r}: one of {', '.join(METHODS)}")
        check_int("samples", self.samples, 1, 10**12)
        check_int("batch", self.batch, 1, 1 << 22)
        check_int("seed", self.seed, 0, SEED_LIMIT - 1)
        self.check_space_seed()
        check_int("ce_samples", self.ce_samples, 1, 1 << 22)
        check_int("ce_levels", self.ce_levels, 1, 1000)
        check_int("ce_components", self.ce_components, 1, 256)
        check_int("ce_iterations", self.ce_iterations, 1, 10_000)
        b = self.ce_burn_in
        if isinstance(b, bool) or not isinstance(b, (int, float)) or not 0.0 <= b < 1.0:
            raise ValueError(f"ce_burn_in must be a number in [0, 1) (got {b!r})")
        for key, lo, hi in (("target_rel_error", 0.0, math.inf), ("confidence", 0.0, 1.0),
                            ("ce_quantile", 0.0, 1.0), ("defensive", 0.0, 1.0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo < v < hi:
                raise ValueError(f"{key} must be a number in ({lo:g}, {hi:g}) (got {v!r})")

    def build(self):
        """``(space, sut, sut_params, requirement, requirement_params)``, checked."""
        self.check()
        sp = self.built_space()
        if self.method == "exact" and sp.size > MAX_SIZE:
            raise ValueError(f"method exact: space {sp.name} has {sp.size:.3g} scenarios, more "
                             f"than can be evaluated one by one ({MAX_SIZE:,}); use is or mc")
        sut = sut_lib.resolve(self.sut)
        given = check_mapping("sut_params", self.sut_params)
        check_space_sut(sp, sut, set(given))
        params = sut_lib.with_params(sut, given)
        sut_lib.check_traceable(sut, params)
        req = req_lib.resolve(self.requirement)
        rparams = req_lib.with_params(req, check_mapping("requirement_params",
                                                         self.requirement_params))
        req_lib.check(req, rparams)
        return sp, sut, params, req, rparams

    def to_toml(self, space: Space, sut, params, req, rparams) -> str:
        return cfg.dumps_toml({
            "kind": "estimate", "space": space.describe(), "space_seed": self.space_seed,
            "sut": sut_lib.recorded_spec(self.sut),
            "sut_params": fixed_sut_params(sut_lib.params_dict(params), space),
            "requirement": self.requirement,
            "requirement_params": sut_lib.params_dict(rparams),
            **{f.name: getattr(self, f.name) for f in dataclasses.fields(self)
               if f.name not in ("space", "space_seed", "sut", "sut_params", "requirement",
                                 "requirement_params")}})


# ----------------------------------------------------------------------------- the programs
@dataclasses.dataclass(frozen=True)
class Proposal:
    """A mixture of K products of one categorical distribution per parameter: ``log_weight``
    (K,) and ``log_prob`` (K, P, V), values beyond a parameter's count at -inf."""

    log_weight: np.ndarray
    log_prob: np.ndarray


def uniform_proposal(sp: Space) -> Proposal:
    shape = np.asarray(sp.shape)
    mask = np.arange(int(shape.max()))[None, :] < shape[:, None]
    table = np.where(mask, -np.log(shape)[:, None], -np.inf).astype(np.float32)
    return Proposal(np.zeros(1, np.float32), table[None])


_PROGRAMS: dict = {}  # compiled programs of this process, by space, SUT, requirement, batch


def _program(sp: Space, sut, req, batch: int):
    """:func:`_compile`'d once per process for each space (its layout and values), SUT,
    requirement and batch."""
    key = (sp.layout, np.asarray(sp.table_array).tobytes(), sut, req, batch)
    if key not in _PROGRAMS:
        _PROGRAMS[key] = _compile(sp, sut, req, batch)
    return _PROGRAMS[key]


def _compile(sp: Space, sut, req, batch: int):
    """One compiled call: ``(key, log weights (K,), log probs (K, P, V), log share, params,
    rparams) -> (idx (B, P), robustness (B,), log weight p/q (B,))``: draws from the
    defensive mixture ``share * uniform + (1 - share) * proposal`` (``log share`` 0: uniform
    draws), simulates them and evaluates the requirement."""
    layout, table = sp.layout, sp.table_array
    sizes = jnp.asarray(sp.shape, jnp.int32)
    log_p = -float(np.sum(np.log(np.asarray(sp.shape, np.float64))))
    steps = int(np.ceil(np.log2(max(int(np.max(sp.shape)), 2)))) + 1

    @jax.jit
    def run(key, log_w, log_q, log_u, params, rparams):
        k_mix, k_comp, k_val = jax.random.split(key, 3)
        n_comp, n_par, width = log_q.shape
        # the component by the inverse of its weights' cumulative sum, one uniform per draw
        # (a Gumbel arg-max would take K: on a CPU the random bits cost more than the draw)
        cum_w = jnp.cumsum(jnp.exp(log_w - jnp.max(log_w)))
        pick = jax.random.uniform(k_comp, (batch,)) * cum_w[-1]
        comp = jnp.minimum(jnp.sum(cum_w[None, :] <= pick[:, None], axis=1), n_comp - 1)
        cdf = jnp.cumsum(jnp.exp(log_q), axis=-1)
        cdf = jnp.where(jnp.arange(width) < sizes[:, None], cdf, 2.0)  # beyond: never chosen
        par = jnp.arange(n_par)[None, :]
        # one uniform per value serves both halves of the defensive mixture: each draw uses it
        # in the half it is drawn from, chosen independently of it
        raw = jax.random.uniform(k_val, (batch, n_par))
        u = raw * cdf[comp[:, None], par, (sizes - 1)[None, :]]
        # first value whose cumulative probability reaches u: a binary search, log2(V) gathers
        lo = jnp.zeros((batch, n_par), jnp.int32)
        hi = jnp.broadcast_to(sizes - 1, (batch, n_par))

        def halve(_, lh):
            lo, hi = lh
            mid = (lo + hi) // 2
            up = cdf[comp[:, None], par, mid] < u
            return jnp.where(up, mid + 1, lo), jnp.where(up, hi, mid)

        from_q, _ = jax.lax.fori_loop(0, steps, halve, (lo, hi))
        from_u = jnp.minimum(jnp.floor(raw * sizes).astype(jnp.int32), sizes - 1)
        uniform = jnp.log(jax.random.uniform(k_mix, (batch,))) < log_u
        idx = jnp.where(uniform[:, None], from_u, from_q).astype(jnp.int32)
        per = jnp.sum(log_q[:, par, idx], axis=-1)  # (K, B)
        log_q_x = jax.nn.logsumexp(per + log_w[:, None], axis=0)
        log_mix = jnp.logaddexp(log_u + log_p, jnp.log1p(-jnp.exp(log_u)) + log_q_x)
        out, _ = sim.batch_rollout(layout.scenario(idx, table), jnp.zeros(batch, jnp.int32),
                                   jax.random.key(0), sut, params,
                                   lanes=sim.lane_count(batch))  # refilled as episodes end
        rob = req_lib.robustness(req, out, rparams)
        return idx, rob, log_p - log_mix

    return run


def exact_rate(space: Space, sut="carla-tm", sut_params=None, requirement=req_lib.DEFAULT,
               requirement_params=None, chunk: int = 1 << 16) -> dict:
    """Every scenario of ``space`` evaluated: ``{"violations", "scenarios", "rate"}``."""
    if space.size > MAX_SIZE:
        raise ValueError(f"space {space.name} has {space.size:.3g} scenarios: too many to "
                         "evaluate every one")
    s = sut_lib.resolve(sut)
    params = sut_lib.with_params(s, sut_params)
    req = req_lib.resolve(requirement)
    rparams = req_lib.with_params(req, requirement_params)
    layout, table = space.layout, space.table_array

    @jax.jit
    def run(flat, params, rparams):
        idx = layout.unravel(flat)
        out, _ = sim.batch_rollout(layout.scenario(idx, table), flat, jax.random.key(0), s,
                                   params)
        return jnp.sum((req_lib.robustness(req, out, rparams) < 0)
                       & (flat < space.size))

    bad = 0
    for b in range(0, space.size, chunk):
        flat = jnp.arange(b, b + chunk, dtype=jnp.int32)
        bad += int(run(flat, params, rparams))
    return {"violations": bad, "scenarios": int(space.size), "rate": bad / space.size}


# ----------------------------------------------------------------------------- intervals
def wilson(k: int, n: int, confidence: float) -> tuple[float, float]:
    """Wilson's score interval for a binomial proportion ``k / n``."""
    z = _z(confidence)
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return (0.0 if k == 0 else max(0.0, centre - half),  # exact ends where rounding is not
            1.0 if k == n else min(1.0, centre + half))


@functools.lru_cache(maxsize=8)
def _z(confidence: float) -> float:
    """The standard normal quantile of a two-sided ``confidence`` interval."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + confidence / 2))


def normal_interval(s1: float, s2: float, n: int, confidence: float):
    """Estimate and normal interval of a mean from the sums of ``x`` and ``x^2`` over n."""
    z = _z(confidence)
    mean = s1 / n
    var = max(s2 / n - mean * mean, 0.0) * n / max(n - 1, 1)
    half = z * math.sqrt(var / n)
    return mean, max(0.0, mean - half), mean + half


def no_violation_bound(uniform_draws: float, confidence: float) -> float:
    """Upper end of the interval when no draw violated: each draw came from a proposal whose
    uniform share ``s_i`` gives every violation at least ``s_i`` times its probability, so
    ``P(no violation) <= exp(-p sum_i s_i)``; the rate at which that is ``(1 - confidence) /
    2`` (the two-sided interval's tail, as Clopper-Pearson's ``1 - ((1 - c) / 2)^(1/n)`` for
    uniform draws, which it approaches)."""
    return min(1.0, -math.log((1.0 - confidence) / 2.0) / max(uniform_draws, 1e-300))


# ----------------------------------------------------------------------------- estimation
def fit_mixture(idx: np.ndarray, w: np.ndarray, shape: np.ndarray, k: int, rng,
                iterations: int = 30, floor: float = 1e-3,
                start: Proposal | None = None) -> Proposal:
    """Weighted EM for a mixture of ``k`` products of categoricals on index vectors ``idx``
    (N, P) with weights ``w`` (N,); every value keeps at least ``floor`` of a uniform
    distribution's probability within its component. The EM starts from the responsibilities
    for the draws of ``start``'s ``k`` heaviest components, reweighted to sum to 1, where
    ``start`` has at least ``k`` (a warm start), else from a random hard assignment drawn with
    ``rng``."""
    from scipy import sparse  # jax's dependency; imported only where a proposal is fitted

    check_int("iterations", iterations, 1)
    n, n_par = idx.shape
    width = int(shape.max())
    mask = np.arange(width)[None, :] < shape[:, None]
    k = max(1, min(k, n))
    w = w / w.sum()
    # each draw's values as the P ones of a row of a sparse (N, P * width) matrix: a
    # component's value counts are a column of its transpose times the weights, and each
    # draw's log-probabilities a row of it times the (P * width, K) table of log-probabilities
    # (each sum runs over the draws, or the parameters, in order); the maximum over the
    # components is taken column by column, faster than a reduction along the short axis
    # (measurements in experiments/results/NOTES.md)
    flat = (idx + (np.arange(n_par) * width)[None, :]).ravel()
    draws = sparse.csr_matrix((np.ones(n * n_par), flat, np.arange(0, n * n_par + 1, n_par)),
                              shape=(n, n_par * width))
    values = draws.T.tocsr()  # (P * width, N), each row's draws in their order
    uniform = np.where(mask, 1.0 / shape[:, None], 0.0)[:, :, None]
    top = np.empty(n)

    def responsibilities(table, log_weight):
        """Each draw's posterior over the components, (N, K), from the (P * width, K) table."""
        per = draws @ table  # (N, K): summed over the parameters in order
        per += log_weight
        np.copyto(top, per[:, 0])
        for c in range(1, k):
            np.maximum(top, per[:, c], out=top)
        per -= top[:, None]
        resp = np.exp(per)
        resp /= resp.sum(1, keepdims=True)
        return resp

    if start is not None and len(start.log_weight) >= k:
        keep = np.sort(np.argsort(-start.log_weight, kind="stable")[:k])
        table = np.where(mask[None], start.log_prob[keep], 0.0).astype(np.float64)
        # (their weights need not sum to 1: a constant shift of the logarithms is no change)
        resp = responsibilities(np.moveaxis(table, 0, -1).reshape(n_par * width, k),
                                start.log_weight[keep])
    else:
        resp = np.zeros((n, k))
        resp[np.arange(n), rng.integers(0, k, n)] = 1.0  # a random hard start
    for _ in range(iterations):
        rw = resp * w[:, None]  # (N, K)
        mass = rw.sum(0) + 1e-300
        log_weight = np.log(mass / mass.sum())
        prob = (values @ rw).reshape(n_par, width, k) / mass
        prob = (1 - floor) * prob + floor * uniform
        table = np.log(np.maximum(prob, 1e-300)).reshape(n_par * width, k)
        resp = responsibilities(table, log_weight)
    log_prob = np.where(mask[None], np.moveaxis(table.reshape(n_par, width, k), 2, 0), -np.inf)
    return Proposal(log_weight.astype(np.float32), log_prob.astype(np.float32))


def _draw(run, key, q: Proposal, log_u: float, params, rparams, n: int, batch: int):
    parts = []
    for _ in range(-(-n // batch)):
        key, k = jax.random.split(key)
        parts.append([np.asarray(a) for a in run(k, jnp.asarray(q.log_weight),
                                                 jnp.asarray(q.log_prob), jnp.float32(log_u),
                                                 params, rparams)])
    return key, [np.concatenate(a)[:n] for a in zip(*parts)]


class Tally:
    """The running estimate over the draws it counts, each weighted by p/q of the proposal it
    was drawn from (1 for uniform draws). Draws come in stages (each cross-entropy level, then
    the final draws); :meth:`leave_out` drops the first stages from the estimate (their draws
    still count in ``n``, the draws made). Without it every draw counts, the levels' too, so an
    estimate never takes more draws than Monte Carlo's where the first, uniform, level already
    reaches the target."""

    FIELDS = ("n", "s1", "s2", "bad", "uniform_draws", "w_max", "above_uniform")

    def __init__(self, method: str, confidence: float):
        self.method, self.confidence = method, confidence
        self.stages: list[dict] = []  # per stage: the sums of FIELDS over its draws
        self.first = 0  # the first stage the estimate counts
        self.n = 0  # every draw made
        self.s1 = self.s2 = self.w_max = self.uniform_draws = 0.0  # over the counted draws:
        self.counted = self.bad = self.above_uniform = 0  # uniform_draws sums each draw's
        # uniform share of its proposal; above_uniform counts violating draws with p/q > 1,
        # where the proposal's mass is below uniform sampling's (drawn through the defensive
        # share): a region it misses
        self.estimate = self.low = self.high = float("nan")
        self.rel = math.inf

    def add(self, violated: np.ndarray, log_weight: np.ndarray, share: float = 1.0,
            new_stage: bool = False) -> None:
        """One batch of draws: ``violated (n,)`` bool, ``log_weight (n,)`` log p/q, ``share``
        the uniform share of the proposal they came from (1: uniform draws); ``new_stage``
        starts a stage with them (the first batch always does)."""
        if new_stage or not self.stages:
            self.stages.append(dict.fromkeys(self.FIELDS, 0))
        st = self.stages[-1]
        w = np.exp(np.asarray(log_weight, np.float64)) * violated
        st["n"] += len(violated)
        st["s1"] += float(w.sum())
        st["s2"] += float((w * w).sum())
        st["bad"] += int(violated.sum())
        st["uniform_draws"] += share * len(violated)
        st["w_max"] = max(st["w_max"], float(w.max(initial=0.0)))
        st["above_uniform"] += int(np.sum(violated & (np.asarray(log_weight) > 1e-6)))
        self.n += len(violated)
        self._update()

    def leave_out(self, stages: int) -> None:
        """Count the draws of stage ``stages`` (0-based) on only."""
        self.first = stages
        self._update()

    def _update(self) -> None:
        kept = self.stages[self.first:]
        self.counted = sum(st["n"] for st in kept)
        self.s1, self.s2, self.uniform_draws = (sum(st[f] for st in kept)
                                                for f in ("s1", "s2", "uniform_draws"))
        self.bad = sum(st["bad"] for st in kept)
        self.above_uniform = sum(st["above_uniform"] for st in kept)
        self.w_max = max((st["w_max"] for st in kept), default=0.0)
        if self.counted == 0:  # nothing counted (yet): no estimate
            self.estimate = self.low = self.high = float("nan")
            self.rel = math.inf
            return
        if self.method == "mc":
            self.estimate = self.bad / self.counted
            self.low, self.high = wilson(self.bad, self.counted, self.confidence)
        elif self.bad == 0:  # no violation yet: the normal interval would be [0, 0]
            self.estimate, self.low = 0.0, 0.0
            self.high = no_violation_bound(self.uniform_draws, self.confidence)
        else:
            self.estimate, self.low, self.high = normal_interval(self.s1, self.s2,
                                                                 self.counted,
                                                                 self.confidence)
        self.rel = (self.high - self.low) / 2 / self.estimate if self.estimate > 0 \
            else math.inf

    def reached(self, target: float) -> bool:
        return self.bad >= MIN_VIOLATIONS and self.rel <= target


def cross_entropy(sp: Space, run, params, rparams, c: EstimateConfig, key,
                  progress: Progress, tally: Tally | None = None,
                  stop=None) -> tuple[Proposal, dict]:
    """The multilevel cross-entropy proposal, a mixture of ``ce_components`` products of
    categoricals: ``(proposal, {"levels", "samples"})``. Each level draws ``ce_samples``
    from the defensive mixture of the current proposal (the first: uniform) and fits the
    mixture by weighted EM to the draws below the level (the ``ce_quantile`` of their
    robustness, or the violations once ``ELITE_MIN`` are among the draws), weighted by p/q.

    The default quantile, 0.5, narrows the proposal slowly (the level halves the mass under
    it per level): on ``aeb-9e6`` (nine isolated failing scenarios in a million) a quantile of
    0.1 let the proposal settle on one or two of its four failure clusters, and the estimate
    (and its narrow interval) missed the others; 0.5 kept them. A ``stop()`` that turns true
    ends the levels (checked before each); the dict then says ``"stopped": True``."""
    shape = np.asarray(sp.shape)
    rng = np.random.default_rng([c.seed, 104729])
    q = uniform_proposal(sp)
    used, levels = 0, 0
    for level in range(c.ce_levels):
        if stop is not None and stop():
            return q, {"levels": levels, "samples": used, "stopped": True}
        levels = level + 1
        key, (idx, rob, logw) = _draw(run, key, q, 0.0 if level == 0 else math.log(
            c.defensive), params, rparams, c.ce_samples, c.batch)
        used += len(rob)
        n_bad = int(np.sum(rob < 0))
        if tally is not None:
            tally.add(rob < 0, logw, 1.0 if level == 0 else c.defensive, new_stage=True)
            tally.leave_out(math.floor(c.ce_burn_in * levels + 1e-9))
            if tally.reached(c.target_rel_error):
                progress.message(f"cross-entropy level {levels}: the estimate reached the "
                                 "target")
                break
        gamma = 0.0 if n_bad >= ELITE_MIN else max(float(np.quantile(rob, c.ce_quantile)),
                                                    0.0)
        elite = rob < 0 if n_bad >= ELITE_MIN else rob <= gamma
        progress.message(f"cross-entropy level {levels}: level {gamma:.4g}, {n_bad} "
                         f"violations of {len(rob)}")
        if not elite.any():
            continue
        w = np.exp(logw[elite] - logw[elite].max())
        # no more components than the elite draws can inform (PER_COMPONENT each): fitted to
        # a few draws, a mixture puts its mass on them and misses the failures beside them
        k = min(c.ce_components, max(1, int(elite.sum()) // PER_COMPONENT))
        q = fit_mixture(idx[elite], w, shape, k, rng, c.ce_iterations, start=q)
        if n_bad >= ELITE_MIN:
            break
    return q, {"levels": levels, "samples": used}


def estimate(config: EstimateConfig, progress: Progress | None = None, stop=None) -> dict:
    """The failure rate of ``config``'s requirement under its space: a dict with
    ``estimator``, ``samples`` (every draw made), ``proposal_samples`` (those drawn while
    fitting the proposal; ``samples`` allows ``config.samples`` more), ``counted_samples`` (the
    draws the estimate counts: all but those of the first ``left_out_levels`` cross-entropy
    levels), ``violations`` (violating draws among them), ``estimate``, ``interval`` [low,
    high] at ``confidence``, ``relative_half_width``, ``reached_target``, ``interrupted``
    (``stop()`` turned true before the draws allowed or the target: the estimate and interval
    are those of the counted draws so far, each weighted by the proposal it was drawn from),
    ``seconds``."""
    cfg.check_type(config, EstimateConfig, "config")
    progress = progress or Progress()
    sp, sut, params, req, rparams = config.build()
    c = config
    t0 = time.perf_counter()
    if c.method == "exact":
        progress.phase(f"every scenario of {sp.name} ({sp.size:,})")
        ex = exact_rate(sp, sut, params, req, rparams)
        return {"estimator": "exhaustive (every scenario evaluated)", "method": "exact",
                "requirement": c.requirement,
                "requirement_params": sut_lib.params_dict(rparams), "space": sp.name,
                "space_size": float(sp.size), "sut": c.sut, "samples": ex["scenarios"],
                "proposal_samples": 0, "proposal_levels": 0, "violations": ex["violations"],
                "estimate": ex["rate"], "interval": [ex["rate"], ex["rate"]],
                "confidence": 1.0, "relative_half_width": 0.0,
                "target_rel_error": c.target_rel_error, "reached_target": True,
                "interrupted": False, "seconds": time.perf_counter() - t0}
    run = _program(sp, sut, req, c.batch)
    key = sim.seed_key(c.seed)
    ce = {"levels": 0, "samples": 0}
    t = Tally(c.method, c.confidence)
    if c.method == "is":
        key, k = jax.random.split(key)
        q, ce = cross_entropy(sp, run, params, rparams, c, k, progress, t, stop)
        log_u = math.log(c.defensive)
    else:
        q, log_u = uniform_proposal(sp), 0.0
    total = ce["samples"] + c.samples
    interrupted = bool(ce.get("stopped"))
    if not interrupted:
        progress.start(total, done=t.n, unit="draw", desc=f"{c.method} estimate")
    new_stage = True  # the final draws: one stage
    while not interrupted and t.n < total and not t.reached(c.target_rel_error):
        if stop is not None and stop():
            interrupted = True
            break
        key, k = jax.random.split(key)
        _, rob, logw = run(k, jnp.asarray(q.log_weight), jnp.asarray(q.log_prob),
                           jnp.float32(log_u), params, rparams)
        m = min(c.batch, total - t.n)
        t.add(np.asarray(rob)[:m] < 0, np.asarray(logw)[:m], math.exp(log_u), new_stage)
        new_stage = False
        progress.update(t.n, estimate=f"{t.estimate:.3g}", rel=f"{t.rel:.3f}")
    progress.close()
    est, low, high, rel, n, k_bad = t.estimate, t.low, t.high, t.rel, t.n, t.bad
    reached = t.reached(c.target_rel_error)
    diagnostics = {} if c.method == "mc" else {
        "left_out_levels": t.first, "violations_above_uniform": t.above_uniform,
        "largest_weight_share": t.w_max / t.s1 if t.s1 > 0 else 0.0}
    return {"estimator": {"mc": "monte-carlo", "is": "importance-sampling (cross-entropy "
                          "proposal, defensive mixture)"}[c.method],
            "method": c.method, "requirement": c.requirement,
            "requirement_params": sut_lib.params_dict(rparams),
            "space": sp.name, "space_size": float(sp.size), "sut": c.sut,
            "samples": n, "proposal_samples": ce["samples"], "proposal_levels": ce["levels"],
            "counted_samples": t.counted, "violations": k_bad, "estimate": est,
            "interval": [low, high],
            "confidence": c.confidence, "relative_half_width": rel,
            "target_rel_error": c.target_rel_error,
            "reached_target": reached, "interrupted": interrupted and not reached,
            **diagnostics, "seconds": time.perf_counter() - t0}


def execute(config: EstimateConfig, out: Path | str, *, force: bool = False,
            progress: Progress | None = None, stop=None,
            startup_seconds: float = 0.0) -> dict:
    """:func:`estimate`, written to the folder ``out``: ``config.toml`` (resolved),
    ``summary.json`` (the estimate) and ``timing.json``; ``status.json`` says complete last,
    or ``interrupted`` when ``stop()`` ended the draws early (the summary then holds the
    estimate of the draws so far and says ``"interrupted": true``). Everything is checked
    before the folder is touched."""
    cfg.check_type(config, EstimateConfig, "config")
    clock = Clock(startup_seconds)
    built = config.build()
    cache.check_backend()
    out = Path(out)
    existed = out.exists()
    lk = store.open_folder(out, "estimate", force=force)
    try:
        lk.claim("estimate")
        if force:
            store.set_aside(out, "estimate")
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "config.toml", config.to_toml(*built))
        status = Status(out, "estimate")
        status.running()
        with clock("estimate"):
            summary = estimate(config, progress, stop)
        write_json(out / "summary.json", summary)
        write_json(out / "timing.json", clock.summary(), indent=2)
        if summary["interrupted"]:
            status.interrupted(samples_done=summary["samples"])
        else:
            status.complete()
        return summary
    except BaseException as e:
        if sut_raised(e) or store.nothing_written(out):
            store.discard(out, "estimate", lk, existed)
        elif (out / "config.toml").exists():
            Status(out, "estimate").failed(e)
        raise
    finally:
        lk.release()


def summary_lines(s: dict) -> list[str]:
    """What ``jaxfalsify estimate`` prints."""
    lo, hi = s["interval"]
    if s.get("interrupted") and s["samples"] == 0:
        return ["interrupted before any draw: no estimate"]
    if s["method"] == "exact":
        return [f"{s['requirement']} violated by {s['violations']:,} of the "
                f"{s['samples']:,} scenarios: {s['estimate']:.4g} (exact), {s['seconds']:.1f} s"]
    left = s.get("left_out_levels", 0)
    lines = [f"{s['requirement']} violated with probability {s['estimate']:.4g} "
             f"({s['confidence']:.0%} interval [{lo:.4g}, {hi:.4g}], relative half-width "
             f"{s['relative_half_width']:.3g})",
             f"{s['estimator']}: {s['samples']:,} draws"
             + (f" ({s['violations']:,} violating)" if not left else "")
             + (f", {s['proposal_samples']:,} of them while fitting the proposal in "
                f"{s['proposal_levels']} level{'s' if s['proposal_levels'] > 1 else ''}"
                if s["proposal_samples"] else "")
             + (f"; the estimate counts {s['counted_samples']:,} of them "
                f"({s['violations']:,} violating), leaving out those of the first {left} "
                f"level{'s' if left > 1 else ''}" if left else "")
             + f", {s['seconds']:.1f} s"]
    if s.get("interrupted"):
        lines.append(f"interrupted after {s['samples']:,} draws: the estimate and interval are "
                     "those of the draws counted so far")
    elif not s["reached_target"]:
        lines.append(f"the target relative half-width {s['target_rel_error']:g} was not "
                     "reached within the draws allowed (raise --samples)")
    if s.get("violations_above_uniform"):
        n = s["violations_above_uniform"]
        lines.append(f"{n} violating draw{'s' if n > 1 else ''} came from where the proposal "
                     "has less mass than uniform sampling (the largest weight is "
                     f"{s['largest_weight_share']:.0%} of the estimate): the proposal misses "
                     "part of the failure set, so the interval may be too narrow; compare "
                     "with --method mc")
    size = s.get("space_size", math.inf)
    if size <= min(s["samples"], MAX_SIZE):  # a sweep would have evaluated fewer scenarios
        lines.append(f"the space has {int(size):,} scenarios, no more than these "
                     f"{s['samples']:,} draws: --method exact evaluates each once and gives "
                     "the rate itself")
    return lines
