"""REINFORCE on the LSTM controller (paper Section II-A, Eq. 2-3), as a search strategy.

Loss = -sum over the batch of log pi(a) * R (Eq. 2), minimised with Adam (optax), i.e. gradient
ascent on the expected reward (Eq. 3). Each episode's input is the previous episode's action
(the paper's "state"); ``chains`` independent chains of previous actions run side by side, each
``batch / chains`` episodes long per update.

Registry entries (``jaxfalsify.search``):

* ``reinforce/paper`` — the original code: 25 episodes per update in one chain, Adam lr 0.01,
  the loss summed and scaled by alpha = 1e-4, epsilon-random exploration (a uniformly random
  action with probability eps; eps starts at 1.0, x0.995 every 4 episodes, floor 0.01, forced
  to 0 from episode 2000), raw reward, no baseline; the paper ran 4000 episodes.
* ``reinforce/factorised`` — the same controller with our training: 50 episodes per update
  as 50 parallel chains, normalised advantages (signal minus the batch mean, over the batch
  standard deviation) of the shaped signal (:func:`jaxfalsify.search.base.shaped_signal`), an
  entropy bonus, Adam lr 0.02, no epsilon exploration.

(``reinforce/default`` is the batched mixture controller of :mod:`jaxfalsify.search.batched`,
``reinforce/screened`` the autoregressive controller of :mod:`jaxfalsify.search.reinforce_ar`.)

Evaluations the campaign marks -inf (NaN rollouts, beyond the budget) get zero weight.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import optax

from jaxfalsify.base import pytree
from jaxfalsify.search import controller
from jaxfalsify.search.base import (
    Strategy,
    categorical_from_uniform,
    resolve_signal,
    sample_uniform,
    uniform,
    uniform_indices,
)

__all__ = ["epsilon", "Reinforce", "ReinforceParams", "ReinforceState"]


@pytree.dataclass
class ReinforceParams:
    lr: float = 0.02  # Adam learning rate
    alpha: float = 1.0  # loss scale (the original's gradient scale, 1e-4)
    entropy: float = 0.01  # entropy bonus coefficient (normalised advantages only)
    eps_start: float = 0.0  # epsilon-random exploration: probability at episode 0
    eps_decay: float = 1.0  # factor every eps_every episodes
    eps_every: float = 1.0  # episodes between decays
    eps_floor: float = 0.0  # lowest probability
    eps_off_after: float = 0.0  # episode from which eps = 0

    RANGES = {"lr": "[0, 10]", "alpha": "[0, inf)", "entropy": "[0, inf)",
              "eps_start": "[0, 1]", "eps_decay": "[0, 1]", "eps_every": "(0, inf)",
              "eps_floor": "[0, 1]", "eps_off_after": "[0, inf)"}


@pytree.dataclass
class ReinforceState:
    params: dict  # controller weights (see controller.init)
    opt: object  # Adam's moments (optax.scale_by_adam)
    prev: jax.Array  # (chains, P) int32, each chain's previous action
    inputs: jax.Array  # (B, P) float32, the controller inputs of the last ask
    episode: jax.Array  # () int32, episodes told so far


def epsilon(episode: jax.Array, p: ReinforceParams) -> jax.Array:
    """Exploration probability at a global episode number (0-based)."""
    eps = jnp.maximum(p.eps_start * p.eps_decay ** jnp.floor(episode / p.eps_every),
                      p.eps_floor)
    return jnp.where(episode >= p.eps_off_after, 0.0, eps)


@dataclasses.dataclass(frozen=True)
class Reinforce(Strategy):
    """Static: ``hidden`` LSTM units, ``chains`` (``batch % chains == 0``), ``advantage``
    (``reward``: raw and summed, the paper; ``normalised``: standardised within the batch)."""

    hidden: int = 32
    chains: int = 0  # 0: one chain per episode of the batch
    advantage: str = "normalised"
    signal: str | Callable = "reward"  # or "shaped", or a function: base.resolve_signal

    Params = ReinforceParams
    RANGES = {"hidden": "[1, 1024]"}  # static sizes (see AutoregressiveReinforce.RANGES)

    def __post_init__(self):
        resolve_signal(self.signal)  # a one-line error on a bad one
        if self.advantage not in ("reward", "normalised"):
            raise ValueError(f"advantage must be 'reward' or 'normalised' "
                             f"(got {self.advantage!r})")
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1 (got {self.hidden})")
        if self.n_chains < 1 or self.batch % self.n_chains:
            raise ValueError(f"chains={self.chains} must divide batch={self.batch}")

    @property
    def n_chains(self) -> int:
        return self.chains or self.batch

    def _logits(self, weights, x):
        return controller.logits(weights, x, self.shape)

    def init(self, key, params):
        k_model, k_prev = jax.random.split(key)
        weights = controller.init(k_model, self.shape, self.hidden)
        return ReinforceState(weights, optax.scale_by_adam().init(weights),
                              sample_uniform(k_prev, self.shape, self.n_chains),
                              jnp.zeros((self.batch, self.n_params)), jnp.int32(0))

    def probs(self, state) -> jax.Array:
        """The controller's per-parameter probabilities ``(P, max_n)`` given chain 0's last
        action (what the next ask samples from)."""
        x = controller.normalise(state.prev[0], self.shape)
        return jax.nn.softmax(self._logits(state.params, x), axis=-1)

    def ask(self, key, state, params):
        C, P = self.n_chains, self.n_params

        def one(carry, u):
            prev, j = carry  # u: (C, 2P + 1) uniforms: policy, exploration, the coin
            x = controller.normalise(prev, self.shape)  # (C, P)
            logits = jax.vmap(lambda xi: self._logits(state.params, xi))(x)
            sampled = categorical_from_uniform(u[:, :P], jax.nn.softmax(logits, axis=-1))
            episode = state.episode + j * C + jnp.arange(C)
            explore = u[:, -1] < epsilon(episode, params)
            action = jnp.where(explore[:, None], uniform_indices(u[:, P:2 * P], self.shape),
                               sampled)
            return (action, j + 1), (x, action)

        # one draw for the whole ask (every jax.random call site costs compile time)
        u = uniform(key, (self.batch // C, C, 2 * P + 1))
        (last, _), (xs, actions) = jax.lax.scan(one, (state.prev, jnp.int32(0)), u)
        # (per_chain, chains, .) -> episode order: step j of every chain, then step j + 1
        return actions.reshape(self.batch, P), dataclasses.replace(
            state, prev=last, inputs=xs.reshape(self.batch, P))

    def tell(self, key, state, indices, rewards, params):
        ok = jnp.isfinite(rewards)
        r = jnp.where(ok, rewards, 0.0)
        if self.advantage == "normalised":
            n = jnp.maximum(jnp.sum(ok), 1)
            mean = jnp.sum(r) / n
            std = jnp.sqrt(jnp.sum(jnp.where(ok, (r - mean) ** 2, 0.0)) / n)
            r = (r - mean) / (std + 1e-8)
        weights = jnp.where(ok, r, 0.0)

        def loss(w):
            logits = jax.vmap(lambda x: self._logits(w, x))(state.inputs)
            logp = jax.vmap(controller.action_log_prob)(logits, indices)
            if self.advantage == "reward":
                return -params.alpha * jnp.sum(logp * weights)  # the original: summed, scaled
            ent = jnp.mean(jax.vmap(controller.entropy)(logits))
            return -params.alpha * jnp.mean(logp * weights) - params.entropy * ent

        grads = jax.grad(loss)(state.params)
        updates, opt = optax.scale_by_adam().update(grads, state.opt, state.params)
        updates = jax.tree.map(lambda u: -params.lr * u, updates)
        return dataclasses.replace(state, params=optax.apply_updates(state.params, updates),
                                   opt=opt, episode=state.episode + self.batch)
