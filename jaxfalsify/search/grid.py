"""Exhaustive enumeration of the space in a seeded random order (without replacement).

After ``size`` evaluations every concrete scenario has been seen exactly once; further asks
wrap around. The order is a ``jax.random.permutation`` of the scenario numbers held in the
state, so spaces of up to ``MAX_SIZE`` scenarios are supported.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.base import pytree
from jaxfalsify.search.base import Strategy

__all__ = ["Grid", "GridState"]

MAX_SIZE = 20_000_000


@pytree.dataclass
class GridState:
    order: jax.Array  # (size,) int32, a permutation of the scenario numbers
    pos: jax.Array  # () int32, next position in the order


@dataclasses.dataclass(frozen=True)
class Grid(Strategy):
    BATCH_AT_MOST_SIZE = True  # search.make's default batch shrinks to a smaller space's size

    def __post_init__(self):
        size = int(np.prod(self.shape))
        if size > MAX_SIZE:
            raise ValueError(f"strategy 'grid' supports spaces of up to {MAX_SIZE} scenarios "
                             f"(this one has {size})")
        if self.batch > size:
            raise ValueError(f"batch={self.batch} exceeds the space's {size} scenarios "
                             "(strategy 'grid' would repeat scenarios within one batch)")

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def init(self, key, params):
        return GridState(jax.random.permutation(key, self.size).astype(jnp.int32),
                         jnp.int32(0))

    def ask(self, key, state, params):
        flat = state.order[(state.pos + jnp.arange(self.batch)) % self.size]
        radices = np.cumprod((1,) + tuple(self.shape[::-1]))[:-1][::-1]
        idx = jnp.stack([(flat // int(r)) % n for r, n in zip(radices, self.shape)], axis=-1)
        return idx.astype(jnp.int32), GridState(state.order,
                                                (state.pos + self.batch) % self.size)

    def tell(self, key, state, indices, rewards, params):
        return state
