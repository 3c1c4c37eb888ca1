"""The paper's controller (Section III-A 'Controller', Fig. 5): an LSTM policy over parameter
values.

Input: the previous action — each parameter's value given as its rank among the parameter's
sorted values, scaled to [0, 1] (the original fed raw values) — as a length-1 sequence. Two
LSTM layers of 32 units with relu activation (Keras ``LSTM(32, activation='relu')`` as the
original), then one softmax head per parameter over that parameter's discrete values. The
heads are one linear layer whose ``(P, max_n)`` output is masked per parameter, which is the
same as P separate heads. As in the original (a stateless Keras LSTM called on one time step),
every call starts from a zero LSTM state.

The network is a Flax (``flax.linen``) module, :class:`PaperController`, built of
:class:`LSTMCell` (Keras' fused LSTM: one ``(in, 4H)`` input kernel, one ``(H, 4H)`` recurrent
kernel, gates in order i, f, g, o, the forget gate's bias starting at 1).
:func:`init` draws its weights in one Glorot-uniform draw (Keras uses an orthogonal recurrent
kernel, which a zero initial state never multiplies, and whose QR decomposition costs seconds of
XLA compilation); ``PaperController(...).init`` gives the same tree with Flax's own initialisers.
``tests/search/test_strategy_contract.py`` checks the cell against the LSTM equations in NumPy.

``flax.linen`` rather than ``flax.nnx``: a linen module is a pure function of a parameter
pytree, which is what a strategy's state holds, a campaign's loop carries, checkpoints
store and ``jax.export`` caches; and it imports faster (on top of jax and optax, measured on
2 CPU cores: linen +0.09 s, nnx +0.16 s).
"""

from __future__ import annotations

from typing import Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

__all__ = [
    "MASKED", "mm", "LSTMCell", "lstm_step", "glorot", "init", "Linear", "PaperController",
    "logits", "action_log_prob", "entropy", "normalise"
]

# Logit of padded (non-existent) values: finite, so gradients through softmax stay finite,
# and low enough that their probability is exactly 0 in float32.
MASKED = -1e9


def mm(a: jax.Array, b: jax.Array) -> jax.Array:
    """``a @ b`` in full float32 on every backend (GPUs otherwise multiply float32 matrices in
    TF32, ~1e-3 relative error, which moved log-probabilities by ~1e-4 on an H100)."""
    return jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)


def lstm_init(key, in_features: int, hidden: int) -> dict[str, jax.Array]:
    """One LSTM layer: ``w (in, 4H)``, ``u (H, 4H)``, ``b (4H,)``; gates in order i, f, g, o."""
    w, u = glorot(key, [(in_features, 4 * hidden), (hidden, 4 * hidden)])
    b = jnp.zeros(4 * hidden, jnp.float32).at[hidden:2 * hidden].set(1.0)
    return {"w": w, "u": u, "b": b}


def _glorot_init(key, shape, dtype=jnp.float32):
    (w,) = glorot(key, [tuple(shape)])
    return w.astype(dtype)


def _forget_bias_init(key, shape, dtype=jnp.float32):
    hidden = shape[0] // 4
    return jnp.zeros(shape, dtype).at[hidden:2 * hidden].set(1.0)


class LSTMCell(nn.Module):
    """Keras' LSTM cell as a Flax module: ``(h, c), x (..., in) -> ((h', c'), h')`` with
    ``z = x w + h u + b``, i, f, o = sigmoid gates, g = ``activation``, ``c' = f c + i g``,
    ``h' = o activation(c')``. Parameters ``w (in, 4H)``, ``u (H, 4H)``, ``b (4H,)``."""

    hidden: int
    activation: Callable = jax.nn.relu

    @nn.compact
    def __call__(self, carry, x):
        h, c = carry
        w = self.param("w", _glorot_init, (x.shape[-1], 4 * self.hidden))
        u = self.param("u", _glorot_init, (self.hidden, 4 * self.hidden))
        b = self.param("b", _forget_bias_init, (4 * self.hidden,))
        z = mm(x, w) + mm(h, u) + b
        i, f, g, o = jnp.split(z, 4, axis=-1)
        c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * self.activation(g)
        h = jax.nn.sigmoid(o) * self.activation(c)
        return (h, c), h


def lstm_step(p: dict, carry: tuple[jax.Array, jax.Array], x: jax.Array,
              activation=jax.nn.relu) -> tuple[jax.Array, jax.Array]:
    """``(h, c), x (in,) -> (h', c')``: one step of :class:`LSTMCell` with weights ``p``."""
    hidden = p["u"].shape[0]
    return LSTMCell(hidden, activation).apply({"params": p}, carry, x)[0]


def dense_init(key, in_features: int, out_features: int) -> dict[str, jax.Array]:
    (w,) = glorot(key, [(in_features, out_features)])
    return {"w": w, "b": jnp.zeros(out_features, jnp.float32)}


def glorot(key, shapes: list[tuple[int, int]]) -> list[jax.Array]:
    """Glorot-uniform matrices, U(-l, l) with l = sqrt(6 / (fan_in + fan_out)), from one draw."""
    sizes = [a * b for a, b in shapes]
    u = jax.random.uniform(key, (sum(sizes),), minval=-1.0, maxval=1.0)
    out, at = [], 0
    for (a, b), n in zip(shapes, sizes):
        out.append(u[at:at + n].reshape(a, b) * jnp.sqrt(6.0 / (a + b)))
        at += n
    return out


def mask_logits(logits: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    width = max(shape)
    mask = jnp.arange(width)[None, :] < jnp.asarray(shape)[:, None]
    return jnp.where(mask, logits, MASKED)


def init(key, shape: tuple[int, ...], hidden: int = 32) -> dict:
    """The paper's controller: two relu LSTM layers and one linear head ``(P * max_n)``
    (all weights from one draw: each random call site costs compile time)."""
    P, width = len(shape), max(shape)
    w1, u1, w2, u2, wh = glorot(key, [(P, 4 * hidden), (hidden, 4 * hidden),
                                      (hidden, 4 * hidden), (hidden, 4 * hidden),
                                      (hidden, P * width)])
    b = jnp.zeros(4 * hidden, jnp.float32).at[hidden:2 * hidden].set(1.0)
    return {"lstm1": {"w": w1, "u": u1, "b": b}, "lstm2": {"w": w2, "u": u2, "b": b},
            "head": {"w": wh, "b": jnp.zeros(P * width, jnp.float32)}}


class Linear(nn.Module):
    """``x (..., in) -> x w + b (..., features)`` in full float32 (:func:`mm`); parameters
    ``w (in, features)`` Glorot-uniform, ``b (features,)`` zeros."""

    features: int

    @nn.compact
    def __call__(self, x):
        w = self.param("w", _glorot_init, (x.shape[-1], self.features))
        b = self.param("b", nn.initializers.zeros_init(), (self.features,))
        return mm(x, w) + b


class PaperController(nn.Module):
    """The paper's controller (Fig. 5): ``x (P,)`` (the previous action, normalised) -> masked
    logits ``(P, max_n)``. Two relu LSTM layers of ``hidden`` units, each called on one time
    step from a zero state, then one linear head over every parameter's values."""

    shape: tuple[int, ...]
    hidden: int = 32

    @nn.compact
    def __call__(self, x):
        zeros = (jnp.zeros(self.hidden), jnp.zeros(self.hidden))
        _, h1 = LSTMCell(self.hidden, name="lstm1")(zeros, x)
        _, h2 = LSTMCell(self.hidden, name="lstm2")(zeros, h1)
        P, width = len(self.shape), max(self.shape)
        out = Linear(P * width, name="head")(h2)
        return mask_logits(out.reshape(P, width), self.shape)


def logits(params: dict, x: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """``x (P,)`` (the previous action, normalised) -> masked logits ``(P, max_n)``: the
    :class:`PaperController` with weights ``params`` (as :func:`init` makes them)."""
    hidden = params["lstm1"]["u"].shape[0]
    return PaperController(tuple(shape), hidden).apply({"params": params}, x)


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
    return -jnp.sum(jnp.exp(lp) * lp)  # padded slots: p == 0 exactly, lp finite


def normalise(indices: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Index vector ``(..., P)`` -> each parameter's position in [0, 1] (its value rank)."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return indices.astype(jnp.float32) / span
