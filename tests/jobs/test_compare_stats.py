"""compare's statistics against hand-computed values, seeds without a collision included."""

import math

import numpy as np
import pytest

from jaxfalsify.engine import campaign
from jaxfalsify.jobs import compare_stats, compare_tables, suites


class _Space:
    shape = (3, 2, 4)


def _result(indices, rewards, collision):
    n = len(rewards)
    fields = {f: np.zeros(n, np.float32) for f in campaign.RECORD_FIELDS}
    fields.update(reward=np.asarray(rewards, np.float32), collision=np.asarray(collision, bool),
                  violated=np.asarray(collision, bool),  # a comparison's critical: collisions
                  nonfinite=np.isnan(np.asarray(rewards, np.float32)))
    return campaign.Result(_Space(), 2, np.asarray(indices, np.int32), fields)


TRUTH = {"global_max_reward": 0.26, "global_min_reward": -0.04, "n_collisions": 5,
         "n_scenarios": 24, "global_max_ties": 1}


def test_uniform_first_collision_by_hand():
    u = compare_stats.uniform_first_collision(100, 1, 50)
    assert u["p"] == 0.01 and u["expected"] == pytest.approx(100.0)  # (1 - p) / p + 1
    assert u["median"] == 69  # ceil(ln 0.5 / ln 0.99) = ceil(68.97)
    assert u["median_censored"] == 51  # beyond the budget: budget + 1
    assert u["expected_censored"] == pytest.approx((1 - 0.99 ** 51) / 0.01)
    assert u["found_probability"] == pytest.approx(1 - 0.99 ** 50)
    none = compare_stats.uniform_first_collision(100, 0, 50)
    assert math.isinf(none["expected"]) and none["expected_censored"] == 51
    assert compare_stats.uniform_first_collision(10, 10, 5)["expected"] == 1.0


def test_seed_stats_and_row_by_hand_with_a_failed_seed():
    idx = [[0, 0, 0], [2, 1, 3], [1, 0, 2], [2, 0, 0], [0, 1, 3], [1, 1, 1], [2, 1, 0],
           [1, 0, 1]]  # corners: rows 0, 1, 3, 4, 6 (every index first or last)
    seeds = [
        _result(idx, [0.0, 0.01, 0.25, 0.26, 0.0, 0.1, 0.2, 0.26],
                [0, 0, 1, 1, 0, 0, 0, 1]),  # first collision at 3, reaches the max
        _result(idx, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.24],
                [0, 0, 0, 0, 0, 0, 0, 1]),  # first at 8
        _result(idx, [-0.02, -0.04, np.nan, -0.03, -0.01, -0.02, -0.02, -0.03],
                [0] * 8),  # none: counts budget + 1 = 9
    ]
    st = [compare_stats.seed_stats(s, r, TRUTH, budget=8) for s, r in enumerate(seeds)]
    assert [s["first_collision"] for s in st] == [3, 8, None]
    assert [s["first_collision_censored"] for s in st] == [3, 8, 9]
    assert [s["reached_global_max"] for s in st] == [True, False, False]
    # (best - min) / (max - min): (0.26 + 0.04) / 0.3, (0.24 + 0.04) / 0.3, (-0.01 + 0.04) / 0.3
    np.testing.assert_allclose([s["best_normalised"] for s in st], [1.0, 0.28 / 0.3, 0.1],
                               rtol=1e-5)
    assert st[2]["best"] == pytest.approx(-0.01) and st[2]["best_normalised"] > 0
    assert [s["distinct"] for s in st] == [3, 1, 0]  # rows 2, 3, 7 are distinct scenarios
    assert st[0]["corner_share"] == pytest.approx(5 / 8)
    # the last quarter (2 evaluations): mean of 0.2, 0.26; of -0.02, -0.03
    assert st[0]["final_mean_reward"] == pytest.approx(0.23)
    assert st[2]["final_mean_reward"] == pytest.approx(-0.025)
    row = compare_stats.strategy_row("x", st, TRUTH, wall=1.0)
    assert row["found_collision_share"] == pytest.approx(2 / 3)
    # over all seeds, 9 for the failed one: [3, 8, 9] -> median 8, IQR 5.5 .. 8.5
    assert row["first_collision_median"] == 8.0
    assert row["first_collision_iqr"] == [5.5, 8.5]
    assert row["best_normalised_median"] == pytest.approx(0.28 / 0.3, rel=1e-5)
    assert row["seeds_reaching_global_max"] == 1
    assert row["distinct_critical_median"] == 1.0
    assert row["corner_share_median"] == pytest.approx(5 / 8)
    md = compare_tables.table_markdown({"rows": [row], "evaluations": 8, "overhead": {"x": 0.002},
                                        "n_collisions": 5, "n_scenarios": 24,
                                        "uniform_first_collision":
                                            compare_stats.uniform_first_collision(24, 5, 8),
                                        "uniform_corner_share": 8 / 24, **TRUTH})
    # not timed (a hand-built result): the search-time columns read "-", never 0
    assert "| x | 2/3 | 8 [5.5, 8.5] | - | - | 0.9333 | 1/3 |" in md
    assert "1/p = 4.8" in md


def test_shares_print_in_one_format_per_column():
    """Corner shares in percent with two significant digits whatever their size (a column
    never mixes 1.3% and 6.7e-03); collision shares in scientific notation; none is 0."""
    assert [compare_tables._percent(x) for x in (0.013, 6.7e-3, 2.5e-5, 0.0)] == \
        ["1.3%", "0.67%", "0.0025%", "0"]
    # every evaluation on a corner (a one-scenario space), a quarter: whole percent
    assert [compare_tables._percent(x) for x in (1.0, 0.25, 0.125)] == ["100%", "25%", "12%"]
    assert [compare_tables.share_text(x) for x in (8.4e-3, 0.0)] == ["8.4e-03", "0"]


def test_suite_section_of_a_space_without_collisions():
    """A space with no collision says so (not that its failures touch an edge); one
    collision and one scenario are singular."""
    entry = {"space": "s", "sut": "carla-tm", "n_collisions": 0, "n_scenarios": 8,
             "collision_share": 0.0, "global_max_reward": -0.05, "global_max_ties": 1,
             "failures_interior": False, "overhead": {}, "uniform_corner_share": 0.5,
             "budgets": [{"budget": 4, "rows": [],
                          "uniform_first_collision":
                              compare_stats.uniform_first_collision(8, 0, 4)}]}
    text = suites.suite_markdown({"suite": "t", "seeds": 2, "entries": [entry]})
    assert "0 collisions of 8 scenarios (p = 0); global maximum -0.0500 (1 scenario); " \
        "no collision anywhere in the space." in text
    one = {**entry, "n_collisions": 1, "failures_interior": True}
    assert "1 collision of 8 scenarios" in suites.suite_markdown(
        {"suite": "t", "seeds": 2, "entries": [one]})


def test_corner_mask_one_value_parameter_is_always_a_corner():
    m = compare_stats.corner_mask(np.array([[0, 0, 4], [0, 0, 2], [2, 0, 0]]), (3, 1, 5))
    assert m.tolist() == [True, False, True]


def test_smaller_budgets_are_the_first_evaluations_by_hand():
    """The suite's budgets: statistics over the first 4 of 8 evaluations, failed seeds
    counting budget + 1 = 5; the per-budget table shows them beside uniform's expectation."""
    idx = [[0, 0, 0], [2, 1, 3], [1, 0, 2], [2, 0, 0], [0, 1, 3], [1, 1, 1], [2, 1, 0],
           [1, 0, 1]]
    seeds = [
        _result(idx, [0.0, 0.01, 0.25, 0.26, 0.0, 0.1, 0.2, 0.26], [0, 0, 1, 1, 0, 0, 0, 1]),
        _result(idx, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.24], [0, 0, 0, 0, 0, 0, 0, 1]),
    ]
    st4 = [compare_stats.seed_stats(s, r, TRUTH, budget=4) for s, r in enumerate(seeds)]
    assert [s["first_collision_censored"] for s in st4] == [3, 5]
    assert [s["reached_global_max"] for s in st4] == [True, False]
    assert [s["distinct"] for s in st4] == [2, 0]
    assert st4[0]["corner_share"] == pytest.approx(3 / 4)  # rows 0, 1, 3
    row4 = compare_stats.strategy_row("x", st4, TRUTH, wall=1.0)
    assert row4["first_collision_median"] == 4.0 and row4["seeds_reaching_global_max"] == 1
    row8 = compare_stats.strategy_row("x", [compare_stats.seed_stats(s, r, TRUTH, 8)
                                            for s, r in enumerate(seeds)], TRUTH, wall=1.0)
    result = {"budgets": [{"budget": 4, "rows": [row4],
                           "uniform_first_collision":
                               compare_stats.uniform_first_collision(24, 5, 4)},
                          {"budget": 8, "rows": [row8],
                           "uniform_first_collision":
                               compare_stats.uniform_first_collision(24, 5, 8)}],
              "overhead": {"x": 0.5}, "uniform_corner_share": 8 / 24}
    md = compare_tables.budgets_markdown(result)
    assert "| x | 1/2 / 4 [3.5, 4.5] / 1/2 / - | 2/2 / 5.5 [4.25, 6.75] / 1/2 / - |" in md
    # uniform: p = 5/24; within 4 evaluations with probability 1 - (19/24)^4
    assert f"{1 - (19 / 24) ** 4:.0%}" in md.splitlines()[-1]


def test_no_ground_truth_rows():
    """A space too large to sweep: no global maximum, so nothing is normalised against it."""
    truth = {"global_max_reward": None, "global_min_reward": None, "n_collisions": None}
    r = _result([[0, 0, 0], [1, 1, 1]], [0.0, 0.25], [0, 1])
    st = compare_stats.seed_stats(0, r, truth, budget=2)
    assert st["first_collision"] == 2 and st["best"] == pytest.approx(0.25)
    assert st["best_normalised"] is None and st["reached_global_max"] is None
    row = compare_stats.strategy_row("x", [st], truth, wall=1.0)
    assert row["seeds_reaching_global_max"] is None and row["all_critical"] is None


def test_per_strategy_options_reach_that_strategy_only():
    """``compare --strategy-param cem:elite_frac=0.5``: cem is built with elite_frac 0.5, the
    other strategies with their registry defaults; options of a strategy not compared, or
    unknown options, are refused with one line."""
    import pytest

    from jaxfalsify.jobs.compare import CompareConfig
    from jaxfalsify.search.cem import CEMParams

    cfg = CompareConfig(strategies=("random", "cem"), seeds=2, evaluations=64,
                        strategy_params={"cem": {"elite_frac": 0.5}})
    cfg.check()
    assert float(cfg.run_config("cem").build().strategy_params.elite_frac) == 0.5
    assert cfg.run_config("random").strategy_params == {}
    assert CEMParams().elite_frac != 0.5  # the option changed something
    assert 'elite_frac = 0.5' in cfg.to_toml()
    with pytest.raises(ValueError, match="'anneal' is not among the strategies"):
        CompareConfig(strategies=("cem",), strategy_params={"anneal": {"t0": 1.0}}).check()
    with pytest.raises(ValueError, match="no option 'nope'"):
        CompareConfig(strategies=("cem",), strategy_params={"cem": {"nope": 1.0}}).check()
    # a single name instead of a list (a string is a sequence of letters)
    with pytest.raises(ValueError, match="strategies must be a list of names"):
        CompareConfig(strategies="random").check()
    with pytest.raises(ValueError, match="elite_frac=1.5 is outside"):
        CompareConfig(strategies=("cem",), strategy_params={"cem": {"elite_frac": 1.5}}).check()


def _tiny_compare(tmp_path, name, jobs, stop=None):
    from conftest import TINY_SPACE

    from jaxfalsify.jobs.compare import CompareConfig, execute

    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    cfg = CompareConfig(strategies=("random", "cem", "anneal"), seeds=2, evaluations=48,
                        space=str(space), overhead=False, jobs=jobs, budgets=(16,))
    return execute(cfg, tmp_path / name, stop=stop)


@pytest.mark.slow
def test_strategies_side_by_side_give_the_same_results(tmp_path):
    """``jobs`` strategies searched at once in threads: every figure of compare.json equals the
    one-at-a-time run's (only wall times differ); the resolved jobs are recorded."""
    import json

    one = _tiny_compare(tmp_path, "one", jobs=1)
    three = _tiny_compare(tmp_path, "three", jobs=3)
    assert one["jobs"] == 1 and three["jobs"] == 3
    assert [r["strategy"] for r in three["rows"]] == ["random", "cem", "anneal"]
    drop = lambda rows: [compare_stats.without_times(r) for r in rows]  # noqa: E731
    assert drop(one["rows"]) == drop(three["rows"])
    for a, b in zip(one["budgets"], three["budgets"]):
        assert drop(a["rows"]) == drop(b["rows"])
    import tomllib

    recorded = tomllib.loads((tmp_path / "three" / "config.toml").read_text())
    assert (recorded["jobs"], recorded["budgets"], recorded["overhead"]) == (3, [16], False)
    md = (tmp_path / "three" / "compare.md").read_text()
    assert "3 strategies side by side" in md
    # the smaller budget's table is in the file, not only on the console, cell for cell
    assert compare_tables.budgets_markdown(three) in md
    assert "| 16: collision / first [IQR] / global max / search s to first | 48: " in md
    assert json.loads((tmp_path / "one" / "compare.json").read_text())["rows"][0]["per_seed"]


@pytest.mark.slow
def test_side_by_side_stop_interrupts_every_strategy_and_writes_nothing(tmp_path):
    """A stop request while strategies run side by side ends all of them at their next chunk:
    Interrupted is raised (naming how many strategies had finished) and no result is
    written."""
    import pytest

    from jaxfalsify.jobs.runs import Interrupted

    calls = []

    def stop():
        calls.append(1)
        return len(calls) > 2  # a few chunks in

    with pytest.raises(Interrupted, match=r"interrupted after \d of 3 strategies; nothing "
                       r"was written to .*stopped; run the compare again$") as e:
        _tiny_compare(tmp_path, "stopped", jobs=2, stop=stop)
    assert e.value.resume is None  # compare has no --resume: the message must not offer one
    assert not (tmp_path / "stopped" / "compare.json").exists()
    assert not (tmp_path / "stopped" / "compare.md").exists()
