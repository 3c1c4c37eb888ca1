"""REINFORCE on the LSTM controller (paper Section II-A, Eq. 2-3), as a search strategy.

Loss = -sum over the batch of log pi(a) * R (Eq. 2), minimised with Adam (optax), i.e. gradient
ascent on the expected reward (Eq. 3). Each episode's input is the previous episode's action
(the paper's "state"); ``chains`` independent chains of previous actions run side by side, each
``batch / chains`` episodes long per update.

Presets:

* ``paper`` — the original code: 25 episodes per update in one chain, Adam lr 0.01, the loss
  scaled by alpha = 1e-4, epsilon-random exploration (a uniformly random action with
  probability eps; eps starts at 1.0, x0.995 every 4 episodes, floor 0.01, forced to 0 from
  episode 2000), no baseline; the paper ran 4000 episodes.
* ``default`` — ours: 250 episodes per update as 250 parallel chains, normalised advantages
  (reward minus the batch mean, over the batch standard deviation), an entropy bonus, Adam
  lr 0.02, no epsilon exploration. Same reward.

Evaluations the driver marks -inf (NaN rollouts, beyond the budget) get zero weight.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import nnx

from jaxfalsify import policy
from jaxfalsify.search.base import Strategy, sample_uniform


class Preset(NamedTuple):
    batch: int  # episodes per update
    chains: int  # parallel previous-action chains (batch % chains == 0)
    lr: float  # Adam learning rate
    alpha: float  # loss scale (the original's gradient scale)
    eps_start: float  # epsilon-random exploration
    eps_decay: float
    eps_every: int  # episodes between decays
    eps_floor: float
    eps_off_after: int  # episode from which eps = 0
    advantage: str  # 'reward' (raw, the paper) or 'normalised'
    entropy: float  # entropy bonus coefficient
    hidden: int = 32


PRESETS: dict[str, Preset] = {
    "paper": Preset(batch=25, chains=1, lr=0.01, alpha=1e-4, eps_start=1.0, eps_decay=0.995,
                    eps_every=4, eps_floor=0.01, eps_off_after=2000, advantage="reward",
                    entropy=0.0),
    "default": Preset(batch=250, chains=250, lr=0.02, alpha=1.0, eps_start=0.0, eps_decay=1.0,
                      eps_every=1, eps_floor=0.0, eps_off_after=0, advantage="normalised",
                      entropy=0.01),
}


def epsilon(episode: jax.Array, p: Preset) -> jax.Array:
    """Exploration probability at a global episode number (0-based)."""
    eps = jnp.maximum(p.eps_start * p.eps_decay ** (episode // p.eps_every), p.eps_floor)
    return jnp.where(episode >= p.eps_off_after, 0.0, eps)


def get_preset(name: str, batch: int | None = None) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset '{name}' (one of {', '.join(PRESETS)})")
    p = PRESETS[name]
    if batch is not None and batch != p.batch:
        chains = 1 if p.chains == 1 else batch
        p = p._replace(batch=batch, chains=chains)
    return p


def make(shape: tuple[int, ...], batch: int | None = None, preset: str = "default") -> Strategy:
    """REINFORCE strategy for a space of the given shape (``batch`` overrides the preset's)."""
    p = get_preset(preset, batch)
    shape = tuple(int(n) for n in shape)
    P = len(shape)
    per_chain = p.batch // p.chains
    graphdef, _ = nnx.split(policy.Controller(shape, p.hidden, rngs=nnx.Rngs(0)))
    tx = optax.adam(p.lr)

    def apply(params, x):
        return nnx.merge(graphdef, params)(x)

    def init(key):
        k_model, k_prev = jax.random.split(key)
        _, params = nnx.split(policy.Controller(shape, p.hidden,
                                                rngs=nnx.Rngs(params=k_model)))
        return {"params": params, "opt": tx.init(params),
                "prev": sample_uniform(k_prev, shape, p.chains),
                "inputs": jnp.zeros((p.batch, P)), "episode": jnp.int32(0)}

    def ask(key, state):
        def one(carry, k):
            prev, j = carry
            k_pol, k_rand, k_eps = jax.random.split(k, 3)
            x = policy.normalise(prev, shape)  # (chains, P)
            logits = jax.vmap(lambda xi: apply(state["params"], xi))(x)
            sampled = jax.random.categorical(k_pol, logits, axis=-1).astype(jnp.int32)
            episode = state["episode"] + j * p.chains + jnp.arange(p.chains)
            explore = jax.random.uniform(k_eps, (p.chains,)) < epsilon(episode, p)
            action = jnp.where(explore[:, None], sample_uniform(k_rand, shape, p.chains),
                               sampled)
            return (action, j + 1), (x, action)

        (last, _), (xs, actions) = jax.lax.scan(one, (state["prev"], jnp.int32(0)),
                                                jax.random.split(key, per_chain))
        # (per_chain, chains, .) -> episode order: step j of every chain, then step j + 1
        actions = actions.reshape(p.batch, P)
        return actions, {**state, "prev": last, "inputs": xs.reshape(p.batch, P)}

    def loss_fn(params, inputs, actions, weights):
        logits = jax.vmap(lambda x: apply(params, x))(inputs)
        logp = jax.vmap(policy.action_log_prob)(logits, actions)
        ent = jnp.mean(jax.vmap(policy.entropy)(logits))
        if p.advantage == "reward":
            return -p.alpha * jnp.sum(logp * weights)  # the original: summed, scaled
        return -p.alpha * jnp.mean(logp * weights) - p.entropy * ent

    def tell(state, indices, rewards):
        ok = jnp.isfinite(rewards)
        r = jnp.where(ok, rewards, 0.0)
        if p.advantage == "normalised":
            n = jnp.maximum(jnp.sum(ok), 1)
            mean = jnp.sum(r) / n
            std = jnp.sqrt(jnp.sum(jnp.where(ok, (r - mean) ** 2, 0.0)) / n)
            r = (r - mean) / (std + 1e-8)
        weights = jnp.where(ok, r, 0.0)
        grads = jax.grad(loss_fn)(state["params"], state["inputs"], indices, weights)
        updates, opt = tx.update(grads, state["opt"], state["params"])
        return {**state, "params": optax.apply_updates(state["params"], updates), "opt": opt,
                "episode": state["episode"] + p.batch}

    return Strategy("reinforce", init, ask, tell)


def policy_probs(strategy_state, shape: tuple[int, ...], preset: str = "default") -> jax.Array:
    """The controller's per-parameter probabilities ``(P, max_n)`` given its last action."""
    p = get_preset(preset)
    graphdef, _ = nnx.split(policy.Controller(shape, p.hidden, rngs=nnx.Rngs(0)))
    x = policy.normalise(strategy_state["prev"][0], shape)
    return jax.nn.softmax(nnx.merge(graphdef, strategy_state["params"])(x), axis=-1)
