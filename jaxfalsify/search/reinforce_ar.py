"""REINFORCE on an autoregressive LSTM controller: ``reinforce/default``.

The paper's method (a recurrent controller trained by the policy gradient, Eq. 2-3, with Adam),
made strong where the original struggles (a factorised policy, few updates, a reward that is
flat until the first collision):

* **autoregressive controller** (:mod:`jaxfalsify.search.autoregressive`): one LSTM step per
  parameter, conditioned on the values already chosen, heads = free logits + a Gaussian bump
  over the value ranks;
* **many small updates**: ``learners`` independent controllers (own weights, own Adam moments)
  share every batch, ``batch / learners`` scenarios each, so a 4000-evaluation budget at
  batch 32 over 4 learners makes 125 updates of each;
* **baseline**: centred ranks of the learning signal within each learner's share of the batch
  (``advantage="rank"``, scale-free and robust to the jump a collision makes) or the signal
  standardised (``"normalised"``);
* **dense signal**: with ``signal="shaped"`` (default) a learner ranks its scenarios by
  :func:`jaxfalsify.search.base.shaped_signal`: STL robustness (min distance - epsilon) while
  there is no collision, the paper's reward among collisions (collisions always rank first);
* **entropy**: a bonus ``entropy`` on the per-step entropies keeps a learner exploring until
  it has seen a collision; then ``entropy_found`` (default 0) lets it concentrate;
* optionally ``uniform_mix``: that share of the scenarios drawn uniformly at random (they do
  not enter the gradient).

Evaluations marked -inf (NaN rollouts, beyond the budget) get zero weight.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import optax

from jaxfalsify import pytree
from jaxfalsify.search import autoregressive as ar
from jaxfalsify.search.base import (Strategy, centred_ranks, check_signal, shaped_signal,
                                    uniform, uniform_indices)


@pytree.dataclass
class ARParams:
    lr: float = 0.05  # Adam learning rate
    entropy: float = 0.02  # entropy bonus while the learner has seen no collision
    entropy_found: float = 0.0  # entropy bonus once it has
    uniform_mix: float = 0.0  # share of uniformly random scenarios (not learnt from)


@pytree.dataclass
class ARState:
    weights: dict  # controller weights, leading axis = learners
    opt: object  # Adam's moments, per learner
    seen: jax.Array  # (L,) bool, the learner has had a collision
    explored: jax.Array  # (B,) bool, which scenarios of the last ask were uniform draws
    told: jax.Array  # () int32, updates so far


@dataclasses.dataclass(frozen=True)
class AutoregressiveReinforce(Strategy):
    """Static: ``hidden`` LSTM units, ``learners`` (divides ``batch``), ``advantage``
    (``rank`` or ``normalised``), ``signal`` (``shaped`` or ``reward``)."""

    hidden: int = 32
    learners: int = 4
    advantage: str = "rank"
    signal: str = "shaped"

    Params = ARParams

    def __post_init__(self):
        if self.advantage not in ("rank", "normalised"):
            raise ValueError(f"advantage must be 'rank' or 'normalised' "
                             f"(got {self.advantage!r})")
        check_signal(self.signal)
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1 (got {self.hidden})")
        if self.learners < 1 or self.batch % self.learners:
            raise ValueError(f"learners={self.learners} must divide batch={self.batch}")

    @property
    def per_learner(self) -> int:
        return self.batch // self.learners

    def init(self, key, params):
        keys = jax.random.split(key, self.learners)
        weights = jax.vmap(lambda k: ar.init(k, self.shape, self.hidden))(keys)
        opt = jax.vmap(optax.scale_by_adam().init)(weights)
        return ARState(weights, opt, jnp.zeros(self.learners, bool),
                       jnp.zeros(self.batch, bool), jnp.int32(0))

    def probs(self, state, learner: int = 0) -> jax.Array:
        """``(P, max_n)``: each parameter's probabilities given the most likely values of the
        parameters before it, for one learner (row 0 is the first parameter's marginal)."""
        w = jax.tree.map(lambda x: x[learner], state.weights)

        def step_fn(p, logits, _):
            return jnp.argmax(logits).astype(jnp.int32), jax.nn.softmax(logits)

        return ar._scan(w, self.shape, step_fn, jnp.zeros(self.n_params))

    def ask(self, key, state, params):
        L, b, P = self.learners, self.per_learner, self.n_params
        u = uniform(key, (L, b, 2 * P + 1))  # one draw: policy, uniform values, the coin
        sampled = jax.vmap(lambda w, ul: jax.vmap(
            lambda ui: ar.sample(w, ui, self.shape))(ul))(state.weights, u[..., :P])
        explored = u[..., -1] < params.uniform_mix
        idx = jnp.where(explored[..., None], uniform_indices(u[..., P:2 * P], self.shape),
                        sampled)
        return idx.reshape(self.batch, P), dataclasses.replace(
            state, explored=explored.reshape(self.batch))

    def tell(self, key, state, indices, rewards, params):
        return self._update(state, indices, rewards, state.seen, params)

    def tell_outcome(self, key, state, indices, rewards, robustness, collision, params):
        signal = (shaped_signal(rewards, robustness, collision) if self.signal == "shaped"
                  else rewards)
        hit = jnp.any(collision.reshape(self.learners, -1), axis=-1)
        return self._update(state, indices, signal, state.seen | hit, params)

    def _update(self, state, indices, signal, seen, params):
        L, b = self.learners, self.per_learner
        sig = signal.reshape(L, b)
        ok = jnp.isfinite(sig) & ~state.explored.reshape(L, b)
        if self.advantage == "rank":
            adv = centred_ranks(sig, ok)
        else:
            x = jnp.where(ok, sig, 0.0)
            n = jnp.maximum(jnp.sum(ok, -1, keepdims=True), 1)
            mean = jnp.sum(x, -1, keepdims=True) / n
            std = jnp.sqrt(jnp.sum(jnp.where(ok, (x - mean) ** 2, 0.0), -1, keepdims=True) / n)
            adv = jnp.where(ok, (x - mean) / (std + 1e-8), 0.0)
        beta = jnp.where(seen, params.entropy_found, params.entropy)  # (L,)
        acts = indices.reshape(L, b, self.n_params)

        def loss(w, a, adv_l, ok_l, beta_l):
            lp, ent = jax.vmap(lambda ai: ar.log_prob_and_entropy(w, ai, self.shape))(a)
            n = jnp.maximum(jnp.sum(ok_l), 1)
            return -(jnp.sum(adv_l * lp) + beta_l * jnp.sum(jnp.where(ok_l, ent, 0.0))) / n

        grads = jax.vmap(jax.grad(loss))(state.weights, acts, adv, ok, beta)
        updates, opt = jax.vmap(optax.scale_by_adam().update)(grads, state.opt, state.weights)
        weights = jax.tree.map(lambda w, u: w - params.lr * u, state.weights, updates)
        return dataclasses.replace(state, weights=weights, opt=opt, seen=seen,
                                   told=state.told + 1)
