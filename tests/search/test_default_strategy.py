"""reinforce/default: the Flax LSTM controller's mixture of discretised logistics and its
REINFORCE update, each against an independent oracle (float64 NumPy step by step, exact
enumeration of a tiny space, the exact gradient of the expected reward)."""

from __future__ import annotations

import dataclasses
import itertools
import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfalsify import search
from jaxfalsify.base import pytree
from jaxfalsify.search import base, batched, discretised

SHAPE = (4, 1, 3, 5)  # a one-value parameter too


def _np_cdf(x):
    """The standard logistic CDF in float64."""
    return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def _np_bin_mass(v, n, mu, sigma):
    """Float64 mass of value ``v`` of ``n`` under a logistic distribution over ranks truncated
    to the tiled interval (the module docstring's formula, written out)."""
    if n == 1:
        return 1.0
    h = 0.5 / (n - 1)
    r = v / (n - 1)
    num = _np_cdf((r + h - mu) / sigma) - _np_cdf((r - h - mu) / sigma)
    den = _np_cdf((1 + h - mu) / sigma) - _np_cdf((-h - mu) / sigma)
    return num / den


def _np_sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def _np_controller(params, shape, hidden, K):
    """The MixtureController step by step in float64: the LSTM equations (gates i, f, g, o,
    tanh), the shared head scaled by 0.1 plus the per-parameter bias, the mixture head."""
    f = lambda x: np.asarray(x, np.float64)  # noqa: E731
    w, u, b = f(params["lstm"]["w"]), f(params["lstm"]["u"]), f(params["lstm"]["b"])
    hw, hb = f(params["head"]["w"]), f(params["head"]["b"])
    bias = f(params["bias"])
    P = len(shape)
    h, c, prev, outs = np.zeros(hidden), np.zeros(hidden), np.zeros(2 * K), []
    for p in range(P):
        x = np.concatenate([np.eye(P)[p], prev])
        z = x @ w + h @ u + b
        i, fg, g, o = np.split(z, 4)
        c = _np_sigmoid(fg) * c + _np_sigmoid(i) * np.tanh(g)
        h = _np_sigmoid(o) * np.tanh(c)
        prev = 0.1 * (h @ hw + hb) + bias[p]
        outs.append(prev)
    z = np.stack(outs, axis=1)
    mix = 0.1 * (h @ f(params["mix"]["w"]) + f(params["mix"]["b"]))
    n = np.asarray(shape, np.float64)
    half = 0.5 / np.maximum(n - 1, 1)
    mu = -half + (1 + 2 * half) * _np_sigmoid(z[:K])
    lo = np.log(batched.SIGMA_MIN_STEPS / np.maximum(n - 1, 1))
    log_sigma = lo + (batched.LOG_SIGMA_MAX - lo) * _np_sigmoid(z[K:])
    return mix, mu, log_sigma


def _np_log_prob(mix, mu, log_sigma, a, shape, eps):
    w = np.exp(mix - mix.max())
    w /= w.sum()
    comp = sum(w[k] * np.prod([_np_bin_mass(a[p], shape[p], mu[k, p], math.exp(log_sigma[k, p]))
                               for p in range(len(shape))]) for k in range(len(w)))
    return math.log((1 - eps) * comp + eps / np.prod(shape))


def _moved(learners, init_seed, move_seed):
    """A small reinforce/default on SHAPE whose every weight is moved off its initial value,
    so the LSTM and heads all matter."""
    s, p = search.make("reinforce/default", SHAPE, 64, hidden=8, components=3,
                       learners=learners)

    @jax.jit  # one compiled program (op by op, the initialisation compiles hundreds)
    def init():
        state = s.init(jax.random.key(init_seed), p)
        leaves, tree = jax.tree.flatten(state.params)
        keys = jax.random.split(jax.random.key(move_seed), len(leaves))
        moved = [x + 0.3 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)]
        return dataclasses.replace(state, params=jax.tree.unflatten(tree, moved))

    return s, p, init()


@pytest.fixture(scope="module")
def strat():
    return _moved(1, 0, 1)


def _every(shape):
    return np.array(list(itertools.product(*[range(n) for n in shape])), np.int32)


def test_controller_and_log_probs_match_numpy_step_by_step(strat):
    s, p, state = strat
    mix, mu, log_sigma = (np.asarray(x, np.float64) for x in jax.jit(s.distribution)(state))
    e_mix, e_mu, e_ls = _np_controller(state.params, SHAPE, 8, 3)
    np.testing.assert_allclose(mix, e_mix, atol=1e-5)
    np.testing.assert_allclose(mu, e_mu, atol=1e-5)
    np.testing.assert_allclose(log_sigma, e_ls, atol=1e-5)
    acts = _every(SHAPE)[::7]
    got = np.asarray(jax.jit(s.log_prob)(state.params, jnp.asarray(acts), p), np.float64)
    want = [_np_log_prob(e_mix, e_mu, e_ls, a, SHAPE, float(p.eps)) for a in acts]
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_probabilities_sum_to_one_and_sampling_matches_them(strat):
    s, p, state = strat
    every = _every(SHAPE)
    prob = np.exp(np.asarray(jax.jit(s.log_prob)(state.params, jnp.asarray(every), p), np.float64))
    assert prob.sum() == pytest.approx(1.0, abs=1e-5)
    # 200,000 draws from ask: each scenario's frequency within 5 standard errors
    big = s.__class__(**{**s.__dict__, "batch": 200_000})
    own = pytree.replace(p, boundary=0.0)  # the policy's own draws at the first update too
    idx, _ = jax.jit(lambda k: big.ask(k, state, own))(jax.random.key(7))
    flat = np.ravel_multi_index(np.asarray(idx).T, SHAPE)
    freq = np.bincount(flat, minlength=len(every)) / len(flat)
    order = np.ravel_multi_index(every.T, SHAPE)
    se = np.sqrt(prob * (1 - prob) / len(flat))
    assert np.all(np.abs(freq[order] - prob) <= 5 * se + 1e-6)
    assert np.all(np.asarray(idx)[:, 1] == 0)


@pytest.mark.parametrize("learners", [1, 3])
def test_later_updates_draw_as_the_first_update_does_without_boundary(learners):
    """Both branches of the first update's cond draw the policy's scenarios: a later update
    (``told`` > 0) draws the same scenarios from the same key and policy as the first update
    with ``boundary`` 0, whose draws follow the policy's probabilities (tested above); one
    learner (no learner axis) and three that do not divide the batch."""
    s, p, state = _moved(learners, 0, 1)
    big = s.__class__(**{**s.__dict__, "batch": 20_000})
    own = pytree.replace(p, boundary=0.0)
    ask = jax.jit(big.ask)
    first = np.asarray(ask(jax.random.key(5), state, own)[0])
    later = dataclasses.replace(state, told=jnp.int32(big.batch))
    np.testing.assert_array_equal(np.asarray(ask(jax.random.key(5), later, own)[0]), first)
    assert first.shape == (20_000, len(SHAPE))


def test_marginals_table_matches_enumeration(strat):
    s, p, state = strat
    every = _every(SHAPE)
    prob = np.exp(np.asarray(jax.jit(s.log_prob)(state.params, jnp.asarray(every), p), np.float64))
    table = np.asarray(jax.jit(s.probs)(state, p), np.float64)
    for q, n in enumerate(SHAPE):
        want = np.array([prob[every[:, q] == v].sum() for v in range(n)])
        np.testing.assert_allclose(table[q, :n], want, atol=1e-5)
        assert np.all(table[q, n:] == 0)


@pytest.mark.parametrize("lo, hi", [(60.0, 60.5), (-70.0, -69.0), (20.0, 20.01)])
def test_log_mass_keeps_far_tails(lo, hi):
    """A bin far out in either tail keeps its (tiny, finite) mass, where ``1 - S(x)`` rounds
    to 0 in float32: CDF differences are taken in the tail where both bounds lie (oracle: the
    float64 CDF, with ``S(hi) - S(lo) = S(-lo) - S(-hi)`` for the upper tail, exact in float64 at
    these sizes)."""
    got = float(discretised.log_mass(jnp.float32(lo), jnp.float32(hi)))
    mass = _np_cdf(-lo) - _np_cdf(-hi) if lo > 0 else _np_cdf(hi) - _np_cdf(lo)
    want = math.log(mass)
    assert math.isfinite(got)
    assert got == pytest.approx(want, abs=2e-3 * abs(want) + 1e-3)


@pytest.mark.parametrize("shape", [(7, 1, 40, 3, 1000), (3,) * 18 + (1,)])
def test_mixture_gradient_matches_automatic_differentiation(shape):
    """log_prob's written-out gradient (and value) against JAX's automatic differentiation of
    the plain expression (log_probs_by_component, one logarithm per parameter), including
    one-value parameters and more than 16 parameters (products taken in groups)."""
    P, K = len(shape), 6
    k = jax.random.split(jax.random.key(0), 5)
    mix = jax.random.normal(k[0], (K,))
    mu = jax.random.uniform(k[1], (K, P), minval=-0.05, maxval=1.05)
    lo = np.log(batched.SIGMA_MIN_STEPS / np.maximum(np.asarray(shape) - 1, 1))
    log_sigma = lo + (batched.LOG_SIGMA_MAX - lo) * jax.random.uniform(k[2], (K, P))  # the
    # controller's range: from 0.1 value steps to the whole range
    acts = jax.random.randint(k[3], (50, P), 0, jnp.asarray(shape))
    w = jax.random.uniform(k[4], (50,))
    eps = 0.01
    log_uniform = -float(np.sum(np.log(np.asarray(shape, np.float64))))

    def plain(mix, mu, log_sigma):
        comp = jax.nn.log_softmax(mix)[:, None] + discretised.log_probs_by_component(
            mu, log_sigma, acts, shape)
        return jnp.logaddexp(jnp.log1p(-eps) + jax.nn.logsumexp(comp, axis=0),
                             jnp.log(eps) + log_uniform)

    def fast(mix, mu, log_sigma):
        return discretised.log_prob(mix, mu, log_sigma, acts, shape, eps)

    np.testing.assert_allclose(jax.jit(fast)(mix, mu, log_sigma),
                               jax.jit(plain)(mix, mu, log_sigma), rtol=1e-5, atol=1e-4)
    want = jax.jit(jax.grad(lambda *a: jnp.sum(w * plain(*a)), argnums=(0, 1, 2)))(
        mix, mu, log_sigma)
    got = jax.jit(jax.grad(lambda *a: jnp.sum(w * fast(*a)), argnums=(0, 1, 2)))(
        mix, mu, log_sigma)
    for g, x in zip(got, want):
        np.testing.assert_allclose(g, x, rtol=1e-4, atol=1e-4 * float(jnp.max(jnp.abs(x))))


@pytest.mark.parametrize("batch, elite", [(60, 0.1), (200, 0.08)])
def test_the_padded_elite_gives_the_loss_and_gradient_of_its_top_scenarios(batch, elite):
    """A learner's elite of 6 (or 16) scenarios, padded to 8 (16) with weight 0, gives the
    loss and the gradient of its top scenarios alone (oracle: NumPy's ranking of the signal,
    CMA-ES's log-rank weights, and JAX's automatic differentiation of the plain expression,
    ``log_probs_by_component`` mixed by ``logsumexp`` over the unpadded top)."""
    shape = (7, 1, 40, 3, 1000)
    s, p = search.make("reinforce/default", shape, batch, learners=1, elite=elite)
    top = round(elite * batch)
    assert s.top == top
    g = np.random.default_rng(3)
    idx = jnp.asarray(g.integers(0, shape, (batch, len(shape))), jnp.int32)
    signal = jnp.asarray(g.permutation(batch) * 0.01 - 0.3, jnp.float32)  # no ties
    weights = s.init(jax.random.key(0), p).params
    picked, w, at, _ = jax.jit(s.pick_elite)(jax.random.key(1), idx, signal)
    assert picked.shape[0] == -(-top // 8) * 8
    order = np.argsort(-np.asarray(signal))[:top]
    np.testing.assert_array_equal(np.asarray(at), order)
    np.testing.assert_array_equal(np.asarray(picked)[:top], np.asarray(idx)[order])
    np.testing.assert_array_equal(np.asarray(w)[top:], 0.0)
    rank_w = np.log(top + 0.5) - np.log(np.arange(1, top + 1))
    np.testing.assert_allclose(np.asarray(w)[:top], rank_w / rank_w.sum(), rtol=1e-5, atol=1e-7)

    def plain(weights):
        mix, mu, log_sigma = s.module.apply({"params": weights})
        comp = jax.nn.log_softmax(mix)[:, None] + discretised.log_probs_by_component(
            mu, log_sigma, idx[order], shape)
        lp = jnp.logaddexp(jnp.log1p(-p.eps) + jax.nn.logsumexp(comp, axis=0),
                           jnp.log(p.eps) - float(np.sum(np.log(shape))))
        return -jnp.sum(jnp.asarray(rank_w / rank_w.sum(), jnp.float32) * lp) \
            - p.entropy * jnp.mean(log_sigma)

    got, want = jax.jit(s.loss)(weights, picked, w, p), jax.jit(plain)(weights)
    assert float(got) == pytest.approx(float(want), rel=1e-5)
    for x, y in zip(jax.tree.leaves(jax.jit(jax.grad(s.loss))(weights, picked, w, p)),
                    jax.tree.leaves(jax.jit(jax.grad(plain))(weights))):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-4 * float(jnp.max(jnp.abs(y))))


@pytest.mark.parametrize("v, at", [(494, 500), (507, 500), (500, 500.3)])
def test_a_bin_far_in_a_tail_keeps_its_mass(v, at):
    """A narrow component (0.1 value steps, located at value ``at``) puts on a value 6-7
    steps away a mass of about e^-60, where CDF differences round to 0 in float32: the closed
    form keeps it (oracle: the float64 CDF difference taken in the tail where the bin lies)."""
    shape, sigma, mu = (1000,), 0.1 / 999, at / 999
    got = float(discretised.log_probs_by_component(
        jnp.asarray([[mu]], jnp.float32), jnp.asarray([[math.log(sigma)]], jnp.float32),
        jnp.asarray([[v]]), shape)[0, 0])
    h, r = 0.5 / 999, v / 999
    lo, hi = (r - h - mu) / sigma, (r + h - mu) / sigma
    mass = _np_cdf(-lo) - _np_cdf(-hi) if lo > 0 else _np_cdf(hi) - _np_cdf(lo)
    norm = _np_cdf((1 + h - mu) / sigma) - _np_cdf((-h - mu) / sigma)
    want = math.log(mass / norm)
    assert got == pytest.approx(want, rel=1e-4, abs=1e-3)


def test_cost_does_not_grow_with_the_number_of_values():
    """The distribution has the same parameters for 10 or 4,000 values per parameter: its
    size (and a scenario's log-probability's work) does not depend on the values."""
    a, pa = search.make("reinforce/default", (10,) * 5, 16)
    b, pb = search.make("reinforce/default", (4000,) * 5, 16)
    sa = jax.tree.map(jnp.shape, jax.eval_shape(a.init, jax.random.key(0), pa).params)
    sb = jax.tree.map(jnp.shape, jax.eval_shape(b.init, jax.random.key(0), pb).params)
    assert sa == sb


def test_reinforce_gradient_estimate_matches_exact_gradient_of_expected_reward(strat):
    """grad E_pi[R] = sum_a pi(a) R(a) grad log pi(a) (Eq. 3), by exact enumeration of the
    60 scenarios, against the estimator (1/B) sum_i R(a_i) grad log pi(a_i) averaged over
    100,000 draws: each component of the gradient within 5 standard errors."""
    s, p, state = strat
    every = jnp.asarray(_every(SHAPE))
    reward = jnp.asarray(np.random.default_rng(0).normal(size=len(every)), jnp.float32)

    def expected(w):
        return jnp.sum(jnp.exp(s.log_prob(w, every, p)) * reward)

    exact = jax.flatten_util.ravel_pytree(jax.jit(jax.grad(expected))(state.params))[0]
    table = {tuple(map(int, a)): float(r) for a, r in zip(np.asarray(every), reward)}
    flat_r = np.zeros(SHAPE, np.float32)
    for a, r in table.items():
        flat_r[a] = r
    rgrid = jnp.asarray(flat_r)
    big = s.__class__(**{**s.__dict__, "batch": 4000})

    own = pytree.replace(p, boundary=0.0)  # the policy's own draws at the first update too

    @jax.jit
    def per_sample_grads(key):
        idx, _ = big.ask(key, state, own)
        r = rgrid[tuple(idx.T)]

        def one(a, ri):
            g = jax.grad(lambda w: s.log_prob(w, a[None], p)[0])(state.params)
            return jax.flatten_util.ravel_pytree(g)[0] * ri

        g = jax.vmap(one)(idx, r)
        return jnp.sum(g, 0), jnp.sum(g * g, 0)

    tot, sq, n = 0.0, 0.0, 0
    for k in jax.random.split(jax.random.key(3), 25):
        a, b = per_sample_grads(k)
        tot, sq, n = tot + np.asarray(a, np.float64), sq + np.asarray(b, np.float64), n + 4000
    mean = tot / n
    se = np.sqrt(np.maximum(sq / n - mean**2, 0) / n)
    exact = np.asarray(exact, np.float64)
    assert np.all(np.abs(mean - exact) <= 5 * se + 1e-6), np.max(np.abs(mean - exact) / (se + 1e-9))
    assert np.max(np.abs(exact)) > 10 * np.median(se)  # the check has power


@pytest.mark.slow
def test_learns_an_interior_optimum_at_batch_1024():
    """A synthetic objective on 5 parameters x 200 values whose optimum lies inside the box
    (oracle: the known optimum); after 30 updates of 1,024, in each of three seeds, one of the
    two learners that start spread over the space draws most (> 80 %) of its share of the last
    batch within 3 value steps of it in every parameter (uniform sampling: (7/200)^5 ~ 5e-8).
    (Each spread-out learner does in about nine seeds of ten: 22 of 24 over seeds 0-11; the two
    that start at the box's vertices, for failures at its corners, may still be there: the
    batch is the learners' shares in order, 256 each.)"""
    shape = (200,) * 5
    target = jnp.array([37, 150, 99, 12, 180])
    s, p = search.make("reinforce/default", shape, 1024)
    assert s.n_vertex_learners == 2

    @jax.jit  # the key is traced: one compilation for every seed
    def loop(key):
        def one(carry, _):
            state, key = carry
            key, k1, k2 = jax.random.split(key, 3)
            idx, state = s.ask(k1, state, p)
            r = -jnp.sum(jnp.abs(idx - target), axis=-1).astype(jnp.float32)
            return (s.tell(k2, state, idx, r, p), key), idx

        k0, k1 = jax.random.split(key)
        return jax.lax.scan(one, (s.init(k0, p), k1), None, length=30)[1]

    for seed in range(3):
        idx = np.asarray(loop(jax.random.key(seed)))
        near = np.all(np.abs(idx[-1] - np.asarray(target)) <= 3, axis=-1)
        per_learner = near.reshape(s.learners, s.share).mean(axis=1)
        assert np.max(per_learner[:2]) > 0.8, (seed, per_learner, idx[-1][:5])


def test_a_collision_seen_before_counts_less():
    """After a collision is told (the batch's elite of one), the same scenario told again as
    a collision has its signal lowered by ``novelty``, and told again without a collision by
    ``revisit``; a collision not seen before, and a scenario that was neither in the elite nor
    a collision, keep the shaped signal (oracle: base.shaped_signal)."""
    s, p = search.make("reinforce/default", (50, 50), 4, learners=1)
    state = jax.jit(s.init)(jax.random.key(0), p)
    old, new, miss = jnp.array([10, 10]), jnp.array([40, 40]), jnp.array([25, 25])
    idx = jnp.stack([old, miss, miss, miss])
    r = jnp.array([0.25, -0.1, -0.1, -0.1], jnp.float32)
    col = jnp.array([True, False, False, False])
    rob = jnp.array([-1.0, 0.5, 0.5, 0.5], jnp.float32)
    state = jax.jit(s.tell_outcome)(jax.random.key(1), state, idx, r, rob, col, p)
    idx2 = jnp.stack([old, new, miss, old])
    col2 = jnp.array([True, True, False, False])
    r2 = jnp.array([0.25, 0.25, -0.1, -0.1], jnp.float32)
    rob2 = jnp.array([-1.0, -1.0, 0.5, 0.5], jnp.float32)
    got = np.asarray(jax.jit(s.signal)(state, idx2, r2, rob2, col2, p))
    want = np.array(base.shaped_signal(r2, rob2, col2))
    want[0] -= float(p.novelty)  # the collision seen before
    want[3] -= float(p.revisit)  # the same scenario, now not colliding: a revisit
    np.testing.assert_allclose(got, want, rtol=1e-6)


@pytest.fixture(scope="module")
def learners3():
    return _moved(3, 2, 3)


def test_several_learners_are_their_equal_mixture(learners3):
    """With 3 learners, a scenario's log-probability is that of the equal mixture of the 3
    controllers, each computed step by step in float64 NumPy from its own weights; the
    probabilities of every scenario sum to 1; the learners' distributions differ."""
    s, p, state = learners3
    every = _every(SHAPE)
    per = []
    for i in range(3):
        w = jax.tree.map(lambda x, i=i: x[i], state.params)
        e_mix, e_mu, e_ls = _np_controller(w, SHAPE, 8, 3)
        per.append([_np_log_prob(e_mix, e_mu, e_ls, a, SHAPE, float(p.eps)) for a in every])
    per = np.asarray(per)
    want = np.log(np.mean(np.exp(per), axis=0))
    got = np.asarray(jax.jit(s.log_prob)(state.params, jnp.asarray(every), p), np.float64)
    np.testing.assert_allclose(got, want, atol=2e-5)
    assert np.exp(got).sum() == pytest.approx(1.0, abs=1e-5)
    assert np.max(np.abs(per[0] - per[1])) > 0.1


def test_several_learners_sample_their_mixture():
    """4 learners dividing a batch of 200,000: each scenario's frequency within 5 standard
    errors of its probability under the equal mixture (oracle: the log-probabilities, which the
    test above checks against NumPy)."""
    s, p = search.make("reinforce/default", SHAPE, 200_000, hidden=8, components=3, learners=4)
    state = jax.jit(s.init)(jax.random.key(4), p)
    every = _every(SHAPE)
    prob = np.exp(np.asarray(jax.jit(s.log_prob)(state.params, jnp.asarray(every), p), np.float64))
    own = pytree.replace(p, boundary=0.0)  # the policy's own draws at the first update too
    idx, _ = jax.jit(lambda k: s.ask(k, state, own))(jax.random.key(7))
    assert idx.shape == (200_000, len(SHAPE))
    flat = np.ravel_multi_index(np.asarray(idx).T, SHAPE)
    freq = np.bincount(flat, minlength=len(every)) / len(flat)
    order = np.ravel_multi_index(every.T, SHAPE)
    se = np.sqrt(prob * (1 - prob) / len(flat))
    assert np.all(np.abs(freq[order] - prob) <= 5 * se + 1e-6)


def test_learners_that_do_not_divide_the_batch_each_learn_from_their_own_share():
    """A batch of 10 for 4 learners: shares of 3, 3, 3 and 1 (the last cut short); ask gives
    10 scenarios, and each learner's elite (the best share of 0.34 of 3 = 1) is the best of its
    own share (oracle: the argmax of each share of the signal)."""
    s, p = search.make("reinforce/default", (50, 50), 10, learners=4, elite=0.34)
    state = jax.jit(s.init)(jax.random.key(0), p)
    idx, _ = jax.jit(s.ask)(jax.random.key(1), state, p)
    assert idx.shape == (10, 2)
    signal = jnp.asarray(np.random.default_rng(5).normal(size=10), jnp.float32)
    new, elite = jax.jit(s._learn)(jax.random.key(2), state, idx, signal, jnp.zeros(10, bool),
                                   p)
    want = np.zeros(10, bool)
    for lo, hi in ((0, 3), (3, 6), (6, 9), (9, 10)):
        want[lo + int(np.argmax(np.asarray(signal)[lo:hi]))] = True
    np.testing.assert_array_equal(np.asarray(elite), want)
    assert int(new.told) == 10


def test_each_learner_searches_with_lr_search_until_its_share_draws_a_collision():
    """Learner 0's share holds a collision, learner 1's does not: learner 0 learns with ``lr``
    (and is marked as having found one), learner 1 with ``lr_search`` (oracle: the same update
    by two copies of the strategy whose learning rates are both ``lr``, both ``lr_search``);
    a collision seen once keeps the learner on ``lr``. (After a first update: the first may use
    ``lr_first``, see below.)"""
    s, p, state = _moved(2, 0, 1)
    state = dataclasses.replace(state, told=jnp.int32(s.batch))
    idx, _ = jax.jit(s.ask)(jax.random.key(1), state, p)
    tell = jax.jit(s.tell_outcome)  # the learning rates are traced: compiled once
    g = np.random.default_rng(7)
    rewards = jnp.asarray(g.uniform(0.3, 0.6, 64), jnp.float32)
    rob = jnp.asarray(g.uniform(-1, 3, 64), jnp.float32)
    hit = jnp.asarray(np.arange(64) == 5)  # in learner 0's share (the first 32)
    got = tell(jax.random.key(2), state, idx, rewards, rob, hit, p)
    np.testing.assert_array_equal(np.asarray(got.found), [True, False])
    for lr, learner in ((p.lr, 0), (p.lr_search, 1)):
        q = pytree.replace(p, lr=lr, lr_search=lr)
        want = tell(jax.random.key(2), state, idx, rewards, rob, hit, q)
        for x, y in zip(jax.tree.leaves(got.params), jax.tree.leaves(want.params)):
            np.testing.assert_array_equal(np.asarray(x)[learner], np.asarray(y)[learner])
    assert p.lr != p.lr_search
    later = tell(jax.random.key(3), got, idx, rewards, rob, jnp.zeros(64, bool), p)
    np.testing.assert_array_equal(np.asarray(later.found), [True, False])


@pytest.mark.slow
def test_the_first_update_takes_lr_first_for_the_first_learners_only():
    """At the first update, with no collision, learners below ``first_learners`` step with
    ``lr_first`` and the others with ``lr_search``; at the second, all with ``lr_search``
    (oracle: the same updates by copies of the strategy whose learning rates are all one
    value)."""
    s, p, state = _moved(3, 0, 1)
    p = pytree.replace(p, first_learners=2.0)
    idx, _ = jax.jit(s.ask)(jax.random.key(1), state, p)
    tell = jax.jit(s.tell_outcome)  # the learning rates are traced: compiled once
    g = np.random.default_rng(8)
    rewards = jnp.asarray(g.uniform(0.3, 0.6, 64), jnp.float32)
    rob = jnp.asarray(g.uniform(0.1, 3, 64), jnp.float32)
    none = jnp.zeros(64, bool)
    later = dataclasses.replace(state, told=jnp.int32(s.batch))
    assert len({p.lr_first, p.lr_search, p.lr}) == 3

    def same(a, b, learner):
        for x, y in zip(jax.tree.leaves(a.params), jax.tree.leaves(b.params)):
            np.testing.assert_array_equal(np.asarray(x)[learner], np.asarray(y)[learner])

    for start, rates in ((state, (p.lr_first, p.lr_first, p.lr_search)),
                         (later, (p.lr_search,) * 3)):
        got = tell(jax.random.key(2), start, idx, rewards, rob, none, p)
        for learner, lr in enumerate(rates):
            q = pytree.replace(p, lr=lr, lr_search=lr, lr_first=lr)
            same(got, tell(jax.random.key(2), start, idx, rewards, rob, none, q), learner)
        q = pytree.replace(p, lr=p.lr_first, lr_search=p.lr_first, lr_first=p.lr_first)
        want = tell(jax.random.key(2), start, idx, rewards, rob, none, q)
        assert not np.array_equal(np.asarray(jax.tree.leaves(got.params)[0])[2],
                                  np.asarray(jax.tree.leaves(want.params)[0])[2])


def test_from_novelty_until_on_the_learners_learn_together_from_the_best_one():
    """Three learners, 64 scenarios (shares of 22, 22 and 20): before ``novelty_until`` each
    learns from its own share's elite; at the first update from then on every learner starts
    from the learner whose share scored best on average (weights and Adam's moments) and learns
    from the whole batch's elite (oracle: NumPy's mean per share and ranking of the batch, and
    one learner's Adam steps on that elite from that learner's state); a collision in one share
    counts as found by all."""
    s, p, state = _moved(3, 0, 1)  # batch 64
    p = pytree.replace(p, novelty_until=float(5 * s.batch))
    g = np.random.default_rng(11)
    idx = jnp.asarray(g.integers(0, SHAPE, (64, len(SHAPE))), jnp.int32)
    signal = jnp.asarray(g.permutation(64) * 0.01 - 0.3, jnp.float32)
    signal = signal.at[22:44].add(0.5)  # learner 1's share scores best
    hit = jnp.asarray(np.arange(64) == 50)  # a collision in learner 2's share
    learn = jax.jit(s._learn)
    sig = np.asarray(signal)
    bounds = ((0, 22), (22, 44), (44, 64))
    # apart: the state after it (each learner's own weights and Adam moments) starts the next
    apart, mask = learn(jax.random.key(2), dataclasses.replace(state, told=jnp.int32(
        4 * s.batch)), idx, signal, hit, p)
    want_mask = np.zeros(64, bool)
    for lo, hi in bounds:
        want_mask[lo + np.argsort(-sig[lo:hi])[:s.top]] = True
    np.testing.assert_array_equal(np.asarray(mask), want_mask)
    np.testing.assert_array_equal(np.asarray(apart.found), [False, False, True])
    start = dataclasses.replace(apart, told=jnp.int32(5 * s.batch))
    new, mask = learn(jax.random.key(3), start, idx, signal, hit, p)
    np.testing.assert_array_equal(np.asarray(new.found), [True, True, True])
    order = np.argsort(-sig)[:s.top]
    want_mask = np.zeros(64, bool)
    want_mask[order] = True
    np.testing.assert_array_equal(np.asarray(mask), want_mask)
    best = int(np.argmax([sig[lo:hi].mean() for lo, hi in bounds]))
    assert best == 1
    rank_w = np.log(s.top + 0.5) - np.log(np.arange(1, s.top + 1))
    elite = jnp.pad(idx[order], ((0, -s.top % 8), (0, 0)))
    w = jnp.pad(jnp.asarray(rank_w / rank_w.sum(), jnp.float32), (0, -s.top % 8))
    one = lambda x: jax.tree.map(lambda a: a[best], x)  # noqa: E731
    want_w, _ = jax.jit(s._learn_one)(one(apart.params), one(apart.opt), elite, w, p, p.lr)
    for learner in range(3):  # (vmapped and single float32 Adam steps round apart: 5e-5;
        # another start or elite moves weights by 0.1-0.3)
        for x, y in zip(jax.tree.leaves(new.params), jax.tree.leaves(want_w)):
            np.testing.assert_allclose(np.asarray(x)[learner], y, rtol=0, atol=2e-4)


def test_a_learner_whose_first_share_collides_takes_lr_not_lr_first():
    s, p, state = _moved(2, 0, 1)
    p = pytree.replace(p, first_learners=2.0)  # both learners would take lr_first
    idx, _ = jax.jit(s.ask)(jax.random.key(1), state, p)
    tell = jax.jit(s.tell_outcome)
    g = np.random.default_rng(9)
    rewards = jnp.asarray(g.uniform(0.3, 0.6, 64), jnp.float32)
    rob = jnp.asarray(g.uniform(-1, 3, 64), jnp.float32)
    hit = jnp.asarray(np.arange(64) == 5)  # in learner 0's share, at the first update
    got = tell(jax.random.key(2), state, idx, rewards, rob, hit, p)
    for lr, learner in ((p.lr, 0), (p.lr_first, 1)):
        q = pytree.replace(p, lr=lr, lr_search=lr, lr_first=lr)
        want = tell(jax.random.key(2), state, idx, rewards, rob, hit, q)
        for x, y in zip(jax.tree.leaves(got.params), jax.tree.leaves(want.params)):
            np.testing.assert_array_equal(np.asarray(x)[learner], np.asarray(y)[learner])


def test_vertex_learners_start_at_the_box_vertices():
    """The last ``vertex_learners`` learners start with every component at a vertex of the box
    (each mean's logit that of 0.02 or 0.98 of the range, both corners drawn) and the width
    ``vertex_sigma`` (through the controller's width map, in NumPy); every other weight, and
    the other learners' biases, are those of the same strategy without vertex learners (same
    key); a single learner never starts at the vertices."""
    shape, K = (7, 1, 50), 5
    kw = dict(hidden=8, components=K, learners=4)
    s0, p = search.make("reinforce/default", shape, 64, vertex_learners=0, **kw)
    s2, _ = search.make("reinforce/default", shape, 64, vertex_learners=2, vertex_sigma=0.03,
                        **kw)
    w0 = jax.jit(s0.init)(jax.random.key(3), p).params
    w2 = jax.jit(s2.init)(jax.random.key(3), p).params
    with_vertices = dict(jax.tree_util.tree_leaves_with_path(w2))
    for path, a in jax.tree_util.tree_leaves_with_path(w0):
        b = np.asarray(with_vertices[path])
        if jax.tree_util.keystr(path) == "['bias']":
            np.testing.assert_array_equal(np.asarray(a)[:2], b[:2])
            assert not np.array_equal(np.asarray(a)[2:], b[2:])
        else:
            np.testing.assert_array_equal(np.asarray(a), b)
    bias = np.asarray(w2["bias"], np.float64)[2:]  # (2 learners, P, 2K)
    mean = 1.0 / (1.0 + np.exp(-bias[..., :K]))
    at = np.where(np.isclose(mean, 0.02, atol=1e-6), 0, np.where(np.isclose(mean, 0.98,
                                                                             atol=1e-6), 1, -1))
    assert np.all(at >= 0) and 0 < at.mean() < 1
    n = np.asarray(shape, np.float64)
    lo = np.log(batched.SIGMA_MIN_STEPS / np.maximum(n - 1, 1))
    sigma = np.exp(lo[:, None] + (batched.LOG_SIGMA_MAX - lo[:, None])
                   / (1.0 + np.exp(-bias[..., K:])))
    np.testing.assert_allclose(sigma[:, [0, 2]], 0.03, rtol=1e-4)  # (a one-value parameter:
    # any width)
    one, _ = search.make("reinforce/default", shape, 64, vertex_learners=2, hidden=8,
                         components=K, learners=1)
    alone, _ = search.make("reinforce/default", shape, 64, vertex_learners=0, hidden=8,
                           components=K, learners=1)
    assert one.n_vertex_learners == 0
    np.testing.assert_array_equal(
        np.asarray(jax.jit(one.init)(jax.random.key(3), p).params["bias"]),
        np.asarray(jax.jit(alone.init)(jax.random.key(3), p).params["bias"]))


def _np_boundary_probs(n, width):
    """The boundary distribution over one parameter's ``n`` values, from its definition: a
    third uniform; a third ``round(r (n - 1))`` values from the low end, a third from the high
    end, ``r`` exponential of mean ``width`` (CDF ``1 - exp(-x / width)``), capped at the other
    end."""
    if n == 1:
        return np.ones(1)
    cdf = lambda x: 1.0 - math.exp(-max(x, 0.0) / width)  # noqa: E731
    low = [cdf((v + 0.5) / (n - 1)) - cdf((v - 0.5) / (n - 1)) for v in range(n - 1)]
    low.append(1.0 - cdf((n - 1.5) / (n - 1)))
    low = np.asarray(low)
    return (np.full(n, 1.0 / n) + low + low[::-1]) / 3.0


@pytest.mark.parametrize("width", [0.02, 0.2])
def test_boundary_draws_follow_their_definition(width):
    """200,000 draws of the boundary distribution: each parameter's value frequencies within 5
    standard errors of the probabilities derived from its definition (float64 NumPy), which
    :func:`discretised.boundary_probs` gives too; the parameters are independent (a pair's
    joint frequency of both low ends against the product)."""
    shape = (1, 2, 7, 50)
    u = jax.random.uniform(jax.random.key(5), (200_000, len(shape)))
    idx = np.asarray(jax.jit(lambda x: discretised.sample_boundary(x, shape, width))(u))
    for p, n in enumerate(shape):
        want = _np_boundary_probs(n, width)
        np.testing.assert_allclose(discretised.boundary_probs(n, width), want, atol=1e-12)
        assert want.sum() == pytest.approx(1.0)
        freq = np.bincount(idx[:, p], minlength=n) / len(idx)
        se = np.sqrt(want * (1 - want) / len(idx))
        assert np.all(np.abs(freq - want) <= 5 * se + 1e-6), (p, freq, want)
    both = np.mean((idx[:, 2] == 0) & (idx[:, 3] == 0))
    prod = _np_boundary_probs(7, width)[0] * _np_boundary_probs(50, width)[0]
    assert abs(both - prod) <= 5 * math.sqrt(prod * (1 - prod) / len(idx))


def test_the_first_update_of_the_boundary_learners_draws_from_the_boundary():
    """With ``boundary`` 0.5 (2 of 4 learners), the first update's draws of learners 0 and 1 follow
    the boundary distribution (per parameter, within 5 standard errors of the definition's
    probabilities) and those of learners 2 and 3 are the policy's (the same draws as without
    boundary learners, same key); from the second update on every draw is the policy's."""
    shape = (9, 40)
    s, p = search.make("reinforce/default", shape, 80_000, learners=4, hidden=8, components=3,
                       vertex_learners=0)
    q = pytree.replace(p, boundary=0.5, boundary_width=0.05)
    p = pytree.replace(p, boundary=0.0)
    state = jax.jit(s.init)(jax.random.key(2), p)
    ask = jax.jit(s.ask)
    plain, _ = ask(jax.random.key(9), state, p)
    first, _ = ask(jax.random.key(9), state, q)
    plain, first = np.asarray(plain), np.asarray(first)
    half = 2 * s.share
    np.testing.assert_array_equal(first[half:], plain[half:])
    for j, n in enumerate(shape):
        want = _np_boundary_probs(n, 0.05)
        freq = np.bincount(first[:half, j], minlength=n) / half
        se = np.sqrt(want * (1 - want) / half)
        assert np.all(np.abs(freq - want) <= 5 * se + 1e-6), (j, freq, want)
    # the policy's draws of those learners are spread (SIGMA_INIT): far from the boundary's
    assert np.mean(plain[:half, 1] == 0) < 0.5 * want[0]
    # with boundary 1 (every learner; the policies' draws are then not computed) the first
    # two learners draw the same, and the last two from the boundary distribution as well
    every = np.asarray(ask(jax.random.key(9), state, pytree.replace(q, boundary=1.0))[0])
    np.testing.assert_array_equal(every[:half], first[:half])
    for j, n in enumerate(shape):
        want = _np_boundary_probs(n, 0.05)
        freq = np.bincount(every[half:, j], minlength=n) / (len(every) - half)
        se = np.sqrt(want * (1 - want) / (len(every) - half))
        assert np.all(np.abs(freq - want) <= 5 * se + 1e-6), (j, freq, want)
    later = dataclasses.replace(state, told=jnp.int32(s.batch))
    np.testing.assert_array_equal(np.asarray(ask(jax.random.key(9), later, q)[0]),
                                  np.asarray(ask(jax.random.key(9), later, p)[0]))


@pytest.mark.parametrize("M", [1, 4])
def test_the_screened_first_batch_is_the_nearest_of_its_boundary_candidates(M):
    """``ask_screened`` with a screen that gives a set ``A`` of scenarios a gap of 0 s and the
    rest 10 s: a first-batch draw lies in ``A`` with probability ``1 - (1 - q)^M``, ``q`` the
    boundary distribution's mass of ``A`` (exact, from the definition), and inside ``A`` it
    follows the boundary distribution restricted to ``A``. With the gap the rank of parameter 1's
    value, the draw's value is the least of ``M`` independent boundary draws: ``P(v >= t) = S(t)^M``
    with ``S`` one draw's survival function. Each within 5 standard errors. With equal gaps, or
    ``screen_candidates`` 1, or plain ``ask``: the boundary's own draws. (The screened rows:
    the first three of four learners' shares, ``screened_learners`` 3; the fourth's are the
    plain draws.)"""
    shape = (9, 40)
    B = 80_000
    s, p = search.make("reinforce/default", shape, B, learners=4, hidden=8, components=3,
                       screen_candidates=M, screened_learners=3)
    state = jax.jit(s.init)(jax.random.key(2), p)
    R = 3 * s.share

    def asked(screen, key):
        return np.asarray(jax.jit(lambda k, st: s.ask_screened(k, st, p, screen)[0])(
            jax.random.key(key), state))[:R]

    b0, b1 = _np_boundary_probs(9, 0.02), _np_boundary_probs(40, 0.02)
    q = b0[0] * b1[35:].sum()
    idx = asked(lambda c: jnp.where((c[:, 0] == 0) & (c[:, 1] >= 35), 0.0, 10.0), 7)
    inside = (idx[:, 0] == 0) & (idx[:, 1] >= 35)
    want = 1 - (1 - q) ** M
    assert abs(inside.mean() - want) <= 5 * math.sqrt(want * (1 - want) / R), (inside.mean(), want)
    cond = b1[35:] / b1[35:].sum()
    freq = np.bincount(idx[inside, 1] - 35, minlength=5) / inside.sum()
    assert np.all(np.abs(freq - cond) <= 5 * np.sqrt(cond * (1 - cond) / inside.sum()))
    least = asked(lambda c: c[:, 1].astype(jnp.float32), 8)[:, 1]
    for t in (1, 5, 20, 39):
        want = b1[t:].sum() ** M
        got = np.mean(least >= t)
        assert abs(got - want) <= 5 * math.sqrt(want * (1 - want) / R) + 1e-6, (t, got, want)
    plain = np.asarray(jax.jit(s.ask)(jax.random.key(7), state, p)[0])
    np.testing.assert_array_equal(asked(lambda c: jnp.zeros(c.shape[0]), 7), plain[:R])
    if M == 1:
        np.testing.assert_array_equal(idx, plain[:R])
    # two screened learners (the default): their shares as with four, the others' the plain draws
    two = dataclasses.replace(s, screened_learners=2)
    half = np.asarray(jax.jit(lambda k, st: two.ask_screened(k, st, p, lambda c: jnp.where(
        (c[:, 0] == 0) & (c[:, 1] >= 35), 0.0, 10.0))[0])(jax.random.key(7), state))
    np.testing.assert_array_equal(half[2 * s.share:], plain[2 * s.share:])
    inside = (half[:2 * s.share, 0] == 0) & (half[:2 * s.share, 1] >= 35)
    want = 1 - (1 - q) ** M
    assert abs(inside.mean() - want) <= 5 * math.sqrt(want * (1 - want) / inside.size)


@pytest.mark.parametrize("learners,screened,batch", [(4, 1, 10), (4, 4, 10), (4, 8, 10),
                                                     (2, 2, 12), (1, 1, 12)])
def test_the_screened_shares_when_the_learners_do_not_divide_the_batch(learners, screened,
                                                                       batch):
    """The first ``min(screened_learners, learners - 1)`` learners' shares are screened and
    the rest of the batch is the plain ``ask``'s, also where the last share is cut short; a
    batch of the asked size. Oracle: a screen that prefers parameter 0's first value."""
    shape = (6, 7)
    s, p = search.make("reinforce/default", shape, batch, learners=learners, hidden=8,
                       components=3, screened_learners=screened)
    state = jax.jit(s.init)(jax.random.key(1), p)
    plain = np.asarray(jax.jit(s.ask)(jax.random.key(4), state, p)[0])
    got = np.asarray(jax.jit(lambda k, st: s.ask_screened(
        k, st, p, lambda c: c[:, 0].astype(jnp.float32))[0])(jax.random.key(4), state))
    assert got.shape == plain.shape == (batch, 2)
    stop = min(min(screened, learners - 1) * s.share, batch)
    np.testing.assert_array_equal(got[stop:], plain[stop:])
    # screened rows: never further from value 0 than the row's own draw
    assert np.all(got[:stop, 0] <= plain[:stop, 0])


@pytest.mark.parametrize("boundary", [1.0, 0.5])
def test_a_started_state_asks_and_learns_as_an_initialised_one(boundary):
    """``start`` (the campaign's state, weights drawn at the first tell or at an ask that
    needs them) against ``init`` (weights drawn at once), same key: the same draws at every
    update and the same weights and Adam moments after each tell, bit for bit, with the
    first batch all boundary draws (``boundary`` 1, the policies not needed before the first
    tell) and half policy draws (0.5); before its first tell the started state holds no
    weights (zeros)."""
    s, p = search.make("reinforce/default", SHAPE, 256, hidden=8, components=3, learners=4)
    p = pytree.replace(p, boundary=boundary)
    started = jax.jit(s.start)(jax.random.key(5), p)
    assert not bool(started.ready)
    assert all(not np.any(np.asarray(x)) for x in jax.tree.leaves(started.params))

    @jax.jit
    def updates(state):
        def one(st, k):
            k_ask, k_tell = jax.random.split(k)
            idx, st = s.ask(k_ask, st, p)
            r = -jnp.sum((idx - 1.0) ** 2, axis=1)  # any reward that ranks the batch
            st = s.tell_outcome(k_tell, st, idx, r, r, r > -1.5, p)
            return st, (idx, st.params, st.opt)
        return jax.lax.scan(one, state, jax.random.split(jax.random.key(8), 3))[1]

    eager = updates(jax.jit(s.init)(jax.random.key(5), p))
    lazy = updates(started)
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(lazy)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # (the draws are not trivially equal: the policies learnt, so later batches differ)
    assert not np.array_equal(np.asarray(eager[0][0]), np.asarray(eager[0][2]))
