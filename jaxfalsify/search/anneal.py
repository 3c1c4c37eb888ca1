"""Simulated annealing with ``batch`` independent chains over the index lattice.

Each chain proposes a neighbour of its current scenario: one parameter, chosen at random,
moves by a random step of +-1..``max_step`` indices (clipped), or with probability
``p_restart`` is redrawn uniformly. Metropolis acceptance with temperature ``t0 * decay^k``
at update k (rewards are in the paper's units, about -0.06..0.27).
"""

import jax
import jax.numpy as jnp

from jaxfalsify.search.base import Strategy, sample_uniform


def make(shape: tuple[int, ...], batch: int, t0: float = 0.05, decay: float = 0.8,
         max_step: int = 2, p_restart: float = 0.1) -> Strategy:
    sizes = jnp.asarray(shape, jnp.int32)
    P = len(shape)

    def init(key):
        return {"current": sample_uniform(key, shape, batch),
                "reward": jnp.full((batch,), -jnp.inf), "temp": jnp.float32(t0),
                "u": jnp.zeros((batch,)), "started": jnp.bool_(False)}

    def ask(key, state):
        k1, k2, k3, k4, k5, k6 = jax.random.split(key, 6)
        which = jax.random.randint(k1, (batch,), 0, P)
        step = jax.random.randint(k2, (batch,), 1, max_step + 1)
        step = jnp.where(jax.random.bernoulli(k3, 0.5, (batch,)), step, -step)
        moved = state["current"] + jax.nn.one_hot(which, P, dtype=jnp.int32) * step[:, None]
        moved = jnp.clip(moved, 0, sizes - 1)
        fresh = sample_uniform(k4, shape, batch)
        restart = jax.random.bernoulli(k5, p_restart, (batch,))[:, None]
        prop = jnp.where(restart, fresh, moved)
        prop = jnp.where(state["started"], prop, state["current"])  # first ask: the starts
        return prop, {**state, "u": jax.random.uniform(k6, (batch,))}

    def tell(state, indices, rewards):
        u = state["u"]  # drawn in ask: tell takes no key
        gain = rewards - state["reward"]
        accept = (gain >= 0) | (u < jnp.exp(jnp.where(jnp.isfinite(gain), gain, -jnp.inf)
                                           / state["temp"]))
        accept = (accept & jnp.isfinite(rewards)) | ~jnp.isfinite(state["reward"])
        return {**state,
                "current": jnp.where(accept[:, None], indices, state["current"]),
                "reward": jnp.where(accept, rewards, state["reward"]),
                "temp": state["temp"] * decay, "started": jnp.bool_(True)}

    return Strategy("anneal", init, ask, tell)
