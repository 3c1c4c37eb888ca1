"""A run names its requirement: the search looks for its violations and every count of
critical scenarios is of violations, with collisions reported beside (oracle: the recorded
minimum box gap and collision flags of every evaluation)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import TINY_SPACE

from jaxfalsify.cli import main
from jaxfalsify.engine import problem
from jaxfalsify.jobs import runs


def _table(out):
    t = pq.read_table(out / "evaluations.parquet").to_pydict()
    return {k: np.asarray(v) for k, v in t.items()}


@pytest.fixture(scope="module")
def space(tmp_path_factory):
    p = tmp_path_factory.mktemp("req") / "tiny.toml"
    p.write_text(TINY_SPACE)
    return p


def test_critical_is_a_violation_of_the_requirement(space, tmp_path):
    rc = runs.RunConfig(space=str(space), strategy="random", evaluations=96, batch=16, seed=2,
                        requirement="clash", requirement_params={"epsilon": 1.5})
    o = runs.execute(rc, tmp_path / "r", figures=False)
    ep = _table(tmp_path / "r")
    want = (ep["min_distance"] - 1.5 < 0) & ~ep["nonfinite"]
    np.testing.assert_array_equal(ep["violated"], want)
    assert want.any() and (want & ~ep["collision"]).any()  # clashes that did not collide
    s = o.summary
    assert s["requirement"] == "clash" and s["requirement_params"] == {"epsilon": 1.5}
    assert s["n_violations"] == int(want.sum())
    assert s["first_violation_evaluation"] == int(np.argmax(want)) + 1
    assert s["n_collisions"] == int(np.sum(ep["collision"] & ~ep["nonfinite"]))
    names = [n[:-4] for n in ep if n.endswith("_idx")]
    idx = np.stack([ep[f"{n}_idx"] for n in names], -1)
    with open(tmp_path / "r" / "critical.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == s["n_distinct_critical"] == len(np.unique(idx[want], axis=0))
    assert all(float(r["min_distance"]) < 1.5 for r in rows)
    # the typical non-critical scenario satisfies it
    typ = runs.analysis.typical_non_critical(ep)
    assert ep["min_distance"][typ] >= 1.5
    toml = (tmp_path / "r" / "config.toml").read_text()
    assert 'requirement = "clash"' in toml and "epsilon = 1.5" in toml
    again = runs.configure(tmp_path / "r" / "config.toml")
    assert again.requirement == "clash" and dict(again.requirement_params) == {"epsilon": 1.5}


def test_without_a_requirement_critical_means_collision(space, tmp_path):
    o = runs.execute(runs.RunConfig(space=str(space), strategy="random", evaluations=64,
                                    batch=16, seed=1), tmp_path / "d", figures=False)
    ep = _table(tmp_path / "d")
    np.testing.assert_array_equal(ep["violated"], ep["collision"] & ~ep["nonfinite"])
    assert o.summary["n_violations"] == o.summary["n_collisions"]
    assert o.summary["requirement"] == "collision"


def test_a_bad_requirement_is_one_line_and_writes_nothing(space, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["run", "--space", str(space), "--requirement", "clash",
                 "--requirement-param", "eps=1", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has no parameter 'eps'" in err[0], err
    assert not out.exists()
    assert main(["run", "--space", str(space), "--requirement", "nope", "--out", str(out),
                 "--quiet"]) == 2
    assert "unknown requirement 'nope'" in capsys.readouterr().err
    assert not out.exists()


def test_the_closing_lines_count_violations(space, tmp_path, capsys):
    assert main(["run", "--space", str(space), "--strategy", "random", "--evaluations", "32",
                 "--batch", "16", "--requirement", "ttc", "--out", str(tmp_path / "t"),
                 "--no-figures"]) == 0
    s = json.loads((tmp_path / "t" / "summary.json").read_text())
    said = capsys.readouterr().out
    assert f"{s['n_violations']} violations of ttc" in said
    assert f"{s['n_collisions']} collisions" in said


def test_compare_counts_the_requirements_violations(tmp_path, capsys, monkeypatch):
    """compare --requirement clash: the ground truth's critical scenarios are the sweep's
    scenarios whose minimum box gap is below epsilon (oracle: the sweep's own min_distance
    column), and each seed's first critical evaluation is the one a run with that
    requirement and seed records."""
    from jaxfalsify.engine import campaign, truth
    from jaxfalsify.jobs import compare
    from jaxfalsify.outputs import analysis

    monkeypatch.chdir(tmp_path)
    assert main(["compare", "--requirement", "clash", "--requirement-param", "epsilon=1.5",
                 "--strategies", "random,cem", "--seeds", "2", "--evaluations", "200",
                 "--space", str(space_path(tmp_path)), "--out", "cmp", "--quiet"]) == 0
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    b = runs.RunConfig(space=str(space_path(tmp_path)), requirement="clash",
                       requirement_params={"epsilon": 1.5}).build()
    cols = truth.sweep_arrays(b.space, "carla-tm", fields=("min_distance", "nonfinite"))
    want = (cols["min_distance"] < 1.5) & ~cols["nonfinite"]
    assert result["requirement"] == "clash" and result["n_collisions"] == int(want.sum())
    assert 0 < want.sum() < want.size
    for row in result["rows"]:
        rb = compare.CompareConfig(space=str(space_path(tmp_path)), requirement="clash",
                                   requirement_params={"epsilon": 1.5},
                                   evaluations=200).run_config(row["strategy"]).build()
        for s in row["per_seed"]:
            res = campaign.run(rb.space, rb.sut, rb.sut_params, rb.strategy,
                               rb.strategy_params, rb.plan, s["seed"],
                               requirement=rb.requirement,
                               requirement_params=rb.requirement_params)
            assert s["first_collision"] == analysis.first_critical(res.fields)
            np.testing.assert_array_equal(
                res.fields["violated"], (res.fields["min_distance"] < 1.5)
                & ~res.fields["nonfinite"])
    assert "Critical: violating `clash`" in (tmp_path / "cmp" / "compare.md").read_text()
    capsys.readouterr()
    assert main(["compare", "--suite", "x.toml", "--requirement", "clash"]) == 2
    assert "drop --requirement" in capsys.readouterr().err


def space_path(tmp_path):
    p = tmp_path / "tiny.toml"
    if not p.exists():
        p.write_text(TINY_SPACE)
    return p


def test_a_suite_entry_names_its_requirement(tmp_path):
    from jaxfalsify.engine import truth
    from jaxfalsify.jobs import compare, suites

    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    suite = tmp_path / "suite.toml"
    suite.write_text('name = "s"\nbudgets = [64]\nseeds = 1\nstrategies = ["random"]\n'
                     '[[entry]]\nspace = "tiny.toml"\nrequirement = "clash"\n'
                     '[entry.requirement_params]\nepsilon = 1.5\n')
    entry = suites.load_suite(suite).entries[0]
    config = suites.load_suite(suite).compare_config(entry)
    assert config.requirement == "clash" and dict(config.requirement_params) == {"epsilon": 1.5}
    result = compare.execute(config, tmp_path / "c")
    b = config.run_config("random").build()
    cols = truth.sweep_arrays(b.space, "carla-tm", fields=("min_distance", "nonfinite"))
    assert result["n_collisions"] == int(np.sum((cols["min_distance"] < 1.5)
                                               & ~cols["nonfinite"]))
    text = suites.suite_markdown({"suite": "s", "seeds": 1, "entries": [result]})
    assert "critical: violating `clash`" in text
    suite.write_text('name = "s"\n[[entry]]\nspace = "tiny.toml"\nrequirement = 3\n')
    with pytest.raises(ValueError, match=r"entry.*requirement must be"):
        suites.load_suite(suite)


def test_ground_truth_takes_a_requirement_by_name_and_table():
    """truth.ground_truth(requirement="clash", requirement_params={...}) is the same as with
    the resolved Requirement and its parameter pytree (oracle: the sweep's min gaps)."""
    from jaxfalsify.core import requirements
    from jaxfalsify.engine import truth

    sp = problem.build_space("paper", 0)
    by_name = truth.ground_truth(sp, requirement="clash", requirement_params={"epsilon": 0.5})
    req = requirements.resolve("clash")
    by_object = truth.ground_truth(sp, requirement=req,
                                   requirement_params=requirements.with_params(
                                       req, {"epsilon": 0.5}))
    cols = truth.sweep_arrays(sp, "carla-tm", fields=("min_distance", "nonfinite"))
    want = (cols["min_distance"] < 0.5) & ~cols["nonfinite"]
    np.testing.assert_array_equal(by_name["collision"], want)
    np.testing.assert_array_equal(by_object["collision"], want)
    plain = truth.ground_truth(sp, requirement="collision")
    np.testing.assert_array_equal(plain["collision"], cols_collision(sp))


def cols_collision(sp):
    from jaxfalsify.engine import truth

    return truth.sweep_arrays(sp, "carla-tm", fields=("collision",))["collision"]


def test_a_suite_may_compare_two_requirements_on_one_space(tmp_path):
    from jaxfalsify.jobs import suites

    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    suite = tmp_path / "suite.toml"
    suite.write_text('name = "s"\n[[entry]]\nspace = "tiny.toml"\n'
                     '[[entry]]\nspace = "tiny.toml"\nrequirement = "clash"\n'
                     '[[entry]]\nspace = "tiny.toml"\nrequirement = "clash"\n'
                     '[entry.requirement_params]\nepsilon = 1.5\n')
    s = suites.load_suite(suite)
    s.check()
    assert [e.requirement for e in s.entries] == ["collision", "clash", "clash"]
    suite.write_text('name = "s"\n[[entry]]\nspace = "tiny.toml"\nrequirement = "clsh"\n')
    with pytest.raises(ValueError, match=r"entry\[0\]\.requirement: ") as e:
        suites.load_suite(suite)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("rows", ["all", "collisions", "none"])
def test_sweep_counts_a_requirements_violations(tmp_path, rows):
    """jaxfalsify sweep --requirement clash: every row's violated flag and the summary's
    count against the rows' own minimum gaps (a sweep without the requirement)."""
    from jaxfalsify.engine import truth

    p = space_path(tmp_path)
    plain = truth.sweep_arrays(problem.build_space(str(p), 0), "carla-tm",
                               fields=("min_distance", "nonfinite", "scenario"))
    want = (plain["min_distance"] < 1.5) & ~plain["nonfinite"]
    assert 0 < want.sum() < want.size
    assert main(["sweep", "--space", str(p), "--requirement", "clash", "--requirement-param",
                 "epsilon=1.5", "--rows", rows, "--out", str(tmp_path / "s"), "--quiet"]) == 0
    s = json.loads((tmp_path / "s" / "summary.json").read_text())
    assert s["n_violations"] == int(want.sum()) and s["requirement"] == "clash"
    assert s["requirement_params"] == {"epsilon": 1.5}
    if rows != "none":
        t = _table_of(tmp_path / "s" / "sweep.parquet")
        got = dict(zip(t["scenario"].tolist(), t["violated"].tolist()))
        if rows == "all":
            assert [got[int(n)] for n in plain["scenario"]] == want.tolist()
        else:
            assert sorted(got) == sorted(int(n) for n in plain["scenario"][want])


def _table_of(path):
    t = pq.read_table(path).to_pydict()
    return {k: np.asarray(v) for k, v in t.items()}


def test_a_users_requirement_file_through_run_sweep_and_estimate(tmp_path, monkeypatch):
    """reqs.py:gap (box gap below 1.2 m) named by file path: the run's violations, the sweep's
    count and the exact rate all against the rows' own minimum gaps."""
    from jaxfalsify.engine import truth
    from jaxfalsify.jobs import estimate

    monkeypatch.chdir(tmp_path)
    (tmp_path / "reqs.py").write_text("def gap(outcome, params):\n"
                                      "    return outcome.min_distance - 1.2\n")
    p = space_path(tmp_path)
    rows = truth.sweep_arrays(problem.build_space(str(p), 0), "carla-tm",
                              fields=("min_distance", "nonfinite"))
    want = (rows["min_distance"] < 1.2) & ~rows["nonfinite"]
    assert 0 < want.sum() < want.size
    assert main(["sweep", "--space", str(p), "--requirement", "reqs.py:gap", "--out", "s",
                 "--rows", "none", "--quiet"]) == 0
    assert json.loads((tmp_path / "s" / "summary.json").read_text())["n_violations"] == \
        int(want.sum())
    assert main(["run", "--space", str(p), "--requirement", "reqs.py:gap", "--strategy",
                 "random", "--evaluations", "64", "--out", "r", "--quiet",
                 "--no-figures"]) == 0
    t = _table(tmp_path / "r")
    np.testing.assert_array_equal(t["violated"], (t["min_distance"] < 1.2) & ~t["nonfinite"])
    r = estimate.estimate(estimate.EstimateConfig(space=str(p), requirement="reqs.py:gap",
                                                  method="exact"))
    assert r["estimate"] == pytest.approx(want.mean())
