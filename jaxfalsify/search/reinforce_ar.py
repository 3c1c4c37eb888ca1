"""REINFORCE on an autoregressive LSTM controller: ``reinforce/screened``.

One concern: the ``reinforce/screened`` strategy, composed of pieces that live apart: its
controller (:mod:`jaxfalsify.search.autoregressive`), the memory of evaluated and of the best
distinct scenarios (:class:`~jaxfalsify.search.memory.NoRepeats`,
:func:`~jaxfalsify.search.memory.top_distinct`), the GP screen
(:class:`~jaxfalsify.search.surrogate.GPScreen`), the advantage and the learning signal
(functions: :func:`~jaxfalsify.search.base.resolve_advantage`,
:func:`~jaxfalsify.search.base.resolve_signal`). Its options say which pieces are on
(:attr:`AutoregressiveReinforce.no_repeats`, :attr:`AutoregressiveReinforce.screen`).

The paper's method (a recurrent controller trained by the policy gradient, Eq. 2-3, with
Adam), made strong where the original struggles: a factorised policy, a handful of updates,
a reward that is flat until the first collision, failures that are rare.

* **Autoregressive controller** (:mod:`jaxfalsify.search.autoregressive`): one LSTM step per
  parameter, conditioned on the values already chosen (the NAS controller the paper's
  controller descends from); each head is free logits plus a Gaussian bump over the value
  ranks, so what is learnt about one value carries to its neighbours.
* **Anchored draws** (``anchored``): like the paper's controller, which reads the previous
  action, most draws are conditioned on an *anchor*, one of the best scenarios found so far
  (``queue`` of them, distinct, best first; the k-th best picked with weight
  ``anchor_decay^k``; ``anchor_decay_found`` once the learner has a collision, so it
  converges on the best ones). An anchored head keeps the anchor's value with a learnt *stay*
  probability and otherwise moves by a learnt offset and width (starting at about one
  parameter moved per draw, 1.5 value steps wide, before ``zoom`` widens it): a learnt
  local move. ``global_share`` of
  the draws have no anchor (the controller's own distribution over the whole space);
  ``global_share_found`` once the learner has a collision (the default 0: every draw
  anchored, so the learner converges on the best region).
  REINFORCE trains both: which parameters to move, how far and where to, and where the good
  scenarios lie.
* **Multi-scale moves** (``zoom``): each anchored draw widens the learnt local move by a
  factor drawn log-uniformly between 1 and ``zoom`` of the parameter's range over the initial
  width (a parameter of 1000 values: 1.5 to 300 value steps), so big parameters are crossed
  in a few moves and small ones searched value by value. The factor is drawn from a known
  distribution that no weight changes, so the policy gradient conditions on it (kept per draw
  in ``zooms``) and stays unbiased.
* **Moves that partly stop at a bound** (``edge_mass``; 0 in this class, 0.2 in
  ``reinforce/screened``): that share of an anchored move's Gaussian mass beyond the first /
  last value goes to that value, the rest is renormalised inside the box (1: moves clipped to
  the box, as evolution strategies clip; 0: never). Helps where failures touch the box's faces
  (README: ``huge-aeb``, ``aeb-9e6``); a large share costs on interior failures (evaluations
  on the faces and corners), 0.2 does not measurably.
* **No repeats until a collision** (``resample``): a deterministic SUT gives the same outcome
  twice, so a repeated scenario wastes an evaluation. The controller draws ``resample``
  candidates per scenario it asks and takes the first ones not evaluated before (a ``memory``
  of 32-bit hashes of the evaluated scenarios) and not repeated within the batch, then uniform
  draws if too few are new. Once a learner has found a collision, a share ``repeat_found`` of
  its draws may repeat one of its own collisions (kept in its ``queue``; with no queue there
  is nothing to repeat), so it can converge on the best scenario (the paper's learning curve).
* **No signal, no step**: a learner whose batch gives it no advantage (every signal tied: a
  converged learner asking copies of its best) and no entropy bonus takes no optimizer step
  (Adam would otherwise step on its momentum and walk the policy off what it learnt).
* **Surrogate screening** (``surrogate``, off by default): until the learner has a
  collision, a Gaussian process (:mod:`jaxfalsify.search.surrogate`) fitted to its last
  ``surrogate`` evaluations and its queue of best scenarios picks which of the new candidates
  (``resample`` per asked scenario) are asked: by GP-BUCB, the highest ``mean + kappa * std``
  first, each further pick's std shrunk as if the earlier ones had been observed, so a batch
  spreads over the promising candidates. The GP's prior mean ``prior_mean`` (standard
  deviations from its data's mean; -0.5 in ``reinforce/screened``) expects unexplored regions
  somewhat worse than the average evaluation, so far-away uncertain candidates stop crowding
  out those beside a promising plateau. One length scale per parameter, refined by marginal
  likelihood: every parameter's in turn at each of the first updates (as many as the
  parameters that vary), then one parameter per update; with ``kernel="auto"`` (in
  ``reinforce/screened``) each refinement also chooses between the squared exponential and the
  Matern 5/2 correlation. The policy still proposes every candidate and learns from what is
  asked.
* **Baseline**: centred ranks of the learning signal within the batch (``advantage="rank"``:
  scale-free, robust to the jump a collision makes) or the signal standardised
  (``"normalised"``).
* **Dense signal**: with ``signal="shaped"`` (default) the learner ranks scenarios by
  :func:`jaxfalsify.search.base.shaped_signal`: STL robustness (min distance - epsilon) until
  a collision, the paper's reward among collisions (collisions always rank first); with
  ``ttc_weight`` > 0 (0.05 in ``reinforce/screened``) a near miss's robustness gains
  ``ttc_weight x min(TTC, 20 s)`` until the learner's first collision
  (:func:`jaxfalsify.search.base.near_miss_ttc`).
* **Entropy** bonus ``entropy`` on the per-step entropies while the learner has seen no
  collision, ``entropy_found`` after (faded linearly to 0 at ``entropy_until`` evaluations
  of the search when that is > 0: explore among the failures, then converge; 0.1 faded out
  at 2000 in ``reinforce/screened``); learning rate ``lr``, then ``lr_found``.
* ``learners`` independent controllers (own weights, Adam moments, queue) may share the batch.

Without ``anchored``/``resample`` this is a plain autoregressive REINFORCE learner. Evaluations
marked -inf (NaN rollouts, beyond the budget) get zero weight.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import optax

from jaxfalsify.base import pytree
from jaxfalsify.search import autoregressive as ar
from jaxfalsify.search import surrogate as gp
from jaxfalsify.search.base import (
    Strategy,
    categorical_from_uniform,
    near_miss_ttc,
    resolve_advantage,
    resolve_signal,
    uniform,
    uniform_indices,
)
from jaxfalsify.search.memory import (
    MemoryState,
    NoRepeats,
    equals_an_earlier,
    scenario_hash,
    top_distinct,
)

__all__ = ["AutoregressiveReinforce", "ARParams", "ARState"]


@pytree.dataclass
class ARParams:
    lr: float = 0.05  # Adam learning rate
    lr_found: float = -1.0  # learning rate once the learner has a collision (< 0: lr)
    entropy: float = 0.02  # entropy bonus while the learner has seen no collision
    entropy_found: float = 0.0  # entropy bonus once it has
    entropy_until: float = 0.0  # > 0: entropy_found falls linearly to 0 at this many
    # evaluations of the search (explore among the failures first, then converge)
    sigma_min: float = 0.05  # narrowest bump, as a fraction of a parameter's range (1e-4..1;
    # never narrower than half a value step)
    global_share: float = 0.25  # anchored: share of draws without an anchor
    global_share_found: float = -1.0  # the same once the learner has a collision (< 0: as
    # global_share)
    anchor_decay: float = 0.95  # anchored: the k-th best of the queue is picked ~ decay^k
    anchor_decay_found: float = -1.0  # the same once the learner has a collision (< 0: as
    # anchor_decay)
    repeat_found: float = 0.0  # once the learner has a collision: share of its draws that
    # may repeat one of its own collisions (queue entries that collided; needs queue >= 1)
    uniform_mix: float = 0.0  # share of uniformly random draws (not learnt from)
    edge_mass: float = 0.0  # anchored: share of a move's mass beyond a bound that stops at
    # the bound's value (1: clipped moves, as an evolution strategy clips; 0: renormalised
    # inside the box)
    edge_explore: float = 0.0  # share of a uniform draw's values put on a bound (the first
    # or last value; for failures on the box's faces)
    kappa: float = 1.0  # surrogate: candidates picked by GP mean + kappa * std (standardised)
    prior_mean: float = 0.0  # surrogate: the GP's prior mean, in standard deviations of the
    # signal from its mean over the GP's data (< 0: unexplored regions expected worse)
    zoom: float = 0.0  # anchored: multi-scale moves, the widest as a fraction of a
    # parameter's range (each draw's width is log-uniform between the learnt width and that
    # many times wider; 0: off)
    ttc_weight: float = 0.0  # near misses told apart by their minimum time-to-collision:
    # where the robustness is below ttc_below, the signal's robustness gains ttc_weight x
    # min(TTC, 20 s) [m per s] (base.near_miss_ttc; 0: off), for each learner until its
    # first collision (the paper's reward ranks what comes after)
    ttc_below: float = -0.5  # m of robustness (-0.5: the road users came within 0.5 m)

    # a negative *_found value means "as before the first collision"
    RANGES = {"lr": "[0, 10]", "entropy": "[0, inf)", "entropy_found": "[0, inf)",
              "entropy_until": "[0, inf)",
              "sigma_min": "[0.0001, 1]", "global_share": "[0, 1]",
              "global_share_found": "(-inf, 1]",
              "anchor_decay": "[0, 1]", "anchor_decay_found": "(-inf, 1]",
              "repeat_found": "[0, 1]", "uniform_mix": "[0, 1]", "edge_mass": "[0, 1]",
              "edge_explore": "[0, 1]", "kappa": "[0, inf)", "zoom": "[0, inf)",
              "prior_mean": "[-5, 5]", "ttc_weight": "[0, 1]", "ttc_below": "[-1, 100]"}


@pytree.dataclass
class ARState:
    weights: dict  # controller weights, leading axis = learners (L)
    opt: object  # Adam's moments, per learner
    seen: jax.Array  # (L,) bool, the learner has had a collision
    explored: jax.Array  # (B,) bool, which scenarios of the last ask were uniform draws
    anchors: jax.Array  # (B, P) int32, the anchor each scenario of the last ask was drawn at
    anchored: jax.Array  # (B,) bool, whether it had one
    zooms: jax.Array  # (B,) float32 in [0, 1), each draw's position on the zoom scale
    queue: jax.Array  # (L, K, P) int32, each learner's best distinct scenarios, best first
    queue_signal: jax.Array  # (L, K) float32, their signals (-inf: empty slot)
    queue_hit: jax.Array  # (L, K) bool, which of them collided
    told: jax.Array  # () int32, updates so far
    memory: MemoryState | None  # the evaluated scenarios' hashes (``resample`` > 1)
    screen: gp.ScreenState | None  # the GP screening's data and length scales (``surrogate``)


MAX_TABLE = 2**28  # entries of the candidates' repeat-check tables (N x N, N x memory)


@dataclasses.dataclass(frozen=True)
class AutoregressiveReinforce(Strategy):
    """Static: ``hidden`` LSTM units, ``learners`` (divides ``batch``), ``advantage``
    (``rank`` or ``normalised``), ``signal`` (``shaped`` or ``reward``), ``queue`` (best
    scenarios kept per learner), ``anchored`` (draw around them; needs ``queue``),
    ``resample`` (policy candidates per asked scenario; 1: repeats allowed), ``explore``
    (uniformly random candidates per asked scenario beside them, with ``resample`` >= 2: the
    fallbacks when too few policy draws are new, and the GP's to pick from), ``memory``
    (evaluated scenarios remembered), ``surrogate`` (evaluations the GP screening is fitted
    to; 0: off; needs ``resample`` >= 2), ``kernel`` (the GP's correlation: ``se``,
    ``matern52`` or ``auto``, either chosen by marginal likelihood with each length scale)."""

    hidden: int = 32
    learners: int = 4
    advantage: str | Callable = "rank"
    signal: str | Callable = "shaped"
    queue: int = 0
    anchored: bool = False
    resample: int = 1
    explore: int = 1
    memory: int = 4096
    surrogate: int = 0
    kernel: str = "se"

    Params = ARParams
    FUNCTION_OPTIONS = {"signal": resolve_signal, "advantage": resolve_advantage}
    # sizes a CPU can hold and a campaign can compile (refused before any folder is written)
    RANGES = {"hidden": "[1, 1024]", "learners": "[1, 1024]", "queue": "[0, 4096]",
              "resample": "[1, 256]", "explore": "[1, 256]", "memory": "[1, 1048576]",
              "surrogate": "[0, 1024]"}

    def __post_init__(self):
        resolve_advantage(self.advantage)  # one-line errors on a bad one
        resolve_signal(self.signal)  # a one-line error on a bad one
        gp.check_kernel(self.kernel)
        if self.hidden < 1:
            raise ValueError(f"hidden must be >= 1 (got {self.hidden})")
        if self.learners < 1 or self.batch % self.learners:
            raise ValueError(f"learners={self.learners} must divide batch={self.batch}")
        if self.queue < 0:
            raise ValueError(f"queue must be >= 0 (got {self.queue})")
        if self.anchored and self.queue < 1:
            raise ValueError("anchored needs queue >= 1")
        if self.surrogate < 0 or (self.surrogate and self.resample < 2):
            raise ValueError(f"surrogate must be >= 0 and needs resample >= 2 (got "
                             f"surrogate={self.surrogate}, resample={self.resample})")
        if self.resample < 1 or self.memory < 1 or self.explore < 1:
            raise ValueError(f"resample, explore and memory must be >= 1 (got "
                             f"{self.resample}, {self.explore}, {self.memory})")
        n = self.batch * (self.resample + self.explore)  # candidates per ask
        if self.resample > 1 and max(n * n, n * self.memory) > MAX_TABLE:
            raise ValueError(
                f"batch x (resample + explore) = {n:,} candidates: the repeat checks compare "
                f"them with each other and with the memory of {self.memory:,} (tables of "
                f"{max(n * n, n * self.memory):,} entries, at most {MAX_TABLE:,}); lower "
                "batch, resample, explore or memory")

    @property
    def per_learner(self) -> int:
        return self.batch // self.learners

    # the pieces this strategy is composed of, as its options configure them (None: off)
    @property
    def no_repeats(self) -> NoRepeats | None:
        """The evaluated scenarios remembered, so candidates are new (``resample`` > 1)."""
        return NoRepeats(self.memory) if self.resample > 1 else None

    @property
    def screen(self) -> gp.GPScreen | None:
        """The GP that picks which candidates are asked until a collision (``surrogate``)."""
        return gp.GPScreen(self.surrogate, self.kernel, tuple(self.shape)) \
            if self.surrogate else None

    def _lsm(self, params):
        return jnp.log(jnp.clip(params.sigma_min, 1e-4, 1.0))

    def _global(self):
        """The anchor argument of a draw without an anchor."""
        return (jnp.zeros(self.n_params, jnp.int32), jnp.bool_(False)) if self.anchored \
            else None

    def _log_zoom(self, params):
        """``(P,)`` the widest move's extra log-width: ``zoom`` of the range over the
        initial local width, never narrower (0 for parameters too small to gain)."""
        span = jnp.maximum(jnp.asarray(self.shape, jnp.float32) - 1, 1.0)
        return jnp.maximum(jnp.log(jnp.maximum(params.zoom * span, 1e-6) / ar.LOCAL_STEPS),
                           0.0)

    def init(self, key, params):
        L, P, K = self.learners, self.n_params, max(self.queue, 1)
        keys = jax.random.split(key, L)
        weights = jax.vmap(lambda k: ar.init(k, self.shape, self.hidden, self.anchored))(keys)
        return ARState(weights, jax.vmap(optax.scale_by_adam().init)(weights),
                       jnp.zeros(L, bool), jnp.zeros(self.batch, bool),
                       jnp.zeros((self.batch, P), jnp.int32), jnp.zeros(self.batch, bool),
                       jnp.zeros(self.batch, jnp.float32), jnp.zeros((L, K, P), jnp.int32),
                       jnp.full((L, K), -jnp.inf, jnp.float32), jnp.zeros((L, K), bool),
                       jnp.int32(0), self.no_repeats and self.no_repeats.init(),
                       self.screen and self.screen.init())

    def probs(self, state, learner: int = 0, params=None) -> jax.Array:
        """``(P, max_n)``: each parameter's probabilities (draws without an anchor) given the
        most likely values of the parameters before it, for one learner (row 0 is the first
        parameter's marginal)."""
        params = params or self.default_params()
        w = jax.tree.map(lambda x: x[learner], state.weights)

        def step_fn(p, logits, _):
            return jnp.argmax(logits).astype(jnp.int32), ar.padded(jax.nn.softmax(logits),
                                                                   self.shape)

        return ar.over_params(w, self.shape, step_fn, jnp.zeros(self.n_params),
                              self._lsm(params), self._global())

    def candidates(self, key, state, params):
        """The scenarios an ask chooses from, per learner: ``idx (L, C, P)``, ``explored``
        (uniform draws), ``anchors (L, C, P)``, ``present`` (anchored), ``zooms`` (all ``(L,
        C)``) and ``allowed (L, C)``, the candidates that may be asked (new, or free to repeat
        once the learner has a collision); ``C = b`` and all allowed when ``resample`` is 1,
        else ``b * (resample + explore)``, the policy draws first."""
        L, b, P, M = self.learners, self.per_learner, self.n_params, self.resample
        lsm = self._lsm(params)
        E = self.explore if M > 1 else 0  # uniform candidates per slot
        C = b * (M + E)  # candidates per learner: M policy draws per slot + E uniform ones
        Cp = b * M if M > 1 else b  # of which the policy draws (the rest: uniform fallbacks)
        # one draw: policy (P), uniform values (P), anchor pick, anchor coin, repeat coin,
        # zoom, uniform-mix coin
        u = uniform(key, (L, C, 2 * P + 5))
        zooms = u[..., 2 * P + 3]  # (L, C)
        lz = self._log_zoom(params)
        em = jnp.asarray(params.edge_mass, jnp.float32)
        if self.anchored:  # an anchor from the learner's queue, the k-th best ~ decay^k
            filled = jnp.sum(jnp.isfinite(state.queue_signal), axis=-1)  # (L,)
            K = state.queue.shape[1]
            decay = jnp.where(state.seen & (params.anchor_decay_found >= 0),
                              params.anchor_decay_found, params.anchor_decay)  # (L,)
            wk = jnp.where(jnp.arange(K)[None, :] < filled[:, None],
                           decay[:, None] ** jnp.arange(K, dtype=jnp.float32)[None, :], 0.0)
            pick = categorical_from_uniform(u[..., 2 * P],
                                            jnp.broadcast_to(wk[:, None, :], (L, C, K)))
            anchors = jnp.take_along_axis(state.queue, pick[..., None], axis=1)  # (L, C, P)
            share = jnp.where(state.seen & (params.global_share_found >= 0),
                              params.global_share_found, params.global_share)  # (L,)
            present = (filled[:, None] > 0) & (u[..., 2 * P + 1] >= share[:, None])
            sampled = jax.vmap(lambda w, ul, al, pl, zl: jax.vmap(
                lambda ui, ai, pi, zi: ar.sample(w, ui, self.shape, lsm, (ai, pi, zi * lz, em)))(
                    ul, al, pl, zl))(state.weights, u[:, :Cp, :P], anchors[:, :Cp],
                                     present[:, :Cp], zooms[:, :Cp])
        else:
            anchors = jnp.zeros((L, C, P), jnp.int32)
            present = jnp.zeros((L, C), bool)
            sampled = jax.vmap(lambda w, ul: jax.vmap(
                lambda ui: ar.sample(w, ui, self.shape, lsm))(ul))(state.weights,
                                                                  u[:, :Cp, :P])
        # the uniform fallbacks need no policy draw
        sampled = jnp.pad(sampled, ((0, 0), (0, C - Cp), (0, 0)))
        explored = u[..., -1] < params.uniform_mix
        if M > 1:  # the last b * E candidates are uniform draws (fallbacks when too few are new)
            explored = explored | (jnp.arange(C) >= Cp)[None, :]
        uni = uniform_indices(u[..., P:2 * P], self.shape)
        # edge_explore: each value of a uniform draw goes to the first or the last value
        # with that probability (its own uniform picks which); a separate stream, so 0
        # changes nothing
        edge = jnp.where(u[..., P:2 * P] < 0.5, 0, jnp.asarray(self.shape, jnp.int32) - 1)
        snap = uniform(jax.random.fold_in(key, 1), uni.shape) < params.edge_explore
        uni = jnp.where(snap, edge, uni)
        idx = jnp.where(explored[..., None], uni, sampled)  # (L, C, P)
        allowed = jnp.ones((L, C), bool)
        if M > 1:
            h = scenario_hash(idx).reshape(-1)
            repeated = equals_an_earlier(h[:, None] == h[None, :])
            fresh = (~self.no_repeats.evaluated(state.memory, h) & ~repeated).reshape(L, C)
            # a learner with a collision may repeat, for a share repeat_found of its draws,
            # one of its own collisions (a queue entry that collided; without a queue, none):
            # a repeated non-collision teaches nothing, and a learner whose policy drifted
            # onto one asked it batch after batch
            own = jnp.any(jnp.all(idx[:, :, None, :] == state.queue[:, None, :, :], -1)
                          & state.queue_hit[:, None, :], -1)
            free = state.seen[:, None] & own & (u[..., 2 * P + 2] < params.repeat_found) \
                & (jnp.arange(C) < Cp)[None, :]
            allowed = fresh | free
        return dict(idx=idx, explored=explored, anchors=anchors, present=present, zooms=zooms,
                    allowed=allowed)

    def ask(self, key, state, params):
        b, P = self.per_learner, self.n_params
        c = self.candidates(key, state, params)
        if self.resample > 1:  # per learner, b of the allowed candidates
            plain = jnp.argsort(~c["allowed"], axis=-1, stable=True)[:, :b]  # in drawing order
            if self.screen:  # until a collision, the GP picks among the allowed candidates
                best = state.queue.reshape(-1, P)
                order, screen = jax.lax.cond(
                    jnp.all(state.seen), lambda: (plain, state.screen),
                    lambda: self.screen.pick(state.screen, best, state.queue_signal.reshape(-1),
                                             state.told, c["idx"], c["allowed"], b,
                                             params.kappa, params.prior_mean))
                state = dataclasses.replace(state, screen=screen)
                order = jnp.where(state.seen[:, None], plain, order)
            else:
                order = plain
            c = {k: jnp.take_along_axis(v, order.reshape(order.shape + (1,) * (v.ndim - 2)),
                                        axis=1) for k, v in c.items()}
            state = dataclasses.replace(state, memory=self.no_repeats.remember(
                state.memory, scenario_hash(c["idx"]).reshape(-1)))
        return c["idx"].reshape(self.batch, P), dataclasses.replace(
            state, explored=c["explored"].reshape(self.batch),
            anchors=c["anchors"].reshape(self.batch, P),
            anchored=c["present"].reshape(self.batch), zooms=c["zooms"].reshape(self.batch))

    def tell(self, key, state, indices, rewards, params):
        return self._update(state, indices, rewards, state.seen, params,
                            jnp.zeros(rewards.shape, bool))

    def tell_outcome(self, key, state, indices, rewards, robustness, collision, params,
                     ttc=None):
        if ttc is not None:  # a learner's aid until its first collision (the reward's after)
            before = jnp.repeat(~state.seen, self.per_learner)
            robustness = jnp.where(before, near_miss_ttc(robustness, ttc, params.ttc_weight,
                                                         params.ttc_below), robustness)
        signal = resolve_signal(self.signal)(rewards, robustness, collision, ttc)
        hit = jnp.any(collision.reshape(self.learners, -1), axis=-1)
        return self._update(state, indices, signal, state.seen | hit, params, collision)

    def _update(self, state, indices, signal, seen, params, collided):
        L, b, P = self.learners, self.per_learner, self.n_params
        lsm = self._lsm(params)
        sig = signal.reshape(L, b)
        ok = jnp.isfinite(sig) & ~state.explored.reshape(L, b)
        adv = resolve_advantage(self.advantage)(sig, ok)
        done = (state.told * self.batch).astype(jnp.float32)  # evaluations before this batch
        fade = jnp.where(params.entropy_until > 0,
                         jnp.clip(1.0 - done / jnp.maximum(params.entropy_until, 1.0), 0.0, 1.0),
                         1.0)
        beta = jnp.where(seen, params.entropy_found * fade, params.entropy)  # (L,)
        acts = indices.reshape(L, b, P)
        anc = state.anchors.reshape(L, b, P)
        pres = state.anchored.reshape(L, b)
        zooms = state.zooms.reshape(L, b)
        lz = self._log_zoom(params)
        em = jnp.asarray(params.edge_mass, jnp.float32)

        def loss(w, a, adv_l, ok_l, beta_l, anc_l, pres_l, z_l):
            if self.anchored:
                lp, ent = jax.vmap(lambda ai, ci, pi, zi: ar.log_prob_and_entropy(
                    w, ai, self.shape, lsm, (ci, pi, zi * lz, em)))(a, anc_l, pres_l, z_l)
            else:
                lp, ent = jax.vmap(lambda ai: ar.log_prob_and_entropy(w, ai, self.shape,
                                                                      lsm))(a)
            n = jnp.maximum(jnp.sum(ok_l), 1)
            return -(jnp.sum(adv_l * lp) + beta_l * jnp.sum(jnp.where(ok_l, ent, 0.0))) / n

        grads = jax.vmap(jax.grad(loss))(state.weights, acts, adv, ok, beta, anc, pres, zooms)
        updates, opt = jax.vmap(optax.scale_by_adam().update)(grads, state.opt, state.weights)
        lr = jnp.where(seen & (params.lr_found >= 0), params.lr_found, params.lr)  # (L,)
        weights = jax.tree.map(lambda w, u: w - lr.reshape((-1,) + (1,) * (u.ndim - 1)) * u,
                               state.weights, updates)
        # no signal, no step: a learner whose batch ranks all alike (a converged learner
        # asking copies of its best scenario) has a zero gradient, and Adam's momentum alone
        # would walk its policy off what it learnt
        active = jnp.any(adv != 0, axis=-1) | (beta > 0)  # (L,)
        keep = lambda new, old: jnp.where(  # noqa: E731
            active.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)
        weights = jax.tree.map(keep, weights, state.weights)
        opt = jax.tree.map(keep, opt, state.opt)
        if self.queue:  # merge the batch into each learner's queue of best distinct scenarios
            q, qs, qh = jax.vmap(lambda qi, qsi, qhi, a, s, h: top_distinct(
                jnp.concatenate([qi, a]), jnp.concatenate([qsi, s]), self.queue,
                jnp.concatenate([qhi, h])))(
                state.queue, state.queue_signal, state.queue_hit, acts,
                jnp.where(jnp.isfinite(sig), sig, -jnp.inf), collided.reshape(L, b))
        else:
            q, qs, qh = state.queue, state.queue_signal, state.queue_hit
        screen = self.screen.record(state.screen, indices.reshape(self.batch, P), signal) \
            if self.screen else state.screen
        return dataclasses.replace(state, weights=weights, opt=opt, seen=seen, queue=q,
                                   queue_signal=qs, queue_hit=qh, told=state.told + 1,
                                   screen=screen)
