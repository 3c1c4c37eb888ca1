"""The strategy interface shared by every search algorithm (evosax's ask/tell shape).

A strategy is a frozen dataclass holding its *static* configuration (the space's ``shape``
``(P,)``, the ``batch`` of scenarios per ask, and whatever fixes shapes), plus pure functions
over integer index vectors whose hyperparameters come in as a traced ``params`` pytree:

* ``default_params() -> params``
* ``init(key, params) -> state``
* ``ask(key, state, params) -> (indices (B, P) int32, state)``: a batch of scenarios to run;
* ``tell(key, state, indices (B, P), rewards (B,), params) -> state``: learn from the rewards;
* ``tell_outcome(key, state, indices, rewards, robustness (B,), collision (B,), params,
  ttc=None)``: what the campaign calls, with the batch's STL robustness (min distance -
  epsilon [m], ``+inf`` where unknown), violation flags and minimum times-to-collision ``ttc``
  [s] beside the rewards. The default turns them into the strategy's learning ``signal`` and
  calls ``tell`` with it.
* ``ask_screened(key, state, params, screen) -> (indices, state)``: ``ask`` given a *screen*,
  a function from candidate scenarios ``(N, P)`` int32 to ``(N,)`` float32 seconds between the
  unbraked car's and the walker's windows at the crossing (:mod:`jaxfalsify.core.screen`; <= 0
  where they meet). The campaign calls it when it simulates the crossing world itself (not for
  an external evaluator); the default ignores the screen and calls ``ask`` (a strategy that
  uses the screen overrides ``ask_screened``, and its ``ask`` is ``ask_screened`` without one).
  ``reinforce/default`` screens part of its first batch by it.

**The learning signal is a function** (evosax's fitness shaping): ``signal(rewards,
robustness, collision, ttc) -> (B,)``, higher is better. :data:`SIGNALS` names the shipped ones
(``reward``: the paper's reward; ``shaped``: :func:`shaped_signal`); a strategy's ``signal``
option takes one of those names (the CLI, config files) or any such function (Python), resolved
by :func:`resolve_signal`.

Rewards given to ``tell`` are finite or ``-inf``: the campaign replaces NaN (a non-finite
rollout) and evaluations beyond the budget by ``-inf``, so they never rank as best. Every
function is jit-compatible; the campaign runs its updates (tell the previous batch -> ask ->
simulate) inside one compiled loop and jits once at the edge. States are
:func:`jaxfalsify.base.pytree.dataclass` pytrees.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, ClassVar

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree

__all__ = [
    "Strategy", "near_miss_ttc", "shaped_signal", "SIGNALS", "resolve_signal", "centred_ranks",
    "standardised", "ADVANTAGES", "resolve_advantage",
    "uniform", "sample_uniform", "value_mask", "sample_categorical",
    "categorical_from_uniform", "categorical_by_bisection", "uniform_indices", "rank_order"
]


@pytree.dataclass
class NoParams:
    """Hyperparameters of a strategy that has none."""


@dataclasses.dataclass(frozen=True)
class Strategy:
    """Base class: ``shape`` (values per parameter, ``(P,)``) and ``batch`` are static."""

    shape: tuple[int, ...]
    batch: int

    Params: ClassVar[type] = NoParams
    # what tell_outcome learns from: a name in SIGNALS or a signal function (a strategy that
    # lets users choose declares a ``signal`` field)
    signal: ClassVar[str | Callable] = "reward"
    # options that take a name or, from Python, a function: option -> its resolver (a
    # one-line ValueError on a bad value)
    FUNCTION_OPTIONS: ClassVar[dict[str, Callable]] = {"signal": lambda v: resolve_signal(v)}

    def default_params(self):
        return self.Params()

    def init(self, key: jax.Array, params) -> Any:
        raise NotImplementedError

    def start(self, key: jax.Array, params) -> Any:
        """The state a campaign starts from: ``init``'s, or a state that behaves as it does
        under ``ask`` and ``tell`` (the same draws, the same updates) with the parts the
        first ask does not need computed when they are first needed (this default: ``init``)."""
        return self.init(key, params)

    def ask(self, key: jax.Array, state, params) -> tuple[jax.Array, Any]:
        raise NotImplementedError

    def ask_screened(self, key: jax.Array, state, params,
                     screen: Callable[[jax.Array], jax.Array]) -> tuple[jax.Array, Any]:
        """``ask`` with a kinematic screen of candidate scenarios (the module docstring);
        this default does not use it."""
        return self.ask(key, state, params)

    def tell(self, key: jax.Array, state, indices: jax.Array, rewards: jax.Array, params):
        raise NotImplementedError

    def tell_outcome(self, key: jax.Array, state, indices: jax.Array, rewards: jax.Array,
                     robustness: jax.Array, collision: jax.Array, params, ttc=None):
        """``tell`` given the outcomes too: with the strategy's learning signal (its
        ``signal``, :func:`resolve_signal`) in place of the rewards. ``ttc (B,)``: each
        scenario's minimum time-to-collision [s] (``inf``: never on a collision course;
        ``None``: not known)."""
        signal = resolve_signal(self.signal)(rewards, robustness, collision, ttc)
        return self.tell(key, state, indices, signal, params)

    @property
    def n_params(self) -> int:
        return len(self.shape)

    @property
    def width(self) -> int:
        return max(self.shape)


# Weight of the STL robustness [reward units per metre] in the shaped signal.
ROBUSTNESS_WEIGHT = 0.05
TTC_CAP = 20.0  # s: a longer (or infinite, or unknown) minimum time-to-collision counts as this


def near_miss_ttc(robustness: jax.Array, ttc: jax.Array, weight, below) -> jax.Array:
    """The robustness [m] with near misses told apart by their minimum time-to-collision:
    where ``robustness < below`` (the two road users came within ``below + 1`` m), add
    ``weight * min(ttc, TTC_CAP)`` [m per s], so among near misses of about the same distance
    the one where the car was still closing fast (low TTC: a collision nearby) ranks as the
    more critical, and one where the car had stopped short (high or infinite TTC) as the less.
    Elsewhere, and with ``weight`` 0, the robustness is returned unchanged."""
    t = jnp.where(jnp.isfinite(ttc), jnp.minimum(ttc, TTC_CAP), TTC_CAP)
    return jnp.where(robustness < below, robustness + weight * t, robustness)


def shaped_signal(rewards: jax.Array, robustness: jax.Array, collision: jax.Array) -> jax.Array:
    """The paper's reward, made dense where it is flat: a collision scores its reward, any
    other scenario ``-ROBUSTNESS_WEIGHT * robustness`` (STL robustness = min distance - 1 m: the
    closer the two road users came, the higher). Robustness is at least -1 m, so a scenario
    without a collision scores at most 0.05 and every collision (reward above 0.22) ranks above
    every non-collision: for a rank-based learner this is "robustness until a collision is
    found, the paper's reward among the collisions". ``-inf`` rewards stay ``-inf``; an
    unknown (non-finite) robustness scores as the reward."""
    dense = jnp.where(jnp.isfinite(robustness), -ROBUSTNESS_WEIGHT * robustness, rewards)
    shaped = jnp.where(collision, rewards, jnp.minimum(dense, ROBUSTNESS_WEIGHT))
    return jnp.where(jnp.isfinite(rewards), shaped, -jnp.inf).astype(jnp.float32)


def reward_signal(rewards, robustness, collision, ttc=None) -> jax.Array:
    """The signal ``reward``: the paper's reward (Eq. 1) as it is."""
    return rewards


def shaped(rewards, robustness, collision, ttc=None) -> jax.Array:
    """The signal ``shaped``: :func:`shaped_signal`."""
    return shaped_signal(rewards, robustness, collision)


# The shipped learning signals by name: ``signal(rewards (B,), robustness (B,) [m],
# collision (B,) bool, ttc (B,) [s] or None) -> (B,)``, higher is better.
SIGNALS: dict[str, Callable] = {"reward": reward_signal, "shaped": shaped}


def resolve_signal(signal) -> Callable:
    """The learning-signal function ``signal`` names (a key of :data:`SIGNALS`), or ``signal``
    itself when it is a function; one-line ValueError otherwise."""
    if isinstance(signal, str) and signal in SIGNALS:
        return SIGNALS[signal]
    if callable(signal) and not isinstance(signal, str):
        return signal
    raise ValueError(f"signal must be one of {', '.join(SIGNALS)} or a function "
                     f"(got {signal!r})")


def centred_ranks(x: jax.Array, valid: jax.Array | None = None) -> jax.Array:
    """Fitness shaping over the last axis: each entry's rank among the valid ones, in
    [-0.5, 0.5] (ties share their mean rank; invalid entries get 0). ``O(n^2)``, for the small
    batches of one learner."""
    if valid is None:
        valid = jnp.isfinite(x)
    vi, vj = valid[..., :, None], valid[..., None, :]
    below = jnp.sum((x[..., None, :] < x[..., :, None]) & vj, axis=-1)
    ties = jnp.sum((x[..., None, :] == x[..., :, None]) & vj & vi, axis=-1) - 1
    n = jnp.sum(valid, axis=-1, keepdims=True)
    # (below + ties / 2) / (n - 1) - 1/2 with an integer numerator, so a tie is exactly 0
    # (XLA may divide by multiplying with a reciprocal: 15.5 / 31 - 0.5 came out -3e-8, and
    # Adam, which normalises the gradient, turned such noise into full-size steps)
    num = 2 * below + jnp.maximum(ties, 0) - (n - 1)
    rank = num.astype(jnp.float32) / (2 * jnp.maximum(n - 1, 1)).astype(jnp.float32)
    return jnp.where(valid & (n > 1), rank, 0.0).astype(jnp.float32)


def standardised(x: jax.Array, valid: jax.Array) -> jax.Array:
    """Fitness shaping over the last axis: the valid entries minus their mean over their
    standard deviation (invalid entries, and every entry when all valid ones are equal, get
    exactly 0)."""
    v = jnp.where(valid, x, 0.0)
    n = jnp.maximum(jnp.sum(valid, -1, keepdims=True), 1)
    mean = jnp.sum(v, -1, keepdims=True) / n
    std = jnp.sqrt(jnp.sum(jnp.where(valid, (v - mean) ** 2, 0.0), -1, keepdims=True) / n)
    # all equal: exactly 0 (v - mean is float32 noise there, which the division by a std of
    # the same noise would blow up to O(1))
    flat = jnp.max(jnp.where(valid, x, -jnp.inf), -1, keepdims=True) \
        <= jnp.min(jnp.where(valid, x, jnp.inf), -1, keepdims=True)
    return jnp.where(valid & ~flat, (v - mean) / (std + 1e-8), 0.0)


# Advantage functions ``(signal (..., n), valid (..., n)) -> (..., n)`` a strategy may be
# given by name (``advantage="rank"``); from Python any such function.
ADVANTAGES: dict[str, Callable] = {"rank": centred_ranks, "normalised": standardised}


def resolve_advantage(advantage) -> Callable:
    """The advantage function ``advantage`` names (a key of :data:`ADVANTAGES`), or
    ``advantage`` itself when it is a function; one-line ValueError otherwise."""
    if isinstance(advantage, str) and advantage in ADVANTAGES:
        return ADVANTAGES[advantage]
    if callable(advantage) and not isinstance(advantage, str):
        return advantage
    raise ValueError(f"advantage must be one of {', '.join(ADVANTAGES)} or a function "
                     f"(got {advantage!r})")


def uniform(key, shape: tuple[int, ...]) -> jax.Array:
    """U[0, 1) float32 of ``shape``, drawn flat and reshaped: with JAX's partitionable threefry
    a multi-dimensional draw costs ~1 s more XLA compilation than a flat one."""
    n = 1
    for d in shape:
        n *= d
    return jax.random.uniform(key, (n,)).reshape(shape)


def sample_uniform(key, shape: tuple[int, ...], batch: int) -> jax.Array:
    """``(batch, P)`` int32 indices, each parameter uniform over its ``shape[p]`` values.

    One uniform draw scaled per parameter (a single threefry call: every ``jax.random`` call
    site is compiled in full, so fewer, larger draws compile faster)."""
    return uniform_indices(uniform(key, (batch, len(shape))), shape)


def value_mask(shape: tuple[int, ...]) -> jax.Array:
    """``(P, max_n)`` bool: which padded slots are real values of each parameter."""
    width = max(shape)
    return jnp.arange(width)[None, :] < jnp.asarray(shape)[:, None]


def sample_categorical(key, probs: jax.Array, batch: int) -> jax.Array:
    """``(batch, P)`` int32 indices from per-parameter probabilities ``probs (P, max_n)``
    (:func:`categorical_by_bisection` of one uniform draw)."""
    return categorical_by_bisection(uniform(key, (batch, probs.shape[0])), probs)


def categorical_by_bisection(u: jax.Array, probs: jax.Array) -> jax.Array:
    """``u (B, P)`` in [0, 1) and per-parameter probabilities ``probs (P, max_n)`` -> indices
    ``(B, P)`` int32: :func:`categorical_from_uniform`'s draws (the same indices for finite
    probabilities, whose cumulative sums do not decrease), each parameter's CDF searched by
    bisection, ``O(B P log max_n)`` (comparing every draw with every value is
    ``O(B P max_n)``: 0.3 s per update at batch 4096 on 8 parameters of up to 2000 values)."""
    cdf = jnp.cumsum(probs, axis=-1)  # (P, n), non-decreasing
    x = u.T * cdf[:, -1:]  # (P, batch)
    # the number of values whose cumulative probability is <= x, as categorical_from_uniform
    idx = jax.vmap(lambda c, v: jnp.searchsorted(c, v, side="right", method="scan"))(cdf, x)
    n = probs.shape[-1]
    last = n - 1 - jnp.argmax(jnp.flip(probs > 0, axis=-1), axis=-1)  # (P,)
    return jnp.minimum(idx, last[:, None]).astype(jnp.int32).T


def categorical_from_uniform(u: jax.Array, probs: jax.Array) -> jax.Array:
    """Inverse-CDF sampling: ``u (...,)`` in [0, 1) and ``probs (..., n)`` -> indices ``(...)``
    int32 (the first value whose cumulative probability exceeds ``u``; padded zero-probability
    slots are never chosen). Lets one uniform draw serve several samplers."""
    cdf = jnp.cumsum(probs, axis=-1)
    idx = jnp.sum(cdf <= u[..., None] * cdf[..., -1:], axis=-1)
    # the last value with a non-zero probability (guards rounding at u -> 1; a narrow
    # distribution can have exact zeros anywhere, not only in the padded slots)
    n = probs.shape[-1]
    last = n - 1 - jnp.argmax(jnp.flip(probs > 0, axis=-1), axis=-1)
    return jnp.minimum(idx, last).astype(jnp.int32)


def uniform_indices(u: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """``u (..., P)`` in [0, 1) -> indices ``(..., P)`` int32, uniform over each ``shape[p]``."""
    n = jnp.asarray(shape, jnp.float32)
    return jnp.minimum(jnp.floor(u * n), n - 1).astype(jnp.int32)


def rank_order(key, rewards: jax.Array) -> jax.Array:
    """Indices sorting ``rewards`` best first, ties broken at random (``-inf`` last)."""
    u = jax.random.uniform(key, rewards.shape)
    return jnp.lexsort((u, -rewards))
