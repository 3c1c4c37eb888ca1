"""Crude Monte Carlo: every concrete scenario drawn uniformly at random (the paper's comparator)."""

import dataclasses

from jaxfalsify.search.base import Strategy, sample_uniform

__all__ = ["RandomSearch"]


@dataclasses.dataclass(frozen=True)
class RandomSearch(Strategy):
    def init(self, key, params):
        return ()

    def ask(self, key, state, params):
        return sample_uniform(key, self.shape, self.batch), state

    def tell(self, key, state, indices, rewards, params):
        return state
