"""A system outside JAX: ask / tell (jaxfalsify.Falsifier) and the worker pool
(jaxfalsify.jobs.evaluators). Oracles: the built-in campaign's own scenarios and collisions (the
evaluator returns the built-in simulator's or the NumPy reference's outcomes), the
robustness ``ped_speed - 1.5`` of the test evaluators, and scenarios chosen to misbehave."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.engine import campaign
from jaxfalsify.engine.rundir import load_run
from jaxfalsify.jobs import evaluators, runs
from jaxfalsify.outputs import analysis

HERE = Path(__file__).resolve().parent
HOST = HERE.parent / "data" / "host_evaluators.py"
REFERENCE = HERE.parents[1] / "experiments" / "external" / "reference_evaluator.py"


def builtin(strategy, evaluations, seed):
    b = runs.RunConfig(strategy=strategy, evaluations=evaluations, seed=seed).build()
    return b, campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params,
                           b.plan, seed)


def jax_outcomes(space, asked):
    out = jf.evaluate({k: np.asarray(v) for k, v in space.scenario(asked.indices).items()},
                      sut="carla-tm")
    return out


@pytest.mark.parametrize("strategy,evaluations", [
    pytest.param("reinforce/screened", 64, marks=pytest.mark.slow), ("cem", 300)])
def test_ask_tell_round_trip_equals_run(tmp_path, strategy, evaluations):
    b, res = builtin(strategy, evaluations, 3)
    f = jf.Falsifier("paper", strategy=strategy, evaluations=evaluations, seed=3,
                     out=tmp_path / "ext")
    while not f.done:
        a = f.ask()
        assert f.ask() is a  # asking again before telling: the same batch
        n = min(f.batch, evaluations - a.update * f.batch)  # the last: the budget's rest
        np.testing.assert_array_equal(a.evaluation, a.update * f.batch + 1 + np.arange(n))
        o = jax_outcomes(b.space, a)
        f.tell(a, np.asarray(o.robustness), np.asarray(o.collision),
               signals={"reward": np.asarray(o.reward), "min_ttc": np.asarray(o.min_ttc),
                        "min_distance": np.asarray(o.min_distance)})
    out = f.finish()
    np.testing.assert_array_equal(out.result.indices, res.indices)
    np.testing.assert_array_equal(out.result.fields["collision"], res.fields["collision"])
    sp, rc, s, ep = load_run(out.out)  # the folder reads as a run's
    assert rc.evaluator == "python" and s["sut"] == "external"
    assert s["n_collisions"] == int(analysis.collided(res.fields).sum())
    assert s["first_collision_evaluation"] == analysis.first_collision(res.fields)
    assert (out.out / "critical.csv").read_text().count("\n") == s["n_distinct_critical"] + 1
    assert json.loads((out.out / "status.json").read_text())["state"] == "complete"
    assert not (out.out / "checkpoint").exists()
    for fig in ("reward_per_evaluation.png", "search_distribution.png",
                "failure_clusters.png"):
        assert (out.out / "figures" / fig).stat().st_size > 1000


def test_reference_through_worker_pool_equals_builtin_run(tmp_path):
    _, res = builtin("cem", 96, 5)
    rc = runs.RunConfig(strategy="cem", evaluations=96, seed=5,
                        evaluator=f"{REFERENCE}:evaluate")
    o = evaluators.run(rc, tmp_path / "ref", workers=2, figures=False)
    np.testing.assert_array_equal(o.result.indices, res.indices)
    np.testing.assert_array_equal(o.result.fields["collision"], res.fields["collision"])
    np.testing.assert_allclose(o.result.fields["robustness"], res.fields["robustness"],
                               atol=1e-4)
    assert o.summary["n_failed"] == 0


LOOP = """
import sys, numpy as np, jaxfalsify as jf
f = jf.Falsifier("paper", strategy="cem", batch=32, evaluations=160, seed=2, out=sys.argv[1],
                 resume=sys.argv[2] == "resume")
while not f.done:
    a = f.ask()
    if sys.argv[2] == "crash" and a.update == 3:
        import os; os._exit(9)  # the user's loop dies mid-batch
    f.tell(a, a.values["ped_speed"] - 1.5)
f.finish(figures=False)
"""


def test_resume_after_the_loop_was_killed(tmp_path):
    script = tmp_path / "loop.py"
    script.write_text(LOOP)
    out = tmp_path / "run"
    r = subprocess.run([sys.executable, str(script), str(out), "crash"], capture_output=True)
    assert r.returncode == 9
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "running" and status["evaluations_done"] == 3 * 32
    r = subprocess.run([sys.executable, str(script), str(out), "resume"], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    whole = tmp_path / "whole"
    r = subprocess.run([sys.executable, str(script), str(whole), "fresh"], capture_output=True)
    assert r.returncode == 0
    a, b = load_run(out)[3], load_run(whole)[3]
    for k in ("ped_speed_idx", "ego_offset_idx", "robustness"):
        np.testing.assert_array_equal(a[k], b[k])
    np.testing.assert_allclose(a["robustness"], a["ped_speed"] - 1.5, atol=1e-6)


def test_tell_refuses_bad_results_in_one_line(tmp_path):
    f = jf.Falsifier("paper", strategy="random", batch=8, evaluations=16, out=tmp_path / "r")
    a = f.ask()
    rob = a.values["ped_speed"] - 1.5
    bad = rob.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match=r"robustness of evaluation 4 \(ego_offset=") as e:
        f.tell(a, bad)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match=r"shape \(8,\)"):
        f.tell(a, rob[:5])
    with pytest.raises(ValueError, match="signal 'speed' is not one of"):
        f.tell(a, rob, signals={"speed": rob})
    # a collision flag that is not true/false (or 1/0) is refused, not read as a collision
    for flag, shown in ((np.full(8, np.nan), "is nan"), (["no"] * 8, "is 'no'"),
                        (np.full(8, 0.5), "is 0.5"), (np.array(["yes"] * 8), "is 'yes'")):
        with pytest.raises(ValueError, match=rf"collision of evaluation 1 \(ego_offset=.*"
                                             rf"{shown}: pass true or false") as e:
            f.tell(a, rob, collision=flag)
        assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="asks 8 scenarios"):
        f.ask(5)
    f.tell(a, bad, failed=np.isnan(bad))  # marked failed: accepted, recorded as failed
    with pytest.raises(ValueError, match="the batch the last ask"):
        f.tell(a, rob)
    f.tell(f.ask(), rob)
    with pytest.raises(ValueError, match="budget of 16 evaluations is spent"):
        f.ask()
    o = f.finish(figures=False)
    assert o.summary["n_failed"] == 1 and o.summary["failed_evaluations"] == [4]
    assert np.isnan(o.result.fields["robustness"][3])


def values_of(result):
    return result.space.exact_values[2][result.indices[:, 2]]  # ped_speed


def pool_batch(n=24, seed=0):
    rng = np.random.default_rng(seed)
    return {"ped_speed": rng.uniform(1.0, 2.0, n), "ego_offset": rng.uniform(1, 9, n)}


@pytest.mark.parametrize("fn,reason", [("raises_fast", "RuntimeError: walker too fast"),
                                       ("hangs_fast", "timed out after 0.5 s"),
                                       ("dies_fast", "died (exit code 3)")])
def test_pool_records_each_failing_scenario(fn, reason):
    batch = pool_batch()
    bad = batch["ped_speed"] > 1.8
    assert 0 < bad.sum() < len(bad)
    with evaluators.Pool(f"{HOST}:{fn}", workers=2, timeout=0.5, retries=1) as pool:
        res = pool.evaluate(batch)
    np.testing.assert_array_equal(res.failed, bad)
    assert set(res.errors) == set(np.nonzero(bad)[0])
    assert all(reason in r for r in res.errors.values())
    np.testing.assert_allclose(res.outputs["robustness"][~bad], batch["ped_speed"][~bad] - 1.5)


def test_pool_retries_then_succeeds(tmp_path, monkeypatch):
    monkeypatch.setenv("FLAKY_DIR", str(tmp_path))
    batch = pool_batch(10)
    with evaluators.Pool(f"{HOST}:flaky", workers=2, retries=1) as pool:
        res = pool.evaluate(batch)
    assert not res.failed.any()
    np.testing.assert_allclose(res.outputs["robustness"], batch["ped_speed"] - 1.5)
    with evaluators.Pool(f"{HOST}:flaky", workers=1, retries=0, chunk=1) as pool:
        res = pool.evaluate(pool_batch(4, seed=9))  # unseen scenarios, no second try
    assert res.failed.all()


def test_signals_and_collision_flags_reach_the_run(tmp_path):
    rc = runs.RunConfig(space="paper", strategy="random", batch=16, evaluations=48,
                        evaluator=f"{HOST}:with_signals")
    o = evaluators.run(rc, tmp_path / "sig", workers=2, figures=False)
    speed = values_of(o.result)
    np.testing.assert_array_equal(o.result.fields["collision"], speed - 1.5 < -0.2)
    np.testing.assert_allclose(o.result.fields["reward"], -2.0 * (speed - 1.5), atol=1e-6)
    np.testing.assert_allclose(o.result.fields["min_distance"], np.abs(speed - 1.5), atol=1e-6)
    assert o.summary["n_collisions"] == int(np.sum(speed - 1.5 < -0.2))


@pytest.mark.parametrize("spec,message", [
    ("nosuchmodule_xyz:evaluate", "importing nosuchmodule_xyz failed"),
    (f"{HOST}:missing", "has no attribute 'missing'"),
    (f"{HOST}:two_args", "must take one argument"),
    (f"{HOST}:NOT_CALLABLE", "is not callable"),
    ("no_colon", "an import path module:attr"),
])
def test_cli_refuses_a_bad_evaluator_in_one_line(tmp_path, capsys, monkeypatch, spec, message):
    monkeypatch.chdir(tmp_path)
    code = main(["run", "--evaluator", spec, "--out", "r", "--quiet", "--evaluations", "8"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and message in err and "\n" not in err
    assert not (tmp_path / "r").exists() and not (tmp_path / "runs").exists()


def test_cli_refuses_a_wrong_length_result_naming_it(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = main(["run", "--evaluator", f"{HOST}:wrong_length", "--out", "r", "--no-figures",
                 "--strategy", "random", "--batch", "4", "--evaluations", "8", "--retries",
                 "0", "--workers", "1"])
    assert code == 0  # every scenario failed, recorded as failed
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert s["n_failed"] == 8 and s["failed_evaluations"] == list(range(1, 9))
    # the closing lines say so, and show no scenario table (no scenario has a result)
    out = capsys.readouterr().out
    assert "No result: all 8 evaluations failed" in out and "ped_speed" not in out


def test_a_scalar_result_fails_every_scenario_with_the_reason():
    """An evaluator returning one number for a batch fails the batch, and each scenario tried
    again alone fails too (a scalar is never read as one scenario's robustness), with the
    reason; the same values as arrays succeed (oracle: ``ped_speed - 1.5``)."""
    with evaluators.Pool(f"{HOST}:scalar", workers=1, retries=1) as pool:
        res = pool.evaluate(pool_batch(3))
    assert res.failed.all()
    assert all("returned one robustness value (a scalar) for 1 scenario: return an array of "
               "shape (n,)" in r for r in res.errors.values()), res.errors
    with evaluators.Pool(f"{HOST}:returns_none", workers=1, retries=0) as pool:
        res = pool.evaluate(pool_batch(3))
    assert res.failed.all()
    assert all("returned robustness None (a missing return?)" in r
               for r in res.errors.values()), res.errors
    with evaluators.Pool(f"{HOST}:plain", workers=1, retries=0) as pool:
        ok = pool.evaluate(pool_batch(3))
    assert not ok.failed.any()
    np.testing.assert_allclose(ok.outputs["robustness"], pool_batch(3)["ped_speed"] - 1.5)


def test_a_forced_comparison_keeps_the_earlier_one_until_it_completes(tmp_path):
    """compare --evaluator --force: the earlier comparison and its runs wait in `.earlier/`
    while the forced one is interrupted, byte for byte; forced again it completes and they
    are gone."""
    from jaxfalsify.io import store

    out = tmp_path / "c"
    kw = dict(strategies=("random",), seeds=1, evaluations=8, batch=4, workers=1)
    evaluators.compare(f"{HOST}:plain", out, **kw)
    before = {str(q.relative_to(out)): q.read_bytes() for q in out.rglob("*")
              if q.is_file() and q.name != ".lock"}
    assert any(k.startswith("runs/") for k in before)
    for _ in range(2):  # the second time, `.earlier` already holds them
        with pytest.raises(store.Interrupted):
            evaluators.compare(f"{HOST}:plain", out, force=True, stop=lambda: True, **kw)
        kept = {str(q.relative_to(out / ".earlier")): q.read_bytes()
                for q in (out / ".earlier").rglob("*") if q.is_file() and q.name != ".lock"}
        assert kept == before
    evaluators.compare(f"{HOST}:plain", out, force=True, **kw)
    assert not (out / ".earlier").exists() and (out / "compare.json").exists()


def test_cli_run_with_an_evaluator(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = main(["run", "--evaluator", f"{HOST}:plain", "--out", "r", "--evaluations", "64",
                 "--workers", "2", "--no-figures"])
    assert code == 0
    s = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert s["strategy"] == "reinforce/screened" and s["evaluator"].endswith(":plain")
    sp, rc, _, ep = load_run(tmp_path / "r")
    np.testing.assert_array_equal(ep["violated"], ep["ped_speed"] - 1.5 < 0)
    assert s["n_violations"] == int(np.sum(ep["ped_speed"] < 1.5))
    assert main(["run", "--sut", "carla-tm", "--workers", "2", "--out", "x"]) == 2
    assert "--workers needs --evaluator" in capsys.readouterr().err


@pytest.mark.slow
def test_dask_cluster_evaluates_as_the_local_pool(tmp_path):
    distributed = pytest.importorskip("distributed")
    batch = pool_batch(30)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            evaluators.DaskPool(f"{HOST}:raises_fast", cluster.scheduler_address,
                                retries=1) as pool:
        res = pool.evaluate(batch)
        bad = batch["ped_speed"] > 1.8
        np.testing.assert_array_equal(res.failed, bad)
        np.testing.assert_allclose(res.outputs["robustness"][~bad],
                                   batch["ped_speed"][~bad] - 1.5)
        rc = runs.RunConfig(strategy="reinforce/screened", evaluations=64, seed=5,
                            evaluator=f"{REFERENCE}:evaluate")
        o = evaluators.run(rc, tmp_path / "dask", scheduler=cluster.scheduler_address,
                           figures=False)
    _, res = builtin("reinforce/screened", 64, 5)
    np.testing.assert_array_equal(o.result.indices, res.indices)




def test_a_scheduler_that_cannot_be_reached_leaves_every_folder_as_it_was(
        tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.chdir(tmp_path)
    small = ["--evaluations", "8", "--batch", "4", "--strategy", "random", "--quiet",
             "--no-figures"]
    assert main(["run", "--evaluator", f"{HOST}:plain", "--out", "r", "--workers", "1",
                 *small]) == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "r").iterdir() if p.is_file()}
    capsys.readouterr()
    for argv in (["run", "--evaluator", f"{HOST}:plain", "--scheduler", "bad", "--out", "r",
                  "--force", *small],
                 ["run", "--evaluator", f"{HOST}:plain", "--scheduler", "bad", "--out", "new",
                  *small],
                 ["compare", "--evaluator", f"{HOST}:plain", "--strategies", "random",
                  "--seeds", "1", "--evaluations", "8", "--batch", "4", "--scheduler", "bad",
                  "--out", "c", "--quiet"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "scheduler 'bad': cannot connect" in err and "\n" not in err
    after = {p.name: p.read_bytes() for p in (tmp_path / "r").iterdir() if p.is_file()}
    assert after == before
    assert not (tmp_path / "new").exists() and not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match="scheduler must be an address"):
        evaluators.run(runs.RunConfig(evaluator=f"{HOST}:plain"), tmp_path / "x",
                       scheduler=" ")
    assert not (tmp_path / "x").exists()


def test_the_last_batch_holds_only_the_budgets_rest(tmp_path):
    f = jf.Falsifier("paper", strategy="random", batch=8, evaluations=12, out=tmp_path / "r")
    sizes = []
    while not f.done:
        a = f.ask()
        sizes.append(len(a))
        f.tell(a, a.values["ped_speed"] - 1.5)
    assert sizes == [8, 4]
    o = f.finish(figures=False)
    assert o.result.n == 12 and o.summary["evaluations"] == 12


def test_cli_compare_with_an_evaluator(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code = main(["compare", "--evaluator", f"{HOST}:plain", "--strategies", "random,cem",
                 "--seeds", "2", "--evaluations", "40", "--batch", "8", "--workers", "2",
                 "--out", "cmp", "--quiet"])
    assert code == 0
    result = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    for name in ("random", "cem"):
        row = result["strategies"][name]
        assert row["batch"] == 8 and row["seeds"] == 2
        for seed_row in row["per_seed"]:  # against the seed's own run folder
            _, _, s, ep = load_run(tmp_path / "cmp" / "runs" / f"{name}-s{seed_row['seed']}")
            first = np.nonzero(ep["ped_speed"] < 1.5)[0]
            assert seed_row["first_failure"] == (int(first[0]) + 1 if first.size else None)
            assert seed_row["distinct_failures"] == len(
                {tuple(r) for r in np.stack([ep[f"{n}_idx"] for n in
                                             ("ego_offset", "ped_accel", "ped_speed",
                                              "ped_offset", "weather")], 1)[first]})
    assert "| random | 8 |" in capsys.readouterr().out
    assert main(["compare", "--evaluator", f"{HOST}:plain", "--sut", "sensor-aeb",
                 "--out", "x"]) == 2
    assert "cannot be combined with --evaluator" in capsys.readouterr().err


def test_a_non_finite_result_is_recorded_as_failed(tmp_path):
    rc = runs.RunConfig(strategy="random", batch=16, evaluations=48,
                        evaluator=f"{HOST}:nan_fast")
    o = evaluators.run(rc, tmp_path / "nan", workers=2, figures=False)
    bad = values_of(o.result) > 1.6
    assert bad.any()
    np.testing.assert_array_equal(o.result.fields["failed"], bad)
    assert o.summary["n_failed"] == int(bad.sum())
    assert o.summary["failed_evaluations"] == [int(e) for e in np.nonzero(bad)[0] + 1]


def test_a_pool_left_early_gives_the_next_batch_its_own_results():
    """Interrupted mid-batch (an exception from a timer), the pool's busy workers are
    restarted: the next batch gets its own robustness, never the old batch's late replies."""
    import signal

    class Early(Exception):
        pass

    def interrupt(*_):
        raise Early

    old = signal.signal(signal.SIGALRM, interrupt)
    try:
        with evaluators.Pool(f"{HOST}:hangs_fast", workers=2) as pool:
            signal.setitimer(signal.ITIMER_REAL, 0.5)
            with pytest.raises(Early):
                pool.evaluate({"ped_speed": np.array([1.9, 1.95, 2.0, 1.85])})
            slow = {"ped_speed": np.array([1.0, 1.2, 1.4, 1.6])}
            np.testing.assert_allclose(pool.evaluate(slow).outputs["robustness"],
                                       slow["ped_speed"] - 1.5)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def test_a_worker_that_died_while_idle_is_replaced():
    import time

    with evaluators.Pool(f"{HOST}:exits_after_reply", workers=1, retries=0) as pool:
        for k in range(3):
            batch = {"ped_speed": np.array([1.0, 1.1]) + k}
            res = pool.evaluate(batch)
            assert not res.failed.any()
            np.testing.assert_allclose(res.outputs["robustness"], batch["ped_speed"] - 1.5)
            time.sleep(0.5)  # the worker exits meanwhile


def test_failed_rows_keep_no_distance(tmp_path):
    rc = runs.RunConfig(strategy="random", batch=16, evaluations=32,
                        evaluator=f"{HOST}:signals_raise_fast")
    o = evaluators.run(rc, tmp_path / "f", workers=2, retries=0, figures=False)
    failed = o.result.fields["failed"]
    np.testing.assert_array_equal(failed, values_of(o.result) > 1.8)
    assert np.isnan(o.result.fields["min_distance"][failed]).all()
    np.testing.assert_allclose(o.result.fields["min_distance"][~failed],
                               np.abs(values_of(o.result)[~failed] - 1.5), atol=1e-6)


def test_resume_takes_the_interrupted_runs_pool_settings(tmp_path):
    (tmp_path / "status.json").write_text(json.dumps(
        {"state": "interrupted", "pool": {"workers": 3, "timeout": 30.0, "retries": 0,
                                          "scheduler": None}}))
    got = evaluators.pool_settings(tmp_path, workers=None, timeout=None, retries=None,
                                   scheduler=None)
    assert got == {"workers": 3, "timeout": 30.0, "retries": 0, "scheduler": None}
    got = evaluators.pool_settings(tmp_path, workers=1, timeout=None, retries=2,
                                   scheduler=None)
    assert got == {"workers": 1, "timeout": 30.0, "retries": 2, "scheduler": None}
    assert evaluators.pool_settings(None, workers=None, timeout=None, retries=None,
                                    scheduler=None)["retries"] == 1


def test_cli_evaluator_keeps_batch_and_options_and_refuses_what_it_cannot_do(
        tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--evaluator", f"{HOST}:plain", "--batch", "4", "--strategy-param",
                 "lr=0.05", "--evaluations", "8", "--workers", "1", "--out", "r",
                 "--quiet", "--no-figures"]) == 0
    rc = runs.RunConfig.from_toml(tmp_path / "r" / "config.toml")
    assert rc.strategy == "reinforce/screened" and rc.batch == 4
    assert rc.strategy_params["lr"] == 0.05
    capsys.readouterr()
    for argv, words in ((["replay", "r"], "needs the run's JAX SUT"),
                        (["export", "r", "--out", "x"], "needs the run's JAX SUT"),
                        (["run", "--evaluator", f"{HOST}:plain", "--sut-param", "x=1",
                          "--out", "y"], "sut_params 'x'")):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert words in err and "\n" not in err
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_trajectories_told_are_kept_and_drawn(tmp_path):
    rc = runs.RunConfig(strategy="random", batch=16, evaluations=48,
                        evaluator=f"{HOST}:with_trajectory")
    o = evaluators.run(rc, tmp_path / "t", workers=2, retries=0)
    speed = values_of(o.result)
    failed = speed > 1.65
    assert failed.any() and (speed < 1.5).any()
    with np.load(tmp_path / "t" / "trajectories.npz") as z:
        np.testing.assert_array_equal(z["evaluation"], np.arange(1, 49))
        t, d = z["t"], z["distance"]
    want = np.abs(speed - 1.5)[:, None] + np.arange(1, 6) * 0.1
    want[speed < 1.5, 3:] = np.nan
    want[failed] = np.nan  # a failed evaluation keeps no trajectory
    np.testing.assert_allclose(d, want, atol=1e-6)
    assert np.isnan(t[failed]).all()
    assert (tmp_path / "t" / "figures" / "distance_14_scenarios.png").stat().st_size > 1000


def test_reference_trajectories_agree_with_its_outcomes():
    sys.path.insert(0, str(REFERENCE.parent))
    try:
        import reference_evaluator as ref
    finally:
        sys.path.pop(0)
    rng = np.random.default_rng(1)
    batch = {"ego_offset": rng.uniform(1, 10, 12), "ped_speed": rng.uniform(1.0, 1.8, 12),
             "ped_accel": rng.uniform(0, 0.1, 12), "ped_offset": rng.uniform(3, 4.5, 12)}
    out = ref.with_trajectories(batch)
    d = out["trajectory"]["distance"]
    np.testing.assert_allclose(np.nanmin(d, axis=1), out["min_distance"], atol=1e-9)
    steps = np.sum(np.isfinite(d), axis=1)
    np.testing.assert_allclose(np.nanmax(out["trajectory"]["t"], axis=1), steps * 0.1,
                               atol=1e-9)


def test_a_bad_trajectory_fails_its_scenarios_with_the_reason(tmp_path):
    with evaluators.Pool(f"{HOST}:bad_trajectory", workers=1, retries=0) as pool:
        res = pool.evaluate(pool_batch(3))
    assert res.failed.all()
    assert all("trajectory distance of shape" in r for r in res.errors.values())
    f = jf.Falsifier("paper", strategy="random", batch=4, evaluations=4, out=tmp_path / "r")
    a = f.ask()
    with pytest.raises(ValueError, match=r"trajectory 'speed'"):
        f.tell(a, a.values["ped_speed"] - 1.5, trajectory={"speed": np.zeros((4, 3))})
    f.close()


def test_a_collision_flag_that_is_not_true_or_false_fails_its_batch_with_the_reason():
    """An evaluator's collision of NaN (or a string, or 0.5) is not read as a collision: the
    batch fails with the value named (oracle: the flags 0/1 the evaluator returns elsewhere)."""
    with evaluators.Pool(f"{HOST}:nan_collision", workers=1, retries=0) as pool:
        res = pool.evaluate(pool_batch(3))
    assert res.failed.all()
    assert all("returned collision nan for scenario 0" in r for r in res.errors.values())
    # booleans and 0/1 of any kind are flags (NumPy and JAX scalars, 0-d arrays, in a list)
    import jax.numpy as jnp

    from jaxfalsify.base import worker

    out = worker.call(lambda v: {"robustness": np.ones(4), "collision": [
        np.bool_(True), jnp.array(False), np.int64(1), 0.0]}, {"x": np.zeros(4)})
    np.testing.assert_array_equal(out["collision"], [True, False, True, False])


def test_trajectories_of_other_lengths_and_names_share_one_length():
    from jaxfalsify.engine.pools import _assemble

    done = {0: {"robustness": 1.0, "trajectory/distance": np.arange(8.0)},
            1: {"robustness": 2.0, "trajectory/t": np.arange(5.0),
                "trajectory/distance": np.arange(5.0)}}
    res = _assemble(3, done, {2: "boom"})
    assert res.outputs["trajectory/distance"].shape == (3, 8)
    assert res.outputs["trajectory/t"].shape == (3, 8)
    np.testing.assert_array_equal(res.outputs["trajectory/t"][1, :5], np.arange(5.0))
    assert np.isnan(res.outputs["trajectory/t"][0]).all()
    assert np.isnan(res.outputs["trajectory/t"][1, 5:]).all() and res.failed.tolist() == [
        False, False, True]


def test_an_error_that_ends_the_pool_leaves_a_failed_resumable_run(tmp_path, monkeypatch):
    """An error that ends the evaluation loop (here the pool's drive raising, as a worker
    that cannot be started does under a file limit): status.json says failed, with the error
    and the command that resumes the run, not interrupted; the resume completes the run to
    the same records as an uninterrupted one (oracle: that run)."""
    rc = runs.RunConfig(strategy="random", evaluations=96, batch=32, seed=3,
                        evaluator=f"{HOST}:plain")
    whole = evaluators.run(rc, tmp_path / "whole", workers=1, figures=False)
    calls = {"n": 0}
    real = evaluators.drive

    def broken(f, pool, progress, stop=None):
        def stop_after_two():
            calls["n"] += 1
            if calls["n"] > 2:
                raise OSError(24, "Too many open files")
            return False
        real(f, pool, progress, stop_after_two)

    monkeypatch.setattr(evaluators, "drive", broken)
    with pytest.raises(OSError, match="Too many open files"):
        evaluators.run(rc, tmp_path / "cut", workers=1, figures=False)
    status = json.loads((tmp_path / "cut" / "status.json").read_text())
    assert status["state"] == "failed" and "Too many open files" in status["error"]
    assert status["resume"] == f"jaxfalsify run --resume {tmp_path / 'cut'}"
    assert status["evaluations_done"] == 64
    monkeypatch.setattr(evaluators, "drive", real)
    again = evaluators.run(rc, tmp_path / "cut", workers=1, resume=True, figures=False)
    np.testing.assert_array_equal(again.result.indices, whole.result.indices)
