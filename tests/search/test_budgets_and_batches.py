"""Each strategy's default batch and budget, as a run and a comparison resolve them (oracle:
the registry entries' declared values, and the paper's 25-per-update / 4000-evaluation
preset)."""

from __future__ import annotations

import tomllib

import jax
import pytest

from jaxfalsify import search
from jaxfalsify.jobs import compare, runs, suites


def test_default_run_is_100_updates_of_4096_and_the_paper_preset_keeps_4000():
    b = runs.RunConfig().build()
    assert (b.strategy.batch, b.plan.evaluations, b.plan.n_updates) == (4096, 409_600, 100)
    # the search explores among failures for half the default budget, then converges
    assert b.strategy_params.novelty_until == b.plan.evaluations / 2
    paper = runs.RunConfig(strategy="reinforce/paper").build()
    assert (paper.strategy.batch, paper.plan.evaluations) == (25, 4000)
    screened = runs.RunConfig(strategy="reinforce/screened").build()
    assert (screened.strategy.batch, screened.plan.evaluations) == (32, 4000)
    given = runs.RunConfig(evaluations=8192, batch=1024).build()
    assert (given.strategy.batch, given.plan.evaluations, given.plan.n_updates) == (1024, 8192, 8)


def test_config_records_the_resolved_budget_and_batch():
    rc = runs.RunConfig()
    doc = tomllib.loads(rc.resolved().to_toml())
    assert (doc["evaluations"], doc["batch"], doc["strategy"]) == (409_600, 4096,
                                                                    "reinforce/default")
    doc.pop("kind")
    again = runs.RunConfig.from_dict(doc).build()
    assert (again.plan.evaluations, again.strategy.batch) == (409_600, 4096)


def test_accelerator_batch(monkeypatch):
    """On a GPU or TPU backend the default batch is the entry's batch_accelerator (65,536 for
    reinforce/default); entries without one keep their CPU batch."""
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert search.default_batch("reinforce/default") == 65_536
    assert search.make("reinforce", (5, 5))[0].batch == 65_536
    assert search.default_batch("cem") == search.REGISTRY["cem"].batch == 200


def test_compare_batch_sets_every_strategy_and_is_recorded(tmp_path):
    cfg = compare.CompareConfig(strategies=("random", "cem", "cmaes"), seeds=1,
                                evaluations=512, batch=64)
    assert {cfg.run_config(s).build().strategy.batch for s in cfg.strategies} == {64}
    assert tomllib.loads(cfg.to_toml())["batch"] == 64
    with pytest.raises(ValueError, match="batch"):
        compare.CompareConfig(strategies=("random",), batch=0).check()
    suite = tmp_path / "s.toml"
    (tmp_path / "tiny.toml").write_text(
        'name = "tiny"\n[parameters.ego_offset]\ndistribution = "integers"\nlow = 1\n'
        'high = 4\nsamples = 4\n')
    suite.write_text('strategies = ["random", "cem"]\nbudgets = [128]\nbatch = 32\n'
                     '[[entry]]\nspace = "tiny.toml"\n')
    got = suites.load_suite(suite)
    assert got.batch == 32
    assert got.compare_config(got.entries[0]).run_config("cem").build().strategy.batch == 32
    assert suites.load_suite(suite, batch=16).batch == 16
    suite.write_text('strategies = ["random"]\nbudgets = [128]\nbatch = -1\n'
                     '[[entry]]\nspace = "tiny.toml"\n')
    with pytest.raises(ValueError, match="s.toml: batch"):
        suites.load_suite(suite)
