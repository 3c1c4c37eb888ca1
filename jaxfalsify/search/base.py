"""The strategy interface shared by every search algorithm.

A strategy is a pair of pure functions over integer index vectors, in the spirit of optax's
``GradientTransformation`` and evosax's ask/tell:

* ``init(key) -> state``
* ``ask(key, state) -> (indices (B, P) int32, state)``: a batch of concrete scenarios to run;
* ``tell(state, indices, rewards (B,)) -> state``: learn from their rewards.

Rewards given to ``tell`` are finite or ``-inf``: the driver replaces NaN (a non-finite rollout)
and evaluations beyond the budget by ``-inf``, so they never rank as best. Strategies are built
by ``make(space_shape, batch, **hyper)`` for a fixed batch size (static shapes) and are
jit-compatible: the campaign driver runs ``ask``/evaluate/``tell`` inside one ``lax.scan``.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp


class Strategy(NamedTuple):
    name: str
    init: Callable[[jax.Array], Any]
    ask: Callable[[jax.Array, Any], tuple[jax.Array, Any]]
    tell: Callable[[Any, jax.Array, jax.Array], Any]


def sample_uniform(key, shape: tuple[int, ...], batch: int) -> jax.Array:
    """``(batch, P)`` int32 indices, each parameter uniform over its ``shape[p]`` values."""
    keys = jax.random.split(key, len(shape))
    cols = [jax.random.randint(k, (batch,), 0, n) for k, n in zip(keys, shape)]
    return jnp.stack(cols, axis=-1).astype(jnp.int32)


def value_mask(shape: tuple[int, ...]) -> jax.Array:
    """``(P, max_n)`` bool: which padded slots are real values of each parameter."""
    width = max(shape)
    return jnp.arange(width)[None, :] < jnp.asarray(shape)[:, None]


def sample_categorical(key, probs: jax.Array, batch: int) -> jax.Array:
    """``(batch, P)`` int32 indices from per-parameter probabilities ``probs (P, max_n)``."""
    logits = jnp.log(jnp.maximum(probs, 1e-30))
    logits = jnp.where(probs > 0, logits, -jnp.inf)
    return jax.random.categorical(key, logits, axis=-1, shape=(batch, probs.shape[0])
                                  ).astype(jnp.int32)
