"""Cross-entropy method over independent per-parameter categorical distributions.

Each update samples a batch from the current distributions, keeps the best ``elite_frac`` of
it (ties broken at random), and moves each parameter's probabilities a step ``smoothing``
towards the elite's value frequencies; a floor of ``min_prob`` (renormalised) keeps every value
possible (Rubinstein & Kroese, *The Cross-Entropy Method*, 2004, smoothed updates).
"""

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.search.base import (
    Strategy,
    rank_order,
    resolve_signal,
    sample_categorical,
    value_mask,
)

__all__ = ["CEMParams", "CEM", "CEMState"]


@pytree.dataclass
class CEMParams:
    elite_frac: float = 0.1  # share of the batch kept as the elite
    smoothing: float = 0.7  # step towards the elite's frequencies
    min_prob: float = 0.002  # floor of every value's probability

    RANGES = {"elite_frac": "(0, 1]", "smoothing": "[0, 1]", "min_prob": "[0, 1)"}


@pytree.dataclass
class CEMState:
    probs: jax.Array  # (P, max_n) float32, per-parameter categorical distributions


@dataclasses.dataclass(frozen=True)
class CEM(Strategy):
    """Static: ``signal``, what it learns from: ``shaped`` (default,
    :func:`jaxfalsify.search.base.shaped_signal`) or ``reward`` (the paper's reward)."""

    signal: str | Callable = "shaped"

    Params = CEMParams

    def __post_init__(self):
        resolve_signal(self.signal)  # a one-line error on a bad one

    def init(self, key, params):
        mask = value_mask(self.shape)
        return CEMState(mask / mask.sum(-1, keepdims=True))

    def ask(self, key, state, params):
        return sample_categorical(key, state.probs, self.batch), state

    def tell(self, key, state, indices, rewards, params):
        mask = value_mask(self.shape)
        n_elite = jnp.maximum(1.0, jnp.round(params.elite_frac * self.batch))
        rank = jnp.zeros(self.batch, jnp.int32).at[rank_order(key, rewards)].set(
            jnp.arange(self.batch, dtype=jnp.int32))
        # the elite: the best n_elite of the finite outcomes (a failed rollout, -inf, never
        # teaches the distribution; a batch of failures leaves it as it was)
        elite = (rank < n_elite) & jnp.isfinite(rewards)
        n = elite.sum()
        weight = elite.astype(jnp.float32) / jnp.maximum(n, 1)  # (B,)
        # the elite's value frequencies, (P, max_n): a scatter-add, O(B P) (a one-hot product
        # is O(B P max_n)); every non-zero addend is the same 1 / n, so the sums do not
        # depend on the order of the additions
        params_of = jnp.broadcast_to(jnp.arange(self.n_params), indices.shape)
        freq = jnp.zeros((self.n_params, self.width), jnp.float32).at[
            params_of, indices].add(jnp.broadcast_to(weight[:, None], indices.shape))
        probs = (1 - params.smoothing) * state.probs + params.smoothing * freq
        probs = jnp.where(mask, jnp.maximum(probs, params.min_prob), 0.0)
        probs = probs / probs.sum(-1, keepdims=True)
        return CEMState(jnp.where(n > 0, probs, state.probs))
