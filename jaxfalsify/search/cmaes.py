"""CMA-ES with margin (Hamano, Saito, Nomura & Shirakawa, GECCO 2022) over the index lattice.

Each parameter's index range is relaxed to ``[0, 1]`` (value ``k`` of ``n`` at ``k / (n - 1)``);
a candidate ``x`` is encoded to the value whose interval (between the midpoints of neighbouring
values) holds ``(x - m) * A + m``, ``m`` the mean and ``A`` the margin's diagonal scaling (1 at
start). Below the first / above the last midpoint means the first / last value. The CMA-ES
itself (evosax's, the standard (mu/mu_w, lambda) update with negative weights) learns from the
raw candidates; after each update the margin correction (the reference implementation, as in
the ``cmaes`` package's ``CMAwM``) keeps, for every parameter, the marginal probability of
leaving the mean's current value at least ``margin / 2`` on each side: where the mean sits in
an inner value's interval, ``A`` and the mean are set so both tails hold at least
``margin / 2``; where it sits in the first or last interval (the edge case) and the probability
of moving inwards is below ``margin``, the mean is pulled in until it is ``margin``. So the
search neither fixes a parameter at one value for ever (the failure of plain rounding) nor
stalls with its mean far outside the box (the clipped candidates of plain CMA-ES all landing on
the bounds); ``margin = 0`` turns the correction off (plain CMA-ES with rounding). ``margin``
< 0 means the paper's default ``1 / (P * lambda)``.

evosax minimises and weights candidates by rank, so it sees each candidate's ordinal rank
(0 for the highest signal), ties broken at random and a -inf (NaN rollout, beyond budget) last:
evosax's own ranking (``rankdata``) gives tied candidates one averaged, truncated rank, hence
the same weight, where Hansen's algorithm uses every weight once; on a plateau of equal
signals that shrank the step size towards 0. ``signal``: ``shaped`` (default;
:func:`jaxfalsify.search.base.shaped_signal`, the robustness that falsification tools give CMA-ES,
until a collision) or ``reward``.
"""

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
from jax.scipy.special import ndtr, ndtri

from jaxfalsify.base import pytree
from jaxfalsify.search.base import Strategy, resolve_signal

__all__ = ["CMAES", "ordinal_ranks", "margin_correction", "CMAESParams", "CMAESState"]


@pytree.dataclass
class CMAESParams:
    std_init: float = 0.3  # initial step size, in units of each parameter's index range
    margin: float = -1.0  # marginal probability floor; < 0: 1 / (P * batch), 0: no margin

    RANGES = {"std_init": "(0, inf)", "margin": "(-inf, 1)"}


@pytree.dataclass
class CMAESState:
    es: object  # evosax's CMA-ES state
    pop: jax.Array  # (B, P) float32, the last asked population (evosax's tell needs it)
    A: jax.Array  # (P,) float32, the margin's diagonal scaling


@dataclasses.dataclass(frozen=True)
class CMAES(Strategy):
    signal: str | Callable = "shaped"

    Params = CMAESParams

    def __post_init__(self):
        resolve_signal(self.signal)  # a one-line error on a bad one
        if self.batch < 2:  # one candidate has no parent to recombine: the mean turns NaN
            raise ValueError(f"batch={self.batch}: strategy 'cmaes' needs a population of at "
                             "least 2")

    def _es(self):
        from evosax.algorithms import CMA_ES

        return CMA_ES(population_size=self.batch, solution=jnp.zeros(self.n_params))

    def _es_params(self, es, params):
        return es.default_params.replace(std_init=params.std_init)

    @property
    def _span(self) -> jax.Array:
        return jnp.maximum(jnp.asarray(self.shape, jnp.float32) - 1, 1.0)

    def _margin(self, params) -> jax.Array:
        return jnp.where(params.margin < 0, 1.0 / (self.n_params * self.batch), params.margin)

    def encode(self, x: jax.Array, mean: jax.Array, A: jax.Array) -> jax.Array:
        """Candidates ``x (..., P)`` -> value indices ``(..., P)`` int32."""
        span = self._span
        z = (x - mean) * A + mean
        last = jnp.asarray(self.shape, jnp.float32) - 1  # a one-value parameter: always 0
        return jnp.clip(jnp.floor(z * span + 0.5), 0, last).astype(jnp.int32)

    def init(self, key, params):
        es = self._es()
        state = es.init(key, jnp.full((self.n_params,), 0.5), self._es_params(es, params))
        return CMAESState(state, jnp.zeros((self.batch, self.n_params)),
                          jnp.ones(self.n_params))

    def ask(self, key, state, params):
        es = self._es()
        pop, es_state = es.ask(key, state.es, self._es_params(es, params))
        return self.encode(pop, state.es.mean, state.A), CMAESState(es_state, pop, state.A)

    def tell(self, key, state, indices, rewards, params):
        es = self._es()
        es_state, _ = es.tell(key, state.pop, ordinal_ranks(key, rewards), state.es,
                              self._es_params(es, params))
        mean, A = margin_correction(es_state.mean, es_state.std, jnp.diag(es_state.C), state.A,
                                    self.shape, self._margin(params))
        return CMAESState(es_state.replace(mean=mean), state.pop, A)


def ordinal_ranks(key, rewards: jax.Array) -> jax.Array:
    """``(B,)`` float32 ranks 0..B-1 of ``rewards (B,)``, 0 for the highest; equal rewards in
    a random order (from ``key``), -inf and NaN last."""
    r = jnp.where(jnp.isnan(rewards), -jnp.inf, rewards)
    order = jnp.lexsort((jax.random.uniform(jax.random.fold_in(key, 1), r.shape), -r))
    return jnp.zeros(r.shape, jnp.float32).at[order].set(jnp.arange(r.shape[0],
                                                                     dtype=jnp.float32))


def margin_correction(mean, sigma, c_diag, A, shape, margin):
    """The margin correction of CMA-ES with margin for parameters of ``shape`` values on the
    ``[0, 1]`` relaxation: ``(mean', A')``. One-value parameters and ``margin == 0`` are left
    as they are."""
    n = jnp.asarray(shape, jnp.float32)
    span = jnp.maximum(n - 1, 1.0)
    # the midpoints around the mean's value: its interval [lo, up]; in the first (last) interval
    # both are the first (last) midpoint, as the reference implementation sets them
    k = jnp.clip(jnp.floor(mean * span + 0.5), 0, n - 1)
    first, last = 0.5 / span, (n - 1.5) / span
    lo = jnp.where(k == 0, first, (k - 0.5) / span)
    up = jnp.where(k == n - 1, last, (k + 0.5) / span)
    active = (n > 1) & (margin > 0)
    a = jnp.maximum(margin, 1e-12)
    scale = sigma * A * jnp.sqrt(c_diag)
    low_cdf = ndtr((lo - mean) / scale)
    up_cdf = 1.0 - ndtr((up - mean) / scale)
    mid_cdf = 1.0 - low_cdf - up_cdf
    edge = jnp.maximum(low_cdf, up_cdf) > 0.5
    # edge case: the mean beyond the first/last midpoint; pull it in until the probability of
    # crossing that midpoint is the margin
    modify = edge & (jnp.minimum(low_cdf, up_cdf) < a)
    sign = jnp.sign(mean - up)
    dist = scale * ndtri(1.0 - a)  # sqrt(chi2_ppf(1 - 2a, 1)) * scale
    mean_edge = jnp.where(modify, up + sign * dist, mean)
    # inner values: lift both tails to margin / 2, rescale the rest, then solve for mean and A
    low_c = jnp.maximum(low_cdf, a / 2)
    up_c = jnp.maximum(up_cdf, a / 2)
    denom = low_c + mid_cdf + up_c - 1.5 * a
    extra = 1.0 - low_c - up_c - mid_cdf
    low_m = jnp.clip(low_c + extra * (low_c - a / 2) / denom, 1e-10, 0.5 - 1e-10)
    up_m = jnp.clip(up_c + extra * (up_c - a / 2) / denom, 1e-10, 0.5 - 1e-10)
    chi_low, chi_up = ndtri(1.0 - low_m), ndtri(1.0 - up_m)
    A_side = (up - lo) / ((chi_low + chi_up) * sigma * jnp.sqrt(c_diag))
    mean_side = (lo * chi_up + up * chi_low) / (chi_low + chi_up)
    new_mean = jnp.where(edge, mean_edge, mean_side)
    new_A = jnp.where(edge, A, A_side)
    ok = active & jnp.isfinite(new_mean) & jnp.isfinite(new_A) & (new_A > 0)
    return jnp.where(ok, new_mean, mean), jnp.where(ok, new_A, A)
