"""Exhaustive enumeration of the space in a seeded random order (without replacement).

After ``size`` evaluations every concrete scenario has been seen exactly once; further asks
wrap around. The order is a ``jax.random.permutation`` of the scenario numbers held in the
state, so spaces of up to ``MAX_SIZE`` scenarios are supported.
"""

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.search.base import Strategy

MAX_SIZE = 20_000_000


def make(shape: tuple[int, ...], batch: int) -> Strategy:
    size = int(np.prod(shape))
    if size > MAX_SIZE:
        raise ValueError(f"strategy 'grid' supports spaces of up to {MAX_SIZE} scenarios "
                         f"(this one has {size})")
    radices = np.cumprod((1,) + tuple(shape[::-1]))[:-1][::-1].astype(np.int64)

    def init(key):
        return {"order": jax.random.permutation(key, size).astype(jnp.int32),
                "pos": jnp.int32(0)}

    def ask(key, state):
        flat = state["order"][(state["pos"] + jnp.arange(batch)) % size]
        idx = jnp.stack([(flat // int(r)) % n for r, n in zip(radices, shape)], axis=-1)
        return idx.astype(jnp.int32), {**state, "pos": (state["pos"] + batch) % size}

    def tell(state, indices, rewards):
        return state

    return Strategy("grid", init, ask, tell)
