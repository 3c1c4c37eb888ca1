"""Cross-entropy method over independent per-parameter categorical distributions.

Each update samples a batch from the current distributions, keeps the best ``elite_frac`` of
it (ties broken at random), and moves each parameter's probabilities a step ``smoothing`` towards
the elite's value frequencies; a floor of ``min_prob`` (renormalised) keeps every value possible.
"""

import jax
import jax.numpy as jnp

from jaxfalsify.search.base import Strategy, sample_categorical, value_mask


def make(shape: tuple[int, ...], batch: int, elite_frac: float = 0.1, smoothing: float = 0.7,
         min_prob: float = 0.002) -> Strategy:
    mask = value_mask(shape)
    n_elite = max(1, int(round(elite_frac * batch)))
    uniform = mask / mask.sum(-1, keepdims=True)

    def init(key):
        return {"probs": uniform}

    def ask(key, state):
        return sample_categorical(key, state["probs"], batch), state

    def tell(state, indices, rewards):
        order = jnp.argsort(-rewards)  # -inf last; stable
        elite = indices[order[:n_elite]]  # (E, P)
        onehot = jax.nn.one_hot(elite, mask.shape[1])  # (E, P, max_n)
        freq = onehot.mean(0)
        probs = (1 - smoothing) * state["probs"] + smoothing * freq
        probs = jnp.where(mask, jnp.maximum(probs, min_prob), 0.0)
        return {"probs": probs / probs.sum(-1, keepdims=True)}

    return Strategy("cem", init, ask, tell)
