"""Search strategies and the LSTM controller: one contract test over the whole registry
(shapes, determinism per key, no recompilation, the optimum of a synthetic objective), the
controller against the LSTM equations in NumPy, REINFORCE's presets, the campaign driver."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import run_campaign

import jaxfalsify as jf
from jaxfalsify import search
from jaxfalsify.base import pytree
from jaxfalsify.engine import campaign
from jaxfalsify.outputs import analysis
from jaxfalsify.search import base, controller, reinforce

SHAPE = (6, 5, 4)
TARGET = np.array([4, 1, 2])
# the contract's space has a one-value parameter too (every index must stay 0 there)
CONTRACT_SHAPE = (6, 1, 5, 4)
CONTRACT_TARGET = np.array([4, 0, 1, 2])


def synthetic_reward(idx, target=TARGET):
    """Unique optimum at ``target`` (reward 0), smooth elsewhere."""
    return -jnp.sum(jnp.abs(idx - target), axis=-1).astype(jnp.float32)


def make_loop(strategy, n_updates, target=TARGET):
    """The whole search on the synthetic objective as one jitted function of (key, params)."""
    def loop(key, params):
        def one(carry, _):
            state, key = carry
            key, k_ask, k_tell = jax.random.split(key, 3)
            idx, state = strategy.ask(k_ask, state, params)
            r = synthetic_reward(idx, target)
            return (strategy.tell(k_tell, state, idx, r, params), key), (idx, r)

        k_init, k_run = jax.random.split(key)
        return jax.lax.scan(one, (strategy.init(k_init, params), k_run), None,
                            length=n_updates)[1]

    return jax.jit(loop)


# ------------------------------------------------------------------ the registry contract
NOT_ADAPTIVE = ("random", "grid")  # sample without learning, by design
@pytest.mark.parametrize("name", list(search.REGISTRY))
def test_strategy_contract(name, compile_events):
    strat, p = search.make(name, CONTRACT_SHAPE, 40)
    loop = make_loop(strat, 25, CONTRACT_TARGET)  # 1000 evaluations of a 120-scenario space
    idx, r = loop(jax.random.key(3), p)
    # shapes and bounds (the one-value parameter always at its only value)
    assert idx.shape == (25, 40, 4) and idx.dtype == jnp.int32 and r.shape == (25, 40)
    flat = np.asarray(idx).reshape(-1, 4)
    assert np.all((flat >= 0) & (flat < np.array(CONTRACT_SHAPE)))
    # finds the optimum of the synthetic objective
    assert float(jnp.max(r)) == 0.0
    if name not in NOT_ADAPTIVE:  # and optimises: the last update's mean reward lies three
        # standard errors above a uniform batch's (oracle: the objective on every scenario;
        # a strategy that does not learn gets there with probability ~0.1 %)
        every = np.stack(np.meshgrid(*map(np.arange, CONTRACT_SHAPE), indexing="ij"),
                         -1).reshape(-1, len(CONTRACT_SHAPE))
        everywhere = np.asarray(synthetic_reward(every, CONTRACT_TARGET), np.float64)
        bar = everywhere.mean() + 3 * everywhere.std() / np.sqrt(strat.batch)
        assert float(jnp.mean(r[-1])) > bar, (float(jnp.mean(r[-1])), bar)
    # deterministic per key, different across keys
    again, _ = loop(jax.random.key(3), p)
    np.testing.assert_array_equal(np.asarray(again), np.asarray(idx))
    with compile_events() as events:  # new key, new hyperparameter values: no recompilation
        other, _ = loop(jax.random.key(4), jax.tree.map(lambda x: x * 1.01, p))
    assert events == []
    assert not np.array_equal(np.asarray(other), np.asarray(idx))


def test_registry_options_and_errors():
    strat, p = search.make("cem", SHAPE, 20, elite_frac=0.25)
    assert p.elite_frac == 0.25 and strat.batch == 20
    assert search.make("reinforce", SHAPE)[0] == search.make("reinforce/default", SHAPE)[0]
    paper, pp = search.make("reinforce/paper", SHAPE)
    assert (paper.batch, paper.chains, paper.advantage) == (25, 1, "reward")
    assert (pp.lr, pp.alpha, pp.eps_start) == pytest.approx((0.01, 1e-4, 1.0))
    with pytest.raises(ValueError, match="unknown strategy 'ga'"):
        search.make("ga", SHAPE)
    with pytest.raises(ValueError, match="no option 'elite'.*elite_frac"):
        search.make("cem", SHAPE, elite=0.2)
    with pytest.raises(ValueError, match="batch"):
        search.make("random", SHAPE, 0)
    with pytest.raises(ValueError, match="learners=7 must divide batch=20"):
        search.make("reinforce/screened", SHAPE, 20, learners=7)
    with pytest.raises(ValueError, match="chains=7 must divide batch=20"):
        search.make("reinforce/factorised", SHAPE, 20, chains=7)
    with pytest.raises(ValueError, match="signal must be one of"):
        search.make("cmaes", SHAPE, signal="distance")
    assert search.options("reinforce/paper")["alpha"] == pytest.approx(1e-4)


def test_option_types_and_intervals():
    """Static options take the type of their default (a command line gives strings and
    numbers); hyperparameters must lie in their class's declared interval."""
    as_python = search.make("reinforce/screened", SHAPE, anchored=False, hidden=16)[0]
    for text in ("false", "False", " FALSE ", 0):
        assert search.make("reinforce/screened", SHAPE, anchored=text, hidden=16.0)[0] == \
            as_python
    assert search.make("reinforce/screened", SHAPE, anchored="true")[0].anchored is True
    # NumPy and JAX scalars are numbers like Python's (a sweep over np.linspace, say)
    strat, params = search.make("reinforce/screened", SHAPE, hidden=np.int64(16),
                                lr=np.float32(0.5), kappa=jnp.asarray(2.0))
    assert strat.hidden == 16 and isinstance(strat.hidden, int)
    assert search.make("reinforce/screened", SHAPE, anchored=np.bool_(False))[0].anchored is False
    assert (float(params.lr), float(params.kappa)) == (0.5, 2.0)
    for bad, needle in [(dict(anchored="maybe"), "not a boolean"),
                        (dict(anchored=2), "not a boolean"),
                        (dict(hidden=1.5), "not a whole number"),
                        (dict(hidden="32"), "not a whole number"),
                        (dict(hidden=np.float32(1.5)), "not a whole number"),
                        (dict(lr=np.array([0.1, 0.2])), "not a finite number"),
                        (dict(lr=np.bool_(True)), "not a finite number"),
                        (dict(kernel=1), "kernel=1 is not a string"),
                        (dict(advantage=1), r"advantage must be one of rank, normalised or a "
                         r"function \(got 1\)"),
                        (dict(sigma_min=0.0), r"sigma_min=0.0 is outside \[0.0001, 1\]"),
                        (dict(global_share=1.01), r"outside \[0, 1\]"),
                        (dict(hidden=10**30), r"hidden=10{30} is outside \[1, 1024\]"
                         .replace("10{30}", str(10**30))),
                        (dict(memory=99999999999), r"memory=99999999999 is outside")]:
        with pytest.raises(ValueError, match=needle):
            search.make("reinforce/screened", SHAPE, **bad)
    # the interval notation: brackets closed, parentheses open
    for value, interval, inside in [(0.0, "(0, 1]", False), (1.0, "(0, 1]", True),
                                    (0.5, "(0, 1]", True), (1.0, "[0, 1)", False),
                                    (-5.0, "(-inf, 1)", True), (1e30, "[0, inf)", True)]:
        assert pytree.in_range(value, interval) is inside, (value, interval)
    # every entry's own options lie inside the intervals (make would refuse them otherwise)
    for name in search.REGISTRY:
        strat, params = search.make(name, SHAPE, 20)
        for field, interval in pytree.ranges(strat.Params).items():
            assert pytree.in_range(float(getattr(params, field)), interval), (name, field)
        for field, interval in pytree.ranges(type(strat)).items():  # static sizes
            assert pytree.in_range(float(getattr(strat, field)), interval), (name, field)


def test_grid_enumerates_every_scenario_once():
    strat, p = search.make("grid", SHAPE, 24)
    idx, _ = make_loop(strat, 5)(jax.random.key(0), p)  # 120 = the whole space
    flat = np.ravel_multi_index(np.asarray(idx).reshape(-1, 3).T, SHAPE)
    assert sorted(flat.tolist()) == list(range(120))
    assert flat.tolist() != list(range(120))  # in a random order


# ------------------------------------------------------------------ controller
def test_controller_shapes_and_heads_are_distributions():
    w = controller.init(jax.random.key(0), (3, 5, 2))
    logits = controller.logits(w, jnp.array([0.0, 0.5, 1.0]), (3, 5, 2))
    assert logits.shape == (3, 5)
    probs = np.asarray(jax.nn.softmax(logits, axis=-1))
    np.testing.assert_allclose(probs.sum(-1), 1.0, rtol=1e-6)
    assert np.all(probs[0, 3:] == 0) and np.all(probs[2, 2:] == 0)
    assert np.all(probs[1] > 0)
    assert w["lstm1"]["u"].shape == (32, 128) and w["lstm2"]["w"].shape == (32, 128)


def _np_lstm(p, h, c, x):
    """The LSTM equations (Hochreiter & Schmidhuber; Keras' gate order i, f, g, o) in float64,
    relu as the cell activation."""
    w, u, b = (np.asarray(p[k], np.float64) for k in ("w", "u", "b"))
    z = x @ w + h @ u + b
    H = len(b) // 4
    sig = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    relu = lambda v: np.maximum(v, 0)  # noqa: E731
    i, f, g, o = sig(z[:H]), sig(z[H:2 * H]), relu(z[2 * H:3 * H]), sig(z[3 * H:])
    c = f * c + i * g
    return o * relu(c), c


def test_lstm_cell_and_controller_match_numpy_equations():
    shape = (3, 5, 2)
    w = controller.init(jax.random.key(1), shape)
    rng = np.random.default_rng(0)
    h0, c0, x = rng.normal(size=32), rng.normal(size=32), rng.normal(size=3)
    h, c = controller.lstm_step(w["lstm1"], (jnp.asarray(h0, jnp.float32),
                                             jnp.asarray(c0, jnp.float32)),
                                jnp.asarray(x, jnp.float32))
    eh, ec = _np_lstm(w["lstm1"], h0, c0, x)
    np.testing.assert_allclose(np.asarray(h), eh, atol=1e-5)
    np.testing.assert_allclose(np.asarray(c), ec, atol=1e-5)
    # the paper's controller: two layers from zero states, then the head
    xin = np.array([0.2, 0.4, 0.9])
    h1, _ = _np_lstm(w["lstm1"], np.zeros(32), np.zeros(32), xin)
    h2, _ = _np_lstm(w["lstm2"], np.zeros(32), np.zeros(32), h1)
    out = (h2 @ np.asarray(w["head"]["w"], np.float64) + np.asarray(w["head"]["b"])).reshape(3, 5)
    got = np.asarray(controller.logits(w, jnp.asarray(xin, jnp.float32), shape))
    np.testing.assert_allclose(got[0, :3], out[0, :3], atol=1e-5)
    np.testing.assert_allclose(got[1], out[1], atol=1e-5)
    assert np.all(got[2, 2:] == controller.MASKED)


def test_log_prob_matches_manual_computation():
    w = controller.init(jax.random.key(1), (3, 5, 2))
    logits = np.asarray(controller.logits(w, jnp.array([0.2, 0.4, 0.9]), (3, 5, 2)),
                        np.float64)
    action = np.array([2, 4, 1])
    manual = 0.0
    for p, n in enumerate((3, 5, 2)):
        z = logits[p, :n]
        manual += z[action[p]] - np.log(np.sum(np.exp(z - z.max()))) - z.max()
    got = float(controller.action_log_prob(jnp.asarray(logits, jnp.float32),
                                           jnp.asarray(action)))
    assert got == pytest.approx(manual, abs=1e-4)


@pytest.mark.parametrize("name,options,shaped", [
    # reinforce/default's learners that start at the box's vertices draw only corners at first:
    # a reward that is flat everywhere else gives them nothing to follow (docs/search.md), so
    # the flat reward is checked with every learner spread, the shaped one with the default
    pytest.param("reinforce/default", {"vertex_learners": 0}, False, marks=pytest.mark.slow),
    pytest.param("reinforce/default", {}, True, marks=pytest.mark.slow),
    ("reinforce/factorised", {}, False), ("reinforce/paper", {}, False)])
def test_reinforce_moves_probability_to_rewarded_index(name, options, shaped):
    strat, p = search.make(name, SHAPE, 50, **options)
    ask = jax.jit(lambda k, s: strat.ask(k, s, p))
    tell = jax.jit(lambda k, s, i, r: strat.tell(k, s, i, r, p))
    probs = jax.jit(strat.probs)
    state = jax.jit(strat.init)(jax.random.key(0), p)
    before = float(probs(state)[0, 3])
    for i in range(40):
        idx, state = ask(jax.random.key(i + 1), state)
        reward = -jnp.abs(idx[:, 0] - 3) if shaped else idx[:, 0] == 3
        state = tell(jax.random.key(100 + i), state, idx, reward.astype(jnp.float32))
    after = float(probs(state)[0, 3])
    assert before < 0.3 and after > 0.6


def test_paper_preset_exploration_schedule():
    _, p = search.make("reinforce/paper", SHAPE)
    eps = np.asarray(reinforce.epsilon(jnp.array([0, 3, 4, 400, 1999, 2000, 3999]), p))
    np.testing.assert_allclose(eps, [1.0, 1.0, 0.995, max(0.995**100, 0.01),
                                     max(0.995**499, 0.01), 0.0, 0.0], rtol=1e-5)


# ------------------------------------------------------------------ campaign driver
def test_campaign_budget_and_determinism():
    sp = jf.load_space("paper")
    a = run_campaign(sp, "cem", batch=50, evaluations=130, seed=1)  # not a batch multiple
    b = run_campaign(sp, "cem", batch=50, evaluations=130, seed=1)
    c = run_campaign(sp, "cem", batch=50, evaluations=130, seed=2)
    assert a.n == 130 and a.evaluation[-1] == 130
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.fields["reward"], b.fields["reward"])
    assert not np.array_equal(a.indices, c.indices)
    # records are the simulator's outcomes for the recorded scenarios
    out = jf.evaluate(sp.scenario(a.indices[:20]))
    np.testing.assert_array_equal(np.asarray(out.reward), a.fields["reward"][:20])


def test_seeds_together_equal_single_runs():
    from jaxfalsify.suts import registry as sut_lib

    sp = jf.load_space("paper")
    s, sp_ = sut_lib.make("carla-tm")
    strat, p = search.make("cem", sp.shape, 50)
    plan = campaign.plan(130, 50)
    many = campaign.run_seeds(sp, s, sp_, strat, p, plan, [1, 2])
    one = campaign.run(sp, s, sp_, strat, p, plan, seed=2)
    np.testing.assert_array_equal(many[1].indices, one.indices)
    np.testing.assert_allclose(many[1].fields["reward"], one.fields["reward"], atol=1e-6)


def test_another_space_seed_or_calibration_does_not_recompile(compile_events):
    """Space values, SUT and strategy parameters are traced: a second campaign with another
    space seed, SUT calibration and hyperparameter value reuses the compiled program."""
    from jaxfalsify.suts import registry as sut_lib

    def go(space_seed, ttc, elite):
        sp = jf.load_space("paper", seed=space_seed)
        s, sp_ = sut_lib.make("sensor-aeb", ttc_full=ttc)
        strat, p = search.make("cem", sp.shape, 32, elite_frac=elite)
        return campaign.run(sp, s, sp_, strat, p, campaign.plan(96, 32), seed=0)

    go(0, 0.9, 0.1)
    with compile_events() as events:
        r = go(1, 1.2, 0.2)
    assert events == [] and r.n == 96


def test_nan_outcomes_never_rank_best():
    from jaxfalsify.suts import registry as sut_lib

    sp = jf.load_space("paper")

    def flaky(obs, state, params, key):  # NaN command whenever the pedestrian is slow
        return jnp.where((obs.t > 0.5) & (obs.ped_vy < 1.3), jnp.nan, 1.0), state

    strat, p = search.make("cem", sp.shape, 50)
    res = campaign.run(sp, sut_lib.resolve(flaky), None, strat, p, campaign.plan(200, 50),
                       seed=0)
    assert res.fields["nonfinite"].any() and (~res.fields["nonfinite"]).any()
    b = analysis.best(res.fields)
    assert not res.fields["nonfinite"][b] and np.isfinite(res.fields["reward"][b])
    assert not np.any(res.fields["collision"] & res.fields["nonfinite"])


def test_analysis_by_hand():
    rew = np.array([-0.03, 0.1, 0.263, 0.05, 0.2648, np.nan], np.float32)
    col = np.array([False, False, True, False, True, False])
    fields = {f: np.zeros(6, np.float32) for f in campaign.RECORD_FIELDS}
    fields.update(reward=rew, collision=col, violated=col, nonfinite=np.isnan(rew))
    idx = np.array([[0] * 5, [1] * 5, [2] * 5, [3] * 5, [2] * 5, [4] * 5], np.int32)
    assert analysis.first_collision(fields) == 3
    assert analysis.best_reached(fields) == 3  # 0.263 is within 1 % of 0.2648
    assert analysis.best(fields) == 4
    assert analysis.typical_non_critical(fields) == 3  # median of -0.03, 0.1, 0.05 is 0.05
    crit = analysis.distinct_critical(idx, fields)
    assert [c["indices"][0] for c in crit] == [2]  # same scenario twice -> one entry
    assert crit[0]["times_evaluated"] == 2 and crit[0]["first_evaluation"] == 3
    assert crit[0]["reward"] == pytest.approx(0.263)  # the first evaluation's outcome


def test_learner_convergence_and_running_best_by_hand():
    """The learner's convergence (moving mean within 5 % of the reward range of its final
    value, window 100) is not the running best's: a learner can find its best early and
    still be sampling elsewhere."""
    r = np.concatenate([np.full(150, -0.05), [0.26], np.full(149, -0.05),
                        np.linspace(-0.05, 0.25, 100), np.full(300, 0.25)]).astype(np.float32)
    f = {"reward": r, "collision": r > 0.2, "nonfinite": np.zeros(len(r), bool)}
    assert analysis.best_reached(f) == 151  # the 0.26 at evaluation 151
    m = analysis.moving_mean(f, 100)
    assert m[99] == pytest.approx(-0.05) and m[-1] == pytest.approx(0.25)
    conv = analysis.learner_converged(f, 100)
    span = 0.26 + 0.05
    # first evaluation from which |m - 0.25| <= 0.05 * span for good (by brute force)
    ok = np.abs(m - 0.25) <= 0.05 * span
    want = next(i for i in range(len(m)) if ok[i:].all()) + 1
    assert conv == want and 400 < conv < 600  # during the climb, after 0.26 was found
    assert analysis.learner_converged({**f, "reward": r[:150]}, 100) is None


def test_submodules_load_on_first_access():
    """``import jaxfalsify`` keeps start-up cheap (strategies, runs, figures not imported) yet
    ``jaxfalsify.search.make`` works as README writes it (a fresh interpreter)."""
    code = ("import sys, jaxfalsify as jf\n"
            "before = 'jaxfalsify.search' in sys.modules\n"
            "strategy, params = jf.search.make('cem', (3, 4), 20, elite_frac=0.2)\n"
            "print(before, type(strategy).__name__, float(params.elite_frac), 'jobs' in dir(jf),\n"
            "      'jaxfalsify.jobs.runs' in sys.modules, callable(jf.jobs.runs.execute))\n"
            "try:\n    jf.no_such_thing\nexcept AttributeError as e:\n    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert out == ["False CEM 0.2 True False True",
                   "module 'jaxfalsify' has no attribute 'no_such_thing'"]


def test_grid_default_batch_fits_a_small_space():
    """grid's default batch (200) shrinks to a smaller space's size, so a first batch visits
    every scenario once; a batch given explicitly above the size is still refused."""
    strat, params = search.make("grid", (4, 8))
    assert strat.batch == 32
    idx, _ = strat.ask(jax.random.key(0), strat.init(jax.random.key(0), params), params)
    assert len({tuple(i) for i in np.asarray(idx).tolist()}) == 32
    assert search.make("grid", (40, 8))[0].batch == 200
    with pytest.raises(ValueError, match="batch=33 exceeds the space's 32 scenarios"):
        search.make("grid", (4, 8), 33)


def test_cem_learns_from_finite_outcomes_only():
    """Failed rollouts (-inf) are never CEM's elite: a batch of failures leaves the
    distribution as it was; with one finite outcome only its values gain mass (by hand:
    smoothing s moves s of the mass to the elite's value, the rest scaled by 1 - s)."""
    s, p = search.make("cem", (50,), 200, smoothing=0.7, min_prob=0.0)
    st = s.init(jax.random.key(0), p)
    idx = jnp.arange(200, dtype=jnp.int32)[:, None] % 50
    failed = jnp.full((200,), -jnp.inf)
    after = s.tell(jax.random.key(1), st, idx, failed, p)
    np.testing.assert_array_equal(np.asarray(after.probs), np.asarray(st.probs))
    one = failed.at[7].set(0.1)
    after = np.asarray(s.tell(jax.random.key(1), st, idx, one, p).probs[0])
    expected = np.full(50, 0.3 / 50)
    expected[7] += 0.7
    np.testing.assert_allclose(after, expected, rtol=1e-5)


def test_cem_draws_are_the_inverse_cdf_of_every_value_compared():
    """The bisection of each parameter's CDF gives the same draws as comparing every draw
    with every value (``categorical_from_uniform`` on the broadcast table), zero-probability
    and padded slots included, and never a value of probability 0."""
    rng = np.random.default_rng(0)
    shape = (300, 7, 1, 40)
    mask = np.asarray(base.value_mask(shape))
    probs = rng.random(mask.shape) * mask * (rng.random(mask.shape) > 0.3)
    probs[:, 0] = 0.0
    probs[2, 0] = 1.0
    probs = jnp.asarray(probs / probs.sum(-1, keepdims=True), jnp.float32)
    key = jax.random.key(3)
    got = np.asarray(base.sample_categorical(key, probs, 5000))
    u = base.uniform(key, (5000, len(shape)))
    want = np.asarray(base.categorical_from_uniform(u, jnp.broadcast_to(probs, (5000,) +
                                                                         probs.shape)))
    np.testing.assert_array_equal(got, want)
    assert np.all(np.asarray(probs)[np.arange(len(shape))[None, :], got] > 0)
    # a draw exactly on a cumulative probability: the first value whose cumulative
    # probability exceeds it, past the zero-probability value (0.5 of [0.5, 0, 0.5] is value 2)
    tie = jnp.asarray([[0.5, 0.0, 0.5], [0.25, 0.25, 0.5]], jnp.float32)
    u = jnp.asarray([[0.5, 0.5], [0.0, 0.25]], jnp.float32)
    np.testing.assert_array_equal(np.asarray(base.categorical_by_bisection(u, tie)),
                                  [[2, 2], [0, 1]])


def test_cem_update_matches_numpy():
    """CEM's tell against NumPy: the elite (the best elite_frac of the batch) value
    frequencies by bincount, the smoothed step, the floor and the renormalisation."""
    shape = (6, 1, 9)
    s, p = search.make("cem", shape, 40, elite_frac=0.25, smoothing=0.6, min_prob=0.01)
    st = s.init(jax.random.key(0), p)
    rng = np.random.default_rng(1)
    idx = np.stack([rng.integers(0, n, 40) for n in shape], axis=1).astype(np.int32)
    rewards = rng.permutation(40).astype(np.float32)  # distinct: no ties to break
    got = np.asarray(s.tell(jax.random.key(2), st, jnp.asarray(idx), jnp.asarray(rewards),
                            p).probs, np.float64)
    elite = idx[np.argsort(-rewards)[:10]]
    mask = np.asarray(base.value_mask(shape))
    for q, n in enumerate(shape):
        freq = np.bincount(elite[:, q], minlength=n) / 10.0
        want = np.maximum(0.4 / n + 0.6 * freq, 0.01)
        np.testing.assert_allclose(got[q, :n], want / want.sum(), rtol=1e-5)
        assert np.all(got[q, ~mask[q]] == 0)


def test_anneal_moves_only_parameters_that_can_move():
    """One-value parameters are never picked (a move there repeats the chain's scenario):
    without restarts every proposal from the middle of a 50-value parameter is new; a huge
    max_step keeps the moves symmetric (it overflowed int32 and pushed them to index 0)."""
    s, p = search.make("anneal", (1, 1, 50), 2000, p_restart=0.0)
    st = jax.jit(s.init)(jax.random.key(0), p)
    st = pytree.replace(st, current=jnp.full((2000, 3), 0, jnp.int32).at[:, 2].set(25),
                        started=jnp.bool_(True))
    prop, _ = jax.jit(s.ask)(jax.random.key(1), st, p)
    prop = np.asarray(prop)
    assert (prop[:, :2] == 0).all() and (prop[:, 2] != 25).all()
    assert set(np.abs(prop[:, 2] - 25)) == {1, 2}  # max_step 2
    s, p = search.make("anneal", (100,), 4000, p_restart=0.0, max_step=1e12)
    st = jax.jit(s.init)(jax.random.key(0), p)
    st = pytree.replace(st, current=jnp.full((4000, 1), 50, jnp.int32),
                        started=jnp.bool_(True))
    prop = np.asarray(jax.jit(s.ask)(jax.random.key(2), st, p)[0])[:, 0]
    down = (prop < 50).mean()
    assert 0.45 < down < 0.55, down  # a fair coin for the sign, 4000 draws: sd 0.008


def test_flax_init_and_one_draw_init_give_the_same_tree():
    """The strategies' one-draw initialiser and the Flax module's own give parameter trees of
    the same structure and shapes, so either can be applied."""
    shape = (3, 5, 2)
    mine = controller.init(jax.random.key(0), shape)
    flax_tree = controller.PaperController(shape).init(jax.random.key(0), jnp.zeros(3))["params"]
    assert jax.tree.structure(mine) == jax.tree.structure(flax_tree)
    assert jax.tree.map(jnp.shape, mine) == jax.tree.map(jnp.shape, flax_tree)
    b = np.asarray(flax_tree["lstm1"]["b"])
    assert np.all(b[32:64] == 1.0) and np.all(b[:32] == 0) and np.all(b[64:] == 0)


def test_the_learning_signal_is_a_function():
    """A strategy's ``signal`` option takes a function of the outcomes as well as a shipped
    name: ``tell_outcome`` with a user's function learns exactly what ``tell`` learns from that
    function's values computed by hand (here from the minimum TTCs, which the campaign hands
    every strategy), and the names resolve to the shipped functions."""
    g = np.random.default_rng(3)
    rewards = g.uniform(0, 1, 8).astype(np.float32)
    rob = g.uniform(-1, 5, 8).astype(np.float32)
    hit = rob < 0
    ttc = g.uniform(0, 9, 8).astype(np.float32)

    def by_ttc(r, robustness, collision, t):
        return -t

    own, p = search.make("cmaes", SHAPE, 8, signal=by_ttc)
    plain, _ = search.make("cmaes", SHAPE, 8, signal="reward")
    state = jax.jit(own.init)(jax.random.key(0), p)
    idx, state = jax.jit(own.ask)(jax.random.key(1), state, p)
    got = jax.jit(own.tell_outcome)(jax.random.key(2), state, idx, rewards, rob, hit, p,
                                    ttc=ttc)
    want = jax.jit(plain.tell)(jax.random.key(2), state, idx, -ttc, p)
    for x, y in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    shaped = search.resolve_signal("shaped")(rewards, rob, hit, None)
    np.testing.assert_array_equal(
        np.asarray(shaped), np.where(hit, rewards, np.minimum(-0.05 * rob, 0.05)))
    with pytest.raises(ValueError, match="signal must be one of reward, shaped or a function"):
        search.make("cem", SHAPE, signal=3)
