"""An autoregressive LSTM controller over a discrete space (the NAS controller of Zoph & Le,
2017, that the paper's controller descends from): one LSTM step per parameter, each step
conditioned on the values already chosen, so the joint distribution need not factorise (it can
put its mass on a diagonal band of ``(ego_offset, ped_speed)``, which per-parameter softmax heads
cannot).

Step ``p`` (parameters in the space's order) reads ``x_p = [onehot_P(p), m_p * (2 r - 1)]``:
which parameter is chosen now, and the value ranks ``r in [0, 1]`` of the parameters chosen
before it (``m_p[q] = q < p``; the NAS controller feeds the previous choice, this feeds all
earlier ones, which the LSTM would otherwise have to remember). One LSTM layer (tanh, ``hidden``
units) turns it into ``h_p``; the logits over parameter p's values ``v`` (rank ``r_v``) are

    logits_p(v) = (h_p W_p + b_p)[v] - (r_v - mu_p)^2 / (2 sigma_p^2),
    mu_p = sigmoid(h_p . a_p + c_p),  sigma_p = exp(clip(h_p . s_p + d_p, ln s_min, 1)),

a free softmax head plus a Gaussian bump over the value ranks. The bump lets what is learnt
about one value carry to its neighbours (the search moves towards a failure region as an
evolution strategy's mean would, instead of value by value); the free head sharpens onto the
individual values that fail. The bump is at least ``s_min`` of the range wide
(``log_sigma_min``; by default 0.05, the strategies' ``sigma_min`` option, e.g. 0.001 in
``reinforce/screened``) and never narrower than half a value step (a narrower one would move its
mass wholesale from value to value as its mean drifts). Heads start at zero
(``sigma = 1``): the first proposals are close to uniform. Weights are padded to the widest
parameter; on spaces with a few wide parameters (:func:`unrolled`) the steps are unrolled and
each head computed over its own values only, elsewhere they are scanned and padded values get
logit ``MASKED`` (probability exactly 0); :func:`conditionals` pads with exact zeros.

Weights are a dict of arrays (Glorot-uniform LSTM kernels, forget-gate bias 1, zero heads), so
many controllers stack along a leading axis and are vmapped.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.search.base import categorical_from_uniform, value_mask
from jaxfalsify.search.controller import MASKED, glorot, lstm_step, mm

__all__ = [
    "LOG_SIGMA_MIN", "init", "LOCAL_STEPS", "unrolled", "padded", "over_params", "sample",
    "log_prob_and_entropy"
]

LOG_SIGMA_MIN = float(np.log(0.05))


def value_ranks(shape: tuple[int, ...]) -> jax.Array:
    """``(P, max_n)`` each value's rank scaled to [0, 1] (0 for a one-value parameter)."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return jnp.arange(max(shape), dtype=jnp.float32)[None, :] / span[:, None]


def init(key, shape: tuple[int, ...], hidden: int = 32, anchored: bool = False) -> dict:
    """Controller weights; ``anchored`` adds the inputs and heads of an anchor (see
    :func:`head_logits`)."""
    P, width = len(shape), max(shape)
    n_in = 4 * P + 1 if anchored else 2 * P
    w, u = glorot(key, [(n_in, 4 * hidden), (hidden, 4 * hidden)])
    b = jnp.zeros(4 * hidden, jnp.float32).at[hidden:2 * hidden].set(1.0)
    z = lambda *s: jnp.zeros(s, jnp.float32)  # noqa: E731
    out = {"lstm": {"w": w, "u": u, "b": b},
           "head": {"w": z(P, hidden, width), "b": z(P, width)},
           "mu": {"w": z(P, hidden), "b": z(P)},
           "sigma": {"w": z(P, hidden), "b": z(P)}}
    if anchored:
        out["delta"] = {"w": z(P, hidden), "b": z(P)}
        out["local"] = {"b": jnp.asarray(_local_log_sigma(shape), jnp.float32)}
        out["stay"] = {"w": z(P, hidden), "b": jnp.asarray(_stay_bias(shape), jnp.float32)}
    return out


LOCAL_STEPS = 1.5  # initial width of an anchored bump, in value steps
MOVES = 1.0  # initial expected number of parameters an anchored draw changes


def _local_log_sigma(shape) -> np.ndarray:
    return np.log(LOCAL_STEPS / np.maximum(np.asarray(shape, np.float64) - 1, 1.0))


def _stay_bias(shape) -> np.ndarray:
    """The stay logit that gives each parameter with two or more values the probability
    ``1 - MOVES / (their number)`` of keeping the anchor's value under the initial bump."""
    n = np.asarray(shape)
    movable = max(int(np.sum(n > 1)), 1)
    p_stay = 1.0 - min(MOVES / movable, 0.5)
    out = np.zeros(len(shape))
    for p, k in enumerate(n):
        if k > 1:  # mass of the initial bump off the anchor (anchor in the middle), relative
            d = np.arange(1, k)
            z = 2.0 * np.sum(np.exp(-0.5 * (d / LOCAL_STEPS) ** 2))
            out[p] = np.log(p_stay / (1.0 - p_stay) * z)
    return out


def step_input(p: jax.Array, chosen: jax.Array, n_params: int, anchor=None) -> jax.Array:
    """``x_p`` from the step ``p`` and the ranks ``chosen (P,)`` of the values so far
    (entries ``q >= p`` are ignored): ``(2P,)``; with ``anchor = (ranks (P,), present)``
    also the anchor's ranks (zeros if absent), which earlier parameters left the anchor's
    value, and the presence flag: ``(4P + 1,)``."""
    q = jnp.arange(n_params)
    x = [(q == p).astype(jnp.float32), jnp.where(q < p, 2.0 * chosen - 1.0, 0.0)]
    if anchor is not None:
        ranks, present = anchor
        moved = present & (q < p) & (jnp.abs(chosen - ranks) > 1e-6)
        x += [jnp.where(present, 2.0 * ranks - 1.0, 0.0), moved.astype(jnp.float32),
              jnp.atleast_1d(present.astype(jnp.float32))]
    return jnp.concatenate(x)


def head_logits(w: dict, p, h: jax.Array, shape: tuple[int, ...],
                log_sigma_min=LOG_SIGMA_MIN, anchor=None) -> jax.Array:
    """Logits of parameter ``p`` from the LSTM output ``h (H,)``: ``(shape[p],)`` over its own
    values when ``p`` is a Python int, else (``p`` traced) ``(max_n,)`` with the padded values
    at ``MASKED`` (probability exactly 0). The bump is at least ``exp(log_sigma_min)`` of the
    range wide. With an anchor present the bump is centred on the anchor's rank plus a learnt
    offset, ``a_p + 0.5 tanh(h . e_p + f_p)``, its log-width gains a learnt bias (starting at
    ``LOCAL_STEPS`` value steps), and the anchor's own value a learnt *stay* logit (starting
    where about ``MOVES`` parameters change per draw): a learnt local move around a good
    scenario, one or two parameters at a time (the paper's controller, too, reads the previous
    action)."""
    own = isinstance(p, int)
    n = shape[p] if own else max(shape)
    free = mm(h, w["head"]["w"][p][:, :n]) + w["head"]["b"][p][:n]
    mu = jax.nn.sigmoid(mm(h, w["mu"]["w"][p]) + w["mu"]["b"][p])
    log_sigma = mm(h, w["sigma"]["w"][p]) + w["sigma"]["b"][p]
    r = value_ranks(shape)[p, :n]
    stay = 0.0
    if anchor is not None:
        ranks, present, zoom, edge_mass = anchor
        local = ranks[p] + 0.5 * jnp.tanh(mm(h, w["delta"]["w"][p]) + w["delta"]["b"][p])
        mu = jnp.where(present, local, mu)
        log_sigma = jnp.where(present, log_sigma + w["local"]["b"][p] + zoom[p], log_sigma)
        at = jnp.abs(r - ranks[p]) < 1e-6  # the anchor's own value
        stay = jnp.where(present & at, mm(h, w["stay"]["w"][p]) + w["stay"]["b"][p], 0.0)
    # never narrower than half a value step (a one-value parameter: any width)
    floor = jnp.maximum(log_sigma_min, jnp.log(0.5 / jnp.maximum(
        jnp.asarray(shape, jnp.float32)[p] - 1, 1.0)))
    sigma = jnp.exp(jnp.clip(log_sigma, floor, 1.0))
    bump = -0.5 * jnp.square((r - mu) / sigma)
    if anchor is not None:
        bump = jnp.where(present & (edge_mass > 0),
                         _edge_clipped(bump, mu, sigma, edge_mass, shape, p, n), bump)
    logits = free + bump + stay
    return logits if own else jnp.where(value_mask(shape)[p], logits, MASKED)


def _edge_clipped(bump, mu, sigma, edge_mass, shape, p, n):
    """An anchored bump whose first / last value also takes ``edge_mass`` of the Gaussian's
    mass beyond that bound (a move past a bound stops at it; 0: the bump is renormalised
    inside the box). Log-mass relative to a value's own mass ``step * density``; one-value
    parameters unchanged."""
    span = jnp.maximum(jnp.asarray(shape, jnp.float32)[p] - 1, 1.0)
    half = 0.5 / span
    log_own = jnp.log(2 * half / (sigma * np.sqrt(2 * np.pi)))
    log_w = jnp.log(jnp.maximum(edge_mass, 1e-30))
    lo = jax.scipy.special.log_ndtr((-half - mu) / sigma) - log_own + log_w
    hi = jax.scipy.special.log_ndtr((mu - 1.0 - half) / sigma) - log_own + log_w
    v = jnp.arange(n)
    last = jnp.asarray(shape, jnp.int32)[p] - 1
    tail = jnp.where(v == 0, lo, jnp.where(v == last, hi, -1e30))  # inner values: + 0
    return jnp.where(span > 1, jnp.logaddexp(bump, tail), bump)


UNROLL_ABOVE = 1024  # padded head values (P x the widest parameter's values) above which the
# controller's steps are unrolled, each head at its own width


def unrolled(shape: tuple[int, ...]) -> bool:
    """Whether :func:`over_params` unrolls the steps (heads at their own widths: less work per draw
    on spaces with a few wide parameters, a larger program to load) or scans them (heads
    padded to the widest parameter)."""
    return len(shape) * max(shape) > UNROLL_ABOVE


def padded(x: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """A parameter's ``(n,)`` vector padded with zeros to the widest parameter ``(max_n,)``."""
    return jnp.pad(x, (0, max(shape) - x.shape[0]))


def _anchor_ranks(anchor, shape):
    """``(indices (P,), present[, zoom (P,)[, edge_mass]])`` -> ``(ranks (P,) in [0, 1],
    present, zoom (P,), edge_mass)`` (zoom and edge_mass 0 when not given), or None."""
    if anchor is None:
        return None
    idx, present = anchor[0], anchor[1]
    zoom = anchor[2] if len(anchor) > 2 else jnp.zeros(len(shape), jnp.float32)
    edge_mass = anchor[3] if len(anchor) > 3 else jnp.float32(0.0)
    span = jnp.maximum(jnp.asarray(shape, jnp.float32) - 1, 1.0)
    return idx.astype(jnp.float32) / span, jnp.asarray(present), zoom, edge_mass


def over_params(w: dict, shape: tuple[int, ...], step_fn, xs, log_sigma_min=LOG_SIGMA_MIN,
                anchor=None):
    """Run the controller over the P parameters for one scenario; ``step_fn(p, logits, x)``
    returns ``(value index, output)`` where ``x`` is that step's per-scenario input; the
    outputs are stacked ``(P, ...)``. ``anchor``: ``(indices (P,), present[, zoom (P,)])`` for
    an anchored controller. Where :func:`unrolled`, ``p`` is a Python int and ``logits`` has
    the parameter's own width (a loop over the controller's structure, not over data); else a
    ``lax.scan`` with ``p`` traced and ``logits (max_n,)``."""
    P = len(shape)
    hidden = w["lstm"]["u"].shape[0]
    ranks = value_ranks(shape)
    anc = _anchor_ranks(anchor, shape)

    def one(carry, p, x):
        h, c, chosen = carry
        h, c = lstm_step(w["lstm"], (h, c), step_input(p, chosen, P, None if anc is None
                                                       else anc[:2]), activation=jnp.tanh)
        logits = head_logits(w, p, h, shape, log_sigma_min, anc)
        a, out = step_fn(p, logits, x)
        return (h, c, chosen.at[p].set(ranks[p, a])), out

    carry = (jnp.zeros(hidden), jnp.zeros(hidden), jnp.zeros(P))
    if not unrolled(shape):
        return jax.lax.scan(lambda c, inp: one(c, *inp), carry, (jnp.arange(P), xs))[1]
    outs = []
    for p in range(P):
        carry, out = one(carry, p, xs[p])
        outs.append(out)
    return jax.tree.map(lambda *o: jnp.stack(o), *outs)


def sample(w: dict, u: jax.Array, shape: tuple[int, ...],
           log_sigma_min=LOG_SIGMA_MIN, anchor=None) -> jax.Array:
    """One scenario ``(P,)`` int32 from uniforms ``u (P,)`` in [0, 1) (inverse CDF, step by
    step: each value is drawn given the ones before it)."""
    def step_fn(p, logits, up):
        a = categorical_from_uniform(up, jax.nn.softmax(logits))
        return a, a

    return over_params(w, shape, step_fn, u, log_sigma_min, anchor)


def log_prob_and_entropy(w: dict, action: jax.Array, shape: tuple[int, ...],
                         log_sigma_min=LOG_SIGMA_MIN, anchor=None):
    """``(log pi(action), sum_p H(pi_p( . | action_<p)))`` of one scenario ``action (P,)``: the
    log-probability sums each step's log-softmax at the chosen value given the values before
    it; the entropy is that of each step's conditional at the same prefix [nats]."""
    def step_fn(p, logits, a):
        lp = jax.nn.log_softmax(logits)
        return a, (lp[a], -jnp.sum(jnp.exp(lp) * lp))

    lp, ent = over_params(w, shape, step_fn, action, log_sigma_min, anchor)
    return jnp.sum(lp), jnp.sum(ent)


def conditionals(w: dict, action: jax.Array, shape: tuple[int, ...],
                 log_sigma_min=LOG_SIGMA_MIN, anchor=None) -> jax.Array:
    """``(P, max_n)`` the probabilities of every parameter's values given ``action``'s values
    before it (row 0 is the first parameter's marginal)."""
    def step_fn(p, logits, a):
        return a, padded(jax.nn.softmax(logits), shape)

    return over_params(w, shape, step_fn, action, log_sigma_min, anchor)
