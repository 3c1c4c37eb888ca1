"""Search strategies and the LSTM controller: shapes, log-probabilities, learning, optimum
finding on a synthetic objective, determinism, NaN handling."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

import jaxfalsify as jf
from jaxfalsify import campaign, policy, reinforce, search

SHAPE = (6, 5, 4)
TARGET = np.array([4, 1, 2])


def synthetic_reward(idx):
    """Unique optimum at TARGET (reward 0), smooth elsewhere."""
    return -jnp.sum(jnp.abs(idx - TARGET), axis=-1).astype(jnp.float32)


def run_synthetic(strategy, key, n_updates):
    def one(carry, _):
        state, key = carry
        key, k = jax.random.split(key)
        idx, state = strategy.ask(k, state)
        r = synthetic_reward(idx)
        return (strategy.tell(state, idx, r), key), (idx, r)

    return jax.jit(lambda k: jax.lax.scan(one, (strategy.init(k), k), None,
                                          length=n_updates)[1])(key)


# ------------------------------------------------------------------ controller
def test_controller_shapes_and_heads_are_distributions():
    model = policy.Controller((3, 5, 2), rngs=nnx.Rngs(0))
    logits = model(jnp.array([0.0, 0.5, 1.0]))
    assert logits.shape == (3, 5)
    probs = np.asarray(jax.nn.softmax(logits, axis=-1))
    np.testing.assert_allclose(probs.sum(-1), 1.0, rtol=1e-6)
    assert np.all(probs[0, 3:] == 0) and np.all(probs[2, 2:] == 0)
    assert np.all(probs[1] > 0)
    # two LSTM layers of 32 units
    assert model.lstm1.hidden_features == 32 and model.lstm2.hidden_features == 32


def test_log_prob_matches_manual_computation():
    model = policy.Controller((3, 5, 2), rngs=nnx.Rngs(1))
    logits = np.asarray(model(jnp.array([0.2, 0.4, 0.9])), np.float64)
    action = np.array([2, 4, 1])
    manual = 0.0
    for p, n in enumerate((3, 5, 2)):
        z = logits[p, :n]
        manual += z[action[p]] - np.log(np.sum(np.exp(z - z.max()))) - z.max()
    got = float(policy.action_log_prob(jnp.asarray(logits, jnp.float32), jnp.asarray(action)))
    assert got == pytest.approx(manual, abs=1e-4)


@pytest.mark.parametrize("preset", ["default", "paper"])
def test_reinforce_moves_probability_to_rewarded_index(preset):
    strat = reinforce.make(SHAPE, 50, preset)
    ask, tell = jax.jit(strat.ask), jax.jit(strat.tell)
    state = strat.init(jax.random.key(0))
    before = float(reinforce.policy_probs(state, SHAPE, preset)[0, 3])
    for i in range(40):
        idx, state = ask(jax.random.key(i + 1), state)
        state = tell(state, idx, (idx[:, 0] == 3).astype(jnp.float32))
    after = float(reinforce.policy_probs(state, SHAPE, preset)[0, 3])
    assert before < 0.3 and after > 0.6


def test_paper_preset_exploration_schedule():
    p = reinforce.PRESETS["paper"]
    eps = np.asarray(reinforce.epsilon(jnp.array([0, 3, 4, 400, 1999, 2000, 3999]), p))
    np.testing.assert_allclose(eps, [1.0, 1.0, 0.995, max(0.995**100, 0.01),
                                     max(0.995**499, 0.01), 0.0, 0.0], rtol=1e-5)
    assert (p.batch, p.lr, p.alpha) == (25, 0.01, 1e-4)


# ------------------------------------------------------------------ strategies
@pytest.mark.parametrize("name", list(search.STRATEGIES))
def test_every_strategy_finds_the_synthetic_optimum(name):
    strat = search.make(name, SHAPE, 40)
    idx, r = run_synthetic(strat, jax.random.key(3), 25)  # 1000 evaluations, 120 scenarios
    assert float(jnp.max(r)) == 0.0
    flat = np.asarray(idx).reshape(-1, len(SHAPE))
    assert np.all((flat >= 0) & (flat < np.array(SHAPE)))


def test_grid_enumerates_every_scenario_once():
    strat = search.make("grid", SHAPE, 24)
    idx, _ = run_synthetic(strat, jax.random.key(0), 5)  # 120 = the whole space
    flat = np.ravel_multi_index(np.asarray(idx).reshape(-1, 3).T, SHAPE)
    assert sorted(flat.tolist()) == list(range(120))
    assert flat.tolist() != list(range(120))  # in a random order


def test_unknown_strategy_and_bad_batch():
    with pytest.raises(ValueError, match="unknown strategy 'ga'"):
        search.make("ga", SHAPE)
    with pytest.raises(ValueError, match="batch"):
        search.make("random", SHAPE, 0)
    with pytest.raises(ValueError, match="unknown preset 'fast'"):
        search.make("reinforce", SHAPE, None, "fast")


# ------------------------------------------------------------------ campaign driver
@pytest.fixture(scope="module")
def small_campaign():
    sp = jf.space("paper")
    strat = search.make("cem", sp.shape, 50)
    plan = campaign.plan(130, 50)  # budget not a multiple of the batch
    return sp, strat, plan


def test_campaign_budget_and_determinism(small_campaign):
    sp, strat, plan = small_campaign
    a = campaign.run(sp, jf.SUTS["carla-tm"], strat, plan, seed=1)
    b = campaign.run(sp, jf.SUTS["carla-tm"], strat, plan, seed=1)
    c = campaign.run(sp, jf.SUTS["carla-tm"], strat, plan, seed=2)
    assert a.n == 130 and a.evaluation[-1] == 130
    np.testing.assert_array_equal(a.indices, b.indices)
    np.testing.assert_array_equal(a.fields["reward"], b.fields["reward"])
    assert not np.array_equal(a.indices, c.indices)
    # records are the simulator's outcomes for the recorded scenarios
    out = jf.evaluate(sp.scenario(a.indices[:20]))
    np.testing.assert_array_equal(np.asarray(out.reward), a.fields["reward"][:20])


def test_seeds_together_equal_single_runs(small_campaign):
    sp, strat, plan = small_campaign
    many = campaign.run_seeds(sp, jf.SUTS["carla-tm"], strat, plan, [1, 2])
    one = campaign.run(sp, jf.SUTS["carla-tm"], strat, plan, seed=2)
    np.testing.assert_array_equal(many[1].indices, one.indices)
    np.testing.assert_allclose(many[1].fields["reward"], one.fields["reward"], atol=1e-6)


def test_nan_outcomes_never_rank_best():
    sp = jf.space("paper")

    def flaky(obs, state, params):  # NaN command whenever the pedestrian is slow
        return jnp.where(obs.ped_vy < 1.3, jnp.nan, 1.0), state

    res = campaign.run(sp, jf.SUT("flaky", flaky, lambda p: jnp.bool_(False)),
                       search.make("cem", sp.shape, 50), campaign.plan(200, 50), seed=0)
    assert res.fields["nonfinite"].any() and (~res.fields["nonfinite"]).any()
    b = campaign.best_index(res)
    assert not res.fields["nonfinite"][b] and np.isfinite(res.fields["reward"][b])
    assert not np.any(res.fields["collision"] & res.fields["nonfinite"])


def test_summary_measures_by_hand():
    sp = jf.space("paper")
    rew = np.array([-0.03, 0.1, 0.263, 0.05, 0.2648], np.float32)
    col = np.array([False, False, True, False, True])
    fields = {f: np.zeros(5, np.float32) for f in campaign.RECORD_FIELDS}
    fields.update(reward=rew, collision=col, nonfinite=np.zeros(5, bool))
    idx = np.array([[0] * 5, [1] * 5, [2] * 5, [3] * 5, [2] * 5], np.int32)
    res = campaign.Result(sp, 5, idx, fields, 0.0, 0.0)
    assert campaign.first_collision_evaluation(res) == 3
    assert campaign.convergence_evaluation(res) == 3  # 0.263 is within 1 % of 0.2648
    assert campaign.best_index(res) == 4
    crit = campaign.distinct_critical(res)
    assert [c["indices"][0] for c in crit] == [2]  # same scenario twice -> one entry
    assert crit[0]["times_evaluated"] == 2 and crit[0]["first_evaluation"] == 3
