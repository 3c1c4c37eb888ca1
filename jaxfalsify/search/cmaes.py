"""CMA-ES (evosax) over the continuous relaxation of the index lattice.

Each parameter's index range ``[0, n_p - 1]`` is scaled to ``[0, 1]``; a candidate is rounded
to the nearest index (clipped into range). evosax minimises, so it sees ``-reward``; a -inf
reward (NaN rollout, beyond budget) becomes a large finite penalty.
"""

import dataclasses

import jax
import jax.numpy as jnp

from jaxfalsify import pytree
from jaxfalsify.search.base import Strategy

PENALTY = 1e3


@pytree.dataclass
class CMAESParams:
    std_init: float = 0.3  # initial step size, in units of each parameter's index range


@pytree.dataclass
class CMAESState:
    es: object  # evosax's CMA-ES state
    pop: jax.Array  # (B, P) float32, the last asked population (evosax's tell needs it)


@dataclasses.dataclass(frozen=True)
class CMAES(Strategy):
    Params = CMAESParams

    def _es(self):
        from evosax.algorithms import CMA_ES

        return CMA_ES(population_size=self.batch, solution=jnp.zeros(self.n_params))

    def _es_params(self, es, params):
        return es.default_params.replace(std_init=params.std_init)

    def _indices(self, x):
        span = jnp.asarray(self.shape, jnp.float32) - 1
        return jnp.clip(jnp.rint(x * span), 0, span).astype(jnp.int32)

    def init(self, key, params):
        es = self._es()
        state = es.init(key, jnp.full((self.n_params,), 0.5), self._es_params(es, params))
        return CMAESState(state, jnp.zeros((self.batch, self.n_params)))

    def ask(self, key, state, params):
        es = self._es()
        pop, es_state = es.ask(key, state.es, self._es_params(es, params))
        return self._indices(pop), CMAESState(es_state, pop)

    def tell(self, key, state, indices, rewards, params):
        es = self._es()
        fitness = jnp.where(jnp.isfinite(rewards), -rewards, PENALTY)
        es_state, _ = es.tell(key, state.pop, fitness, state.es, self._es_params(es, params))
        return CMAESState(es_state, state.pop)
