"""CMA-ES (evosax) over the continuous relaxation of the index lattice.

Each parameter's index range ``[0, n_p - 1]`` is scaled to ``[0, 1]``; a candidate is rounded
to the nearest index (clipped into range). evosax minimises, so it sees ``-reward``; a -inf
reward (NaN rollout, beyond budget) becomes a large finite penalty.
"""

import jax
import jax.numpy as jnp

from jaxfalsify.search.base import Strategy

PENALTY = 1e3


def make(shape: tuple[int, ...], batch: int, std_init: float = 0.3) -> Strategy:
    from evosax.algorithms import CMA_ES

    P = len(shape)
    span = jnp.asarray(shape, jnp.float32) - 1
    es = CMA_ES(population_size=batch, solution=jnp.zeros(P))
    params = es.default_params.replace(std_init=std_init)

    def to_indices(x):
        return jnp.clip(jnp.rint(x * span), 0, span).astype(jnp.int32)

    def init(key):
        return {"es": es.init(key, jnp.full((P,), 0.5), params),
                "pop": jnp.zeros((batch, P)), "key": key}

    def ask(key, state):
        k_ask, k_tell = jax.random.split(key)
        pop, es_state = es.ask(k_ask, state["es"], params)
        return to_indices(pop), {"es": es_state, "pop": pop, "key": k_tell}

    def tell(state, indices, rewards):
        fitness = jnp.where(jnp.isfinite(rewards), -rewards, PENALTY)
        es_state, _ = es.tell(state["key"], state["pop"], fitness, state["es"], params)
        return {**state, "es": es_state}

    return Strategy("cmaes", init, ask, tell)
