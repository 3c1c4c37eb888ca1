"""The paper's controller (Section III-A 'Controller', Fig. 6): an LSTM policy over parameter values.

Input: the previous action — each parameter's value given as its rank among the parameter's
sorted values, scaled to [0, 1] (the original fed raw values) — as a length-1 sequence. Two LSTM layers
of 32 units with relu activation (Keras ``LSTM(32, activation='relu')`` as the original), then one
softmax head per parameter over that parameter's discrete values. The heads are one linear
layer whose ``(P, max_n)`` output is masked per parameter, which is the same as P separate
heads. Sizes follow the space, so any user space works.

As in the original (a stateless Keras LSTM called on one time step), every call starts from a
zero LSTM state.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx


# Logit of padded (non-existent) values: finite, so gradients through softmax stay finite,
# and low enough that their probability is exactly 0 in float32.
MASKED = -1e9


class Controller(nnx.Module):
    """``Controller(shape)(x (P,)) -> logits (P, max_n)``, ``MASKED`` on padded slots."""

    def __init__(self, shape: tuple[int, ...], hidden: int = 32, *, rngs: nnx.Rngs):
        self.shape = tuple(int(n) for n in shape)
        self.hidden = hidden
        P, width = len(self.shape), max(self.shape)
        self.lstm1 = nnx.OptimizedLSTMCell(P, hidden, activation_fn=nnx.relu, rngs=rngs)
        self.lstm2 = nnx.OptimizedLSTMCell(hidden, hidden, activation_fn=nnx.relu, rngs=rngs)
        self.head = nnx.Linear(hidden, P * width, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        P, width = len(self.shape), max(self.shape)
        zeros = (jnp.zeros(self.hidden), jnp.zeros(self.hidden))
        _, h1 = self.lstm1(zeros, x)
        _, h2 = self.lstm2(zeros, h1)
        logits = self.head(h2).reshape(P, width)
        mask = jnp.arange(width)[None, :] < jnp.asarray(self.shape)[:, None]
        return jnp.where(mask, logits, MASKED)


def log_probs(logits: jax.Array) -> jax.Array:
    """Per-head log-softmax ``(P, max_n)``; padded slots get ~MASKED."""
    return jax.nn.log_softmax(logits, axis=-1)


def action_log_prob(logits: jax.Array, action: jax.Array) -> jax.Array:
    """log pi(a) = sum over heads of log softmax(logits_p)[a_p]; ``action (P,)`` int."""
    lp = log_probs(logits)
    return jnp.sum(jnp.take_along_axis(lp, action[:, None], axis=-1))


def entropy(logits: jax.Array) -> jax.Array:
    """Sum over heads of each head's entropy [nats]."""
    lp = log_probs(logits)
    p = jnp.exp(lp)
    return -jnp.sum(p * lp)  # padded slots: p == 0 exactly, lp finite


def normalise(indices: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Index vector ``(..., P)`` -> each parameter's position in [0, 1] (its value rank)."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return indices.astype(jnp.float32) / span
