"""Simulated annealing with ``batch`` independent chains over the index lattice.

Each chain proposes a neighbour of its current scenario: one parameter of more than one value,
chosen at random, moves by a random step of +-1..``max_step`` indices (clipped), or with probability
``p_restart`` is redrawn uniformly. Metropolis acceptance with temperature ``t0 * decay^k``
at update k (rewards are in the paper's units, about -0.06..0.27).
"""

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.search.base import (
    Strategy,
    resolve_signal,
    sample_uniform,
    uniform,
    uniform_indices,
)

__all__ = ["Anneal", "AnnealParams", "AnnealState"]


@pytree.dataclass
class AnnealParams:
    t0: float = 0.05  # initial temperature (reward units)
    decay: float = 0.8  # temperature factor per update
    p_restart: float = 0.1  # probability of a uniformly random proposal
    max_step: float = 2.0  # largest index move of one parameter

    RANGES = {"t0": "[0, inf)", "decay": "[0, 1]", "p_restart": "[0, 1]", "max_step": "[1, inf)"}


@pytree.dataclass
class AnnealState:
    current: jax.Array  # (B, P) int32, each chain's scenario
    reward: jax.Array  # (B,) float32, its reward (-inf before the first tell)
    temp: jax.Array  # () float32
    started: jax.Array  # () bool, False until the first tell


@dataclasses.dataclass(frozen=True)
class Anneal(Strategy):
    """Static: ``signal``, what it learns from: ``shaped`` (default,
    :func:`jaxfalsify.search.base.shaped_signal`) or ``reward`` (the paper's reward)."""

    signal: str | Callable = "shaped"

    Params = AnnealParams

    def __post_init__(self):
        resolve_signal(self.signal)  # a one-line error on a bad one

    def init(self, key, params):
        return AnnealState(sample_uniform(key, self.shape, self.batch),
                           jnp.full((self.batch,), -jnp.inf), jnp.float32(params.t0),
                           jnp.bool_(False))

    def ask(self, key, state, params):
        B, P = self.batch, self.n_params
        sizes = jnp.asarray(self.shape, jnp.int32)
        u = uniform(key, (B, P + 4))  # one draw: parameter, step, sign, restart, fresh values
        # the parameter moved: one with more than one value (moving another repeats the
        # chain's scenario); the k-th of them for u in [k/M, (k+1)/M)
        movable = [p for p, n in enumerate(self.shape) if n > 1] or [0]
        k = jnp.minimum(jnp.floor(u[:, 0] * len(movable)), len(movable) - 1).astype(jnp.int32)
        which = jnp.asarray(movable, jnp.int32)[k]
        # at most the widest parameter's span (a huge max_step would overflow int32)
        top = jnp.clip(jnp.round(params.max_step), 1.0, max(max(self.shape) - 1, 1))
        step = (1 + jnp.minimum(jnp.floor(u[:, 1] * top), top - 1)).astype(jnp.int32)
        step = jnp.where(u[:, 2] < 0.5, step, -step)
        moved = state.current + jax.nn.one_hot(which, P, dtype=jnp.int32) * step[:, None]
        moved = jnp.clip(moved, 0, sizes - 1)
        fresh = uniform_indices(u[:, 4:], self.shape)
        restart = (u[:, 3] < params.p_restart)[:, None]
        prop = jnp.where(restart, fresh, moved)
        return jnp.where(state.started, prop, state.current), state  # first ask: the starts

    def tell(self, key, state, indices, rewards, params):
        u = jax.random.uniform(key, (self.batch,))
        gain = rewards - state.reward
        accept = (gain >= 0) | (u < jnp.exp(jnp.where(jnp.isfinite(gain), gain, -jnp.inf)
                                           / state.temp))
        accept = (accept & jnp.isfinite(rewards)) | ~jnp.isfinite(state.reward)
        return AnnealState(jnp.where(accept[:, None], indices, state.current),
                           jnp.where(accept, rewards, state.reward),
                           state.temp * params.decay, jnp.bool_(True))
