"""Crude Monte Carlo: every concrete scenario drawn uniformly at random (the paper's comparator)."""

from jaxfalsify.search.base import Strategy, sample_uniform


def make(shape: tuple[int, ...], batch: int) -> Strategy:
    def init(key):
        return ()

    def ask(key, state):
        return sample_uniform(key, shape, batch), state

    def tell(state, indices, rewards):
        return state

    return Strategy("random", init, ask, tell)
