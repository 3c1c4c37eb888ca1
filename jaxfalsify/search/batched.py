"""``reinforce/default``: a Flax LSTM controller trained by REINFORCE (paper Section II-A,
Eq. 2-3) with optax, on thousands of concrete scenarios per update.

One concern: the batched learner (its controller, its draws, its update and its memory of
the failures seen); the mixture's probabilities are :mod:`jaxfalsify.search.discretised`'s.

**The controller** (:class:`MixtureController`, ``flax.linen``) is the paper's LSTM controller
made cheap at any resolution. As the NAS controller the paper builds on, the LSTM steps over
the parameters, one step each, and each step's head describes that parameter; the step reads
which parameter it is and what the previous step's head said, so each parameter's description
is conditioned on those before it. Instead of one softmax logit per value, a head gives ``K``
components' mean and width over the parameter's value ranks, and a last head the components'
weights: the policy is a mixture of ``K`` products of discretised truncated logistic
distributions with a uniform floor (:mod:`jaxfalsify.search.discretised`). The components are
joint modes: each ties a value of every parameter to the others (a diagonal band of ``ego_offset`` x
``ped_speed`` is a chain of components, which independent per-parameter heads cannot hold). A
scenario's probability costs ``O(K P)`` exponentials whatever the number of values, and the
LSTM runs once per update, not once per scenario.

**The update** (Eq. 2-3): each update draws ``batch`` scenarios, the campaign rolls them out
in the same compiled step, and the loss is ``-sum_j w_j log pi(a_j)`` over the ``elite`` best
share of the batch by the shaped signal (the STL robustness until a collision is found, near
misses told apart by their minimum time-to-collision, the paper's reward among collisions:
:func:`jaxfalsify.search.base.shaped_signal`), ``w_j`` CMA-ES's log-rank weights summing to 1,
the rest of the batch weight 0: non-negative rank utilities with baseline 0, unbiased as any
constant baseline is. ``steps`` Adam steps (optax) follow it on the same batch, with learning
rate ``lr_search`` (0.1) until the learner has drawn a collision and ``lr`` (0.03) from then on:
large steps towards the failures while there are none, small ones to converge on the best
failures once there are (Adam's steps have about the learning rate's size whatever the
gradient's scale, so the learning rate is how far the policy moves per update). Optionally the
first update is a larger jump (``lr_first``) for learners 0 to ``first_learners`` - 1 whose
share drew no collision (off by default: ``first_learners`` 0). ``first_learners`` is a traced
number like every hyperparameter: a learner takes ``lr_first`` when its index is below it. An
entropy bonus ``entropy x mean log sigma`` keeps the components from collapsing early.

**The first batch at the boundary**: at the first update the learners whose index is below
``boundary x learners`` (all by default) draw their shares from the boundary distribution
(:func:`jaxfalsify.search.discretised.sample_boundary`: each parameter independently uniform,
near its lowest value or near its highest, a third each) instead of their policies, and learn
from it as from their own draws: boundary-value testing for every parameter at once. A failure
region on a face or an edge of the box (some parameters at an end of their ranges, the others
anywhere) gets many times the mass uniform draws give it, where the policies' initial
components (means in 0.05-0.95 of each range) give it less than uniform draws do.

**Screened by the crossing's kinematics**: where the campaign simulates the crossing world
itself (``ask_screened``), each boundary draw in the first two learners' shares of the first
batch (``screened_learners``) is the one nearest to a conflict among ``screen_candidates`` (8)
boundary candidates: the least ``max(gap, 0)``, ``gap`` the seconds between the unbraked car's
and the walker's windows at the crossing (:func:`jaxfalsify.core.screen.conflict_gap`; <= 0
where the car, driving as if no walker were there, would hit it). A collision needs the actors
to meet, and an AEB's car meets the walker where the unbraked car would, or just after. On
``aeb-9e6`` (9 collisions in a million) a first batch of 4096 then holds a collision with
probability about 0.7, against 0.27 for the boundary draws alone and 0.036 for uniform ones
(docs/search.md). The other two learners' shares stay the boundary's: with every share
screened the paper space's learning target held in 17 of 20 seeds (a first batch of conflicts
alone narrowed what the learners start from). A later update's draws are the policies'; an
external evaluator's run (``ask``) draws the boundary alone.

**Several learners** (``learners``, 4): independent controllers (until ``novelty_until``,
below), each drawing an equal share of the batch and updated on its own share's elite, so one
learner held on a plateau of near misses does not hold the others (the batch is their equal
mixture). On a logical scenario whose failures are isolated in a rough corner of the space
(``experiments/spaces/fast-walkers.toml``) one learner reached a collision in 1 of 5 seeds
within 100 updates, four in 6 of 10 within 200 (learning rate 0.03 throughout; with
``lr_search`` before the first collision, in 10 of 10).

The search keeps moving: a scenario that was in an earlier update's elite or collided is
remembered (a hashed table in the state); drawn again, a collision loses ``novelty`` (0.5: it
ranks below every new scenario, so after the first collision the elite moves on to collisions
not found yet instead of re-drawing the best one), a non-collision ``revisit`` (0.01, the
signal of 0.2 m of robustness: among near misses of about the same distance a new one ranks
first). From ``novelty_until`` evaluations on (by default half the default budget) neither
applies and the learners converge together on the best failures (the paper's reward ranks
them): each learns from the whole batch's elite, starting from the learner whose share scored
best on average (learning apart to the end, one of four often stayed on a worse failure mode
and held a quarter of the batch there).
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxfalsify.base import pytree
from jaxfalsify.search import discretised
from jaxfalsify.search.base import Strategy, near_miss_ttc, shaped_signal, uniform
from jaxfalsify.search.controller import Linear, LSTMCell

__all__ = [
    "SIGMA_MIN_STEPS", "LOG_SIGMA_MAX", "BatchedReinforce", "MixtureController",
    "BatchedParams", "BatchedState", "SIGMA_INIT", "DEFAULT_EVALUATIONS"
]

SIGMA_MIN_STEPS = 0.1  # narrowest component's logistic scale, in value steps (98.7 % of its
# mass on one value: S(5) - S(-5))
LOG_SIGMA_MAX = 0.0  # widest component: sigma = 1 (the whole range)
SIGMA_INIT = 0.165  # initial logistic scale, in rank units (a standard deviation of 0.3)
DEFAULT_EVALUATIONS = 100 * 4096  # a run's default budget: 100 updates of the CPU batch


class MixtureController(nn.Module):
    """The LSTM controller: ``() -> (mix_logits (K,), mu (K, P), log_sigma (K, P))`` in rank
    units. Step ``p`` of a tanh LSTM of ``hidden`` units reads ``[onehot_P(p), previous step's
    head (2K,)]``; its head (shared weights, a per-parameter bias) gives the ``K`` means'
    logits and widths' logits of parameter ``p``; a last linear head on the final LSTM output
    gives the mixture weights' logits. The per-parameter biases start at component means
    spread over the range (drawn at init) and widths of ``SIGMA_INIT``: the first proposals
    cover the space."""

    shape: tuple[int, ...]
    hidden: int = 32
    components: int = 24

    @nn.compact
    def __call__(self):
        P, K = len(self.shape), self.components
        cell = LSTMCell(self.hidden, jnp.tanh, name="lstm")
        head = Linear(2 * K, name="head")
        bias = self.param("bias", _initial_bias(self.shape, K), (P, 2 * K))
        carry = (jnp.zeros(self.hidden), jnp.zeros(self.hidden))
        prev, outs, h = jnp.zeros(2 * K), [], None
        for p in range(P):  # over the parameters (the controller's structure), not data
            carry, h = cell(carry, jnp.concatenate([jax.nn.one_hot(p, P), prev]))
            prev = 0.1 * head(h) + bias[p]
            outs.append(prev)
        z = jnp.stack(outs, axis=1)  # (2K, P)
        mix_logits = Linear(K, name="mix")(h) * 0.1
        n = np.asarray(self.shape, np.float64)
        half = jnp.asarray(discretised.half_steps(self.shape), jnp.float32)
        mu = -half + (1.0 + 2.0 * half) * jax.nn.sigmoid(z[:K])
        lo = jnp.asarray(np.log(SIGMA_MIN_STEPS / np.maximum(n - 1, 1)), jnp.float32)
        log_sigma = lo + (LOG_SIGMA_MAX - lo) * jax.nn.sigmoid(z[K:])
        return mix_logits, mu, log_sigma


def _initial_bias(shape, K, vertices=0.0, vertex_sigma=SIGMA_INIT):
    """The controller's per-parameter head biases at init, ``(P, 2K)``: the components'
    means' logits (drawn uniformly over 0.05-0.95 of the range) and widths' logits
    (``SIGMA_INIT``); the first ``round(vertices * K)`` components instead start at a vertex
    of the box (each parameter's mean at 0.02 or 0.98 of its range, a fair coin each) with
    width ``vertex_sigma`` (rank units)."""
    n = np.asarray(shape, np.float64)
    lo = np.log(SIGMA_MIN_STEPS / np.maximum(n - 1, 1))

    def z_of(sigma):  # sigmoid(z) for the width sigma (a one-value parameter: any)
        s = np.clip((np.log(sigma) - lo) / (LOG_SIGMA_MAX - lo), 0.01, 0.99)
        return jnp.asarray(np.log(s / (1 - s)), jnp.float32)[:, None]

    z_sigma, z_vertex = z_of(SIGMA_INIT), z_of(vertex_sigma)
    n_vertex = int(round(vertices * K))

    def init(key, size, dtype=jnp.float32):
        P, _ = size
        k_mean, k_vertex = jax.random.split(key)
        m = jax.random.uniform(k_mean, (P, K), minval=0.05, maxval=0.95)
        at = jnp.arange(K)[None, :] < n_vertex  # (1, K): the components at vertices
        m = jnp.where(at, jnp.where(jax.random.bernoulli(k_vertex, 0.5, (P, K)), 0.98, 0.02), m)
        zs = jnp.where(at, z_vertex, z_sigma)  # (P, K)
        return jnp.concatenate([jnp.log(m / (1 - m)), zs], axis=1).astype(dtype)

    return init


def _shift(j: int, p: int, n: int) -> int:
    """The row shift of parameter ``p`` in the ``j``-th (1-based) screened candidate of a
    batch of ``n`` rows, ``j (2 p + 1)`` modulo ``n``: nonzero and distinct over ``j`` while
    ``j (2 p + 1) < n``, so a row's candidates share no parameter's draw."""
    return (j * (2 * p + 1)) % n if n > 1 else 0


@pytree.dataclass
class BatchedParams:
    lr: float = 0.03  # Adam learning rate once the learner has found a collision ...
    lr_search: float = 0.1  # ... and until then ...
    lr_first: float = 0.3  # ... except at the first update, for the first learners:
    first_learners: float = 0.0  # learners whose index is below it (the rest: lr_search)
    eps: float = 0.01  # the uniform floor's weight in the policy
    entropy: float = 0.01  # bonus on the components' mean log-width
    novelty: float = 0.5  # signal taken off a collision seen before (elite or collision) ...
    revisit: float = 0.01  # ... off a scenario seen before that did not collide ...
    novelty_until: float = DEFAULT_EVALUATIONS / 2  # ... until this many evaluations were
    # told (half the default budget; then the learners converge together on the best failures)
    ttc_weight: float = 0.0  # near misses told apart by their min TTC [m per s] (0: off)
    ttc_below: float = -0.5  # ... below this robustness [m]
    boundary: float = 1.0  # share of the learners (the first ones) whose first share of the
    # batch is drawn from the boundary distribution (discretised.sample_boundary), not the policy
    boundary_width: float = 0.02  # ... its mean distance from a range's end (rank units)

    RANGES = {"lr": "[0, 10]", "lr_search": "[0, 10]", "lr_first": "[0, 10]",
              "first_learners": "[0, inf)", "eps": "(0, 1)", "entropy": "[0, inf)",
              "novelty": "[0, inf)", "revisit": "[0, inf)",
              "novelty_until": "[0, inf)", "ttc_weight": "[0, inf)", "ttc_below": "(-inf, inf)",
              "boundary": "[0, 1]", "boundary_width": "(0, inf)"}


@pytree.dataclass
class BatchedState:
    params: dict  # the controller's Flax parameters
    opt: object  # Adam's moments
    seen: jax.Array  # (table,) uint32 hashes of collisions evaluated (0: empty)
    told: jax.Array  # () int32 evaluations told
    found: jax.Array  # (L,) bool (() for one learner): the learner has drawn a collision
    ready: jax.Array  # () bool: ``params`` holds the weights (False: zeros until the first
    # tell, the weights being init's from ``init_key``; see BatchedReinforce.start)
    init_key: jax.Array  # the typed key init draws the weights from


@dataclasses.dataclass(frozen=True)
class BatchedReinforce(Strategy):
    """Static: ``hidden`` LSTM units, ``components`` of the mixture, ``steps`` Adam steps per
    update, ``elite`` share learnt from, ``table`` slots of the collisions-seen hash table (a
    power of two), ``learners`` controllers, each drawing an equal share of the batch and
    learning from its own share's elite until ``novelty_until``, from the whole batch's after
    (the batch is their equal mixture; the last
    share is cut short when they do not divide the batch); the last ``vertex_learners`` of
    them (never the first) start with a share ``vertices`` of their components at vertices of
    the box, of width ``vertex_sigma`` (rank units), where boundary-value testing looks: a
    system that gets worse monotonically in each parameter fails at a corner."""

    hidden: int = 32
    components: int = 24
    steps: int = 8
    elite: float = 0.1
    table: int = 1 << 16
    learners: int = 4
    vertex_learners: int = 2
    vertices: float = 1.0
    vertex_sigma: float = 0.02
    screen_candidates: int = 8  # boundary candidates per first-batch slot (ask_screened; 1: off)
    screened_learners: int = 2  # ... in the shares of the first this many learners

    Params = BatchedParams
    RANGES = {"hidden": "[1, 1024]", "components": "[1, 256]", "steps": "[1, 64]",
              "elite": "(0, 1]", "table": "[16, 16777216]", "learners": "[1, 256]",
              "vertex_learners": "[0, 256]", "vertices": "[0, 1]", "vertex_sigma": "(0, 1]",
              "screen_candidates": "[1, 64]", "screened_learners": "[0, 256]"}

    def __post_init__(self):
        if self.table & (self.table - 1):
            raise ValueError(f"table must be a power of two (got {self.table})")

    @property
    def module(self) -> MixtureController:
        return MixtureController(tuple(self.shape), self.hidden, self.components)

    @property
    def n_screened_learners(self) -> int:
        """Learners whose first-batch share is screened (``ask_screened``): the first
        ``screened_learners``, never all (one learner, or two, keeps the boundary's draws for
        at least one share)."""
        return min(self.screened_learners, self.learners - 1)

    @property
    def n_vertex_learners(self) -> int:
        """Learners that start at the box's vertices: the last ``vertex_learners``, never the
        first (a single learner always starts spread over the space)."""
        return min(self.vertex_learners, self.learners - 1)

    def _each(self, f):
        """``f`` over the learners: vmapped over a leading ``(L,)`` axis, or ``f`` itself for
        one learner (whose state has no such axis)."""
        return f if self.learners == 1 else jax.vmap(f)

    def _shares(self, x, fill=0):
        """``(B, ...) -> (L, share, ...)``: the learners' shares of a batch, the last padded
        with ``fill`` when the learners do not divide it; ``x`` itself for one learner."""
        if self.learners == 1:
            return x
        pad = self.learners * self.share - x.shape[0]
        x = jnp.pad(x, ((0, pad),) + ((0, 0),) * (x.ndim - 1), constant_values=fill)
        return x.reshape(self.learners, self.share, *x.shape[1:])

    def _keys(self, key):
        return key if self.learners == 1 else jax.random.split(key, self.learners)

    def init(self, key, params):
        state = self.start(key, params)
        return dataclasses.replace(state, params=self._initial_weights(key),
                                   ready=jnp.bool_(True))

    def start(self, key, params):
        """``init``'s state with the controllers' weights not drawn yet (zeros, ``ready``
        False): the first batch is the boundary's (``boundary`` 1, the default), so the first
        ask does not need them, and the first tell (or an ask that does) draws them from the
        same key, the same weights as ``init``'s. A campaign's first update then costs what
        drawing and simulating its batch costs (drawing four learners' weights took about 0.6
        ms at batch 4096 on 2 CPU cores, against 9-13 ms for the update)."""
        weights = jax.eval_shape(self._initial_weights, key)
        weights = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), weights)
        opt = self._each(optax.scale_by_adam().init)(weights)  # (zeros: the same for any)
        found = jnp.zeros(() if self.learners == 1 else (self.learners,), bool)
        return BatchedState(weights, opt, jnp.zeros(self.table, jnp.uint32), jnp.int32(0),
                            found, jnp.bool_(False), key)

    def _initial_weights(self, key):
        """The controllers' weights at init, drawn from ``key`` (a leading ``(L,)`` axis for
        several learners)."""
        # independent learners: a leading axis on every weight and Adam moment
        keys = self._keys(key)
        weights = self._each(lambda k: self.module.init(k)["params"])(keys)
        n_v = self.n_vertex_learners
        if n_v:  # the last n_v learners' components (a share `vertices`) start at vertices
            K, P = self.components, self.n_params
            vertex = _initial_bias(self.shape, K, self.vertices, self.vertex_sigma)
            vb = jax.vmap(lambda k: vertex(jax.random.fold_in(k, 1), (P, 2 * K)))(
                keys[self.learners - n_v:])
            weights["bias"] = weights["bias"].at[self.learners - n_v:].set(vb)
        return weights

    def _weights(self, state):
        """The controllers' weights: ``state.params``, or init's when not drawn yet."""
        return jax.lax.cond(state.ready, lambda: state.params,
                            lambda: self._initial_weights(state.init_key))

    def distribution(self, state):
        """``(mix_logits (K,), mu (K, P), log_sigma (K, P))`` of the current policy; with
        ``learners`` > 1 each with a leading ``(L,)`` axis, one policy per learner."""
        return self._each(lambda w: self.module.apply({"params": w}))(self._weights(state))

    def probs(self, state, params=None) -> jax.Array:
        """``(P, max_n)`` each parameter's marginal probabilities under the current policy
        (with several learners, their equal mixture: what ``ask`` draws from when the learners
        divide the batch, after the first update's boundary draws)."""
        eps = (params or self.default_params()).eps
        p = self._each(lambda m, u, s: discretised.probs_table(m, u, s, self.shape, eps))(
            *self.distribution(state))
        return p if self.learners == 1 else jnp.mean(p, axis=0)

    def ask(self, key, state, params):
        return self.ask_screened(key, state, params, None)

    def ask_screened(self, key, state, params, screen):
        def draw(dist, u):
            return discretised.sample(*dist, u, self.shape, params.eps)

        # learner l draws the l-th share of the batch (the last share is cut short when the
        # learners do not divide the batch). A barrier: fused into its consumers, the
        # threefry draw was recomputed there (ask and gradient in one program: 68 ms instead
        # of 5 ms per update at batch 4096 on 2 cores)
        u = jax.lax.optimization_barrier(
            uniform(key, (self.learners * self.share, self.n_params + 2)))
        def own(u):
            idx = self._each(draw)(self.distribution(state), self._shares(u))
            return idx.reshape(-1, self.n_params)

        # the first update: the first learners (a share `boundary` of them) draw from the
        # boundary distribution instead (their policies learn from it as from their own
        # draws). A cond, so later updates do not compute the boundary draws; the policy's
        # draws are computed inside the branches that use them (computed outside and passed
        # in, they cost 0.7 ms more per update at batch 4096 on 2 cores: laid out for the
        # cond, their elementwise work no longer vectorised). (Under a vmap the conds would
        # become selects, every branch computed; the campaign maps seeds with lax.map.)
        def at_boundary(u):
            at = jnp.arange(u.shape[0]) // self.share < params.boundary * self.learners
            bound = self._boundary(u, params, screen)
            # the policies' draws only when some learner keeps its own (boundary < 1)
            return jax.lax.cond(jnp.all(at), lambda u: bound,
                                lambda u: jnp.where(at[:, None], bound, own(u)), u)

        idx = jax.lax.cond(state.told == 0, at_boundary, own, u)
        return idx[:self.batch], state

    def _boundary(self, u, params, screen):
        """``(N, P)`` first-batch boundary draws, one per row of the uniforms ``u (N, P + 2)``;
        with a ``screen``, in the shares of the first ``screened_learners`` learners each
        row's draw is the candidate nearest to a conflict (the least
        ``max(gap, 0)``, the first of equals) among ``screen_candidates``: the row's own draw
        and ``screen_candidates - 1`` recombinations of the other rows' draws (candidate ``j``
        of row ``i`` takes parameter ``p`` from row ``i - s_jp``, fixed shifts distinct for
        every ``j`` and ``p``: each a draw of the boundary distribution, independent of the
        row's other candidates when ``(screen_candidates - 1)(2 P - 1) < N``; no uniforms to
        draw)."""
        drawn = discretised.sample_boundary(u[:, 2:], self.shape, params.boundary_width)
        M = self.screen_candidates
        # the screened rows: the first screened_learners learners' shares
        stop = min(self.n_screened_learners * self.share, drawn.shape[0])
        if screen is None or M == 1 or stop == 0:
            return drawn
        first = drawn[:stop]
        N, P = first.shape
        more = [jnp.stack([jnp.roll(first[:, p], _shift(j, p, N)) for p in range(P)], axis=1)
                for j in range(1, M)]
        gap = jnp.maximum(screen(jnp.concatenate([first] + more)), 0.0).reshape(M, N)
        # the nearest by where's, not an argmin and a gather: XLA fused the screen into the
        # reduction's kernel (2.5 against 1.6 ms for 8 x 4096 candidates on one core); an
        # infinite gap (an actor that never gets there) never replaces a finite one
        best, best_gap = first, gap[0]
        for j in range(1, M):
            nearer = gap[j] < best_gap
            best = jnp.where(nearer[:, None], more[j - 1], best)
            best_gap = jnp.where(nearer, gap[j], best_gap)
        return jnp.concatenate([best, drawn[stop:]])

    def log_prob(self, weights, indices, params) -> jax.Array:
        """``(B,)`` log pi of each scenario ``indices (B, P)`` under the policy ``weights``
        (with several learners, their equal mixture: what ``ask`` draws from when the learners
        divide the batch, after the first update's boundary draws)."""
        lp = self._each(lambda w: self._log_prob_one(w, indices, params))(weights)
        if self.learners == 1:
            return lp
        return jax.nn.logsumexp(lp, axis=0) - jnp.log(float(self.learners))

    def _log_prob_one(self, weights, indices, params, dist=None) -> jax.Array:
        """``(B,)`` log pi of each scenario ``indices (B, P)`` under one learner's policy
        ``weights`` (``dist``: the policy's ``module.apply``, when already computed)."""
        mix, mu, log_sigma = self.module.apply({"params": weights}) if dist is None else dist
        return discretised.log_prob(mix, mu, log_sigma, indices, self.shape, params.eps)

    def tell(self, key, state, indices, rewards, params):
        return self._learn(key, state, indices, rewards, jnp.zeros(rewards.shape, bool),
                           params)[0]

    def tell_outcome(self, key, state, indices, rewards, robustness, collision, params,
                     ttc=None):
        h = self._hash(indices)
        signal = self._signal(state, h, rewards, robustness, collision, params, ttc)
        hit = collision & jnp.isfinite(rewards)
        state, elite = self._learn(key, state, indices, signal, hit, params)
        # remembered: this update's elite and its collisions (a later draw of one of them
        # counts less, see signal)
        keep = hit | elite
        slot = (h & (self.table - 1)).astype(jnp.int32)
        new = jnp.where(keep, h, state.seen[slot])
        return dataclasses.replace(state, seen=state.seen.at[slot].set(new))

    def signal(self, state, indices, rewards, robustness, collision, params, ttc=None):
        """``(B,)`` what the update ranks: the shaped signal (near misses told apart by their
        minimum TTC ``ttc (B,)`` [s] when given), less ``novelty`` for a collision, and less
        ``revisit`` for a non-collision, whose scenario the seen table holds (one that was in
        an earlier update's elite, or collided), as long as fewer than ``novelty_until``
        evaluations were told. A hash collision in the table can make an unseen scenario
        count as seen: rare with a table much larger than the scenarios it holds."""
        return self._signal(state, self._hash(indices), rewards, robustness, collision, params,
                            ttc)

    def _signal(self, state, h, rewards, robustness, collision, params, ttc):
        if ttc is not None:
            robustness = near_miss_ttc(robustness, ttc, params.ttc_weight, params.ttc_below)
        signal = shaped_signal(rewards, robustness, collision)
        seen = state.seen[(h & (self.table - 1)).astype(jnp.int32)] == h
        seen &= state.told < params.novelty_until
        return jnp.where(seen, signal - jnp.where(collision, params.novelty, params.revisit),
                         signal)

    def _hash(self, indices) -> jax.Array:
        """``(B,)`` uint32 hash of each scenario's index vector, never 0 (0 marks an empty
        slot)."""
        h = jnp.full(indices.shape[:1], 2166136261, jnp.uint32)
        for p in range(self.n_params):  # FNV-1a over the parameters' indices
            h = (h ^ indices[:, p].astype(jnp.uint32)) * jnp.uint32(16777619)
        return jnp.maximum(h, 1)

    @property
    def share(self) -> int:
        """Scenarios each learner draws per update: ``ceil(batch / learners)``."""
        return -(-self.batch // self.learners)

    @property
    def top(self) -> int:
        """Scenarios of each learner's share of the batch it learns from: the ``elite`` best
        share."""
        return max(1, min(self.share, round(self.elite * self.share)))

    def _learn(self, key, state, indices, signal, collided, params):
        """``(state, elite (B,) bool)``: each learner's update (:meth:`_learn_one`) on the elite
        of its own share of the batch (a padded share's missing draws have signal -inf, never
        elite) while fewer than ``novelty_until`` evaluations were told; from then on every
        learner's on the elite of the whole batch (the same ``top`` scenarios for all), each
        starting, at the first such update, from the learner whose share scored best on
        average: all converge on the best failures found rather than each on its own
        share's."""
        together_now = state.told >= params.novelty_until
        found = state.found | jnp.any(self._shares(collided, False), axis=-1)
        if self.learners > 1:  # learning together, a collision found by one is found by all
            found |= together_now & jnp.any(found)
        # the learning rate of each learner: lr once it has a collision; before, lr_first at
        # the first update for learners below first_learners, else lr_search
        bold = (state.told == 0) & (jnp.arange(self.learners) < params.first_learners)
        lr = jnp.where(found, params.lr, jnp.where(bold, params.lr_first, params.lr_search))

        shares = self._shares(signal, -jnp.inf)

        def own(_):
            elite, w, at, best = self._each(self.pick_elite)(
                self._keys(key), self._shares(indices), shares)
            mask = self._each(lambda a, b: jnp.zeros(self.share, bool).at[a].set(
                jnp.isfinite(b)))(at, best)
            return elite, w, mask.reshape(-1)[:self.batch]

        def together(_):
            elite, w, at, best = self.pick_elite(jax.random.fold_in(key, self.learners),
                                                 indices, signal)
            mask = jnp.zeros(self.batch, bool).at[at].set(jnp.isfinite(best))
            L = self.learners
            return (jnp.broadcast_to(elite, (L, *elite.shape)),
                    jnp.broadcast_to(w, (L, *w.shape)), mask)

        weights, opt = self._weights(state), state.opt
        if self.learners == 1:
            elite, w, mask = own(None)
            lr = lr[0]
        else:
            elite, w, mask = jax.lax.cond(together_now, together, own, None)
            # at the first update together, every learner starts from the one whose share
            # scored best on average (a learner whose components lie far from the elite gets
            # a gradient that underflows to 0 and would never move)
            first = together_now & (state.told - self.batch < params.novelty_until)

            def from_best(t):  # (computed at that update only)
                ok = jnp.isfinite(shares)
                score = jnp.sum(jnp.where(ok, shares, 0.0), axis=1) / jnp.maximum(
                    jnp.sum(ok, axis=1), 1)
                best = jnp.argmax(jnp.where(jnp.any(ok, axis=1), score, -jnp.inf))
                return jax.tree.map(lambda x: jnp.broadcast_to(x[best], x.shape), t)

            weights, opt = jax.lax.cond(first, from_best, lambda t: t, (weights, opt))
        weights, opt = self._each(
            lambda wt, o, e, ew, r: self._learn_one(wt, o, e, ew, params, r))(
            weights, opt, elite, w, lr)
        return dataclasses.replace(state, params=weights, opt=opt, told=state.told + self.batch,
                                   found=found, ready=jnp.bool_(True)), mask

    def pick_elite(self, key, indices, signal):
        """One learner's elite: ``(scenarios (S, P), weights (S,), at (top,), best (top,))``,
        the ``top`` best scenarios of its share ``indices (share, P)`` by ``signal (share,)``
        (near ties broken at random by ``key``; ``at`` their positions in the share, ``best``
        their signals, -inf where fewer were finite) and CMA-ES's log-rank weights summing to
        1 (0 for a non-finite signal). ``S`` is ``top`` rounded up to a multiple of 8, the
        extra scenarios weighing 0: they add exact zeros to the loss and its gradient, and on
        XLA CPU the log-probabilities' loops over the elite (innermost) cost more with a
        remainder past the 8-wide vectors than padded (the controller's update at batch 4096,
        four learners' 102 scenarios: 2.16 ms, padded to 104: 1.94 ms)."""
        ok = jnp.isfinite(signal)
        noise = jax.random.uniform(key, signal.shape, maxval=1e-6)  # ties at random
        best, at = jax.lax.top_k(jnp.where(ok, signal + noise * jnp.abs(signal), -jnp.inf),
                                 self.top)
        ranks = jnp.arange(self.top, dtype=jnp.float32)
        w = jnp.log(self.top + 0.5) - jnp.log(ranks + 1.0)
        w = jnp.where(jnp.isfinite(best), w, 0.0)
        w = w / jnp.maximum(jnp.sum(w), 1e-30)
        pad = -self.top % 8
        return indices[jnp.pad(at, (0, pad))], jnp.pad(w, (0, pad)), at, best

    def loss(self, weights, elite, w, params):
        """One learner's loss: ``-sum_j w_j log pi(a_j) - entropy x mean log sigma`` over its
        elite (:meth:`pick_elite`): REINFORCE (Eq. 2) with non-negative rank utilities and
        baseline 0 (unbiased for any constant baseline); the scenarios below the top have
        utility 0 and drop out of the sum."""
        dist = self.module.apply({"params": weights})
        lp = self._log_prob_one(weights, elite, params, dist)
        return -jnp.sum(w * lp) - params.entropy * jnp.mean(dist[2])

    def _learn_one(self, weights, opt, elite, w, params, lr):
        """``(weights, opt)`` of one learner: ``steps`` Adam steps on :meth:`loss` over the
        elite ``elite (S, P)`` with weights ``w (S,)`` (:meth:`pick_elite`)."""

        def adam_step(carry, _):
            weights, opt = carry
            grads = jax.grad(self.loss)(weights, elite, w, params)
            updates, opt = optax.scale_by_adam().update(grads, opt, weights)
            updates = jax.tree.map(lambda u: -lr * u, updates)
            return (optax.apply_updates(weights, updates), opt), None

        (weights, opt), _ = jax.lax.scan(adam_step, (weights, opt), None, length=self.steps)
        return weights, opt
