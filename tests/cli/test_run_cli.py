"""The main job ``jaxfalsify run`` and ``jaxfalsify compare`` on tiny budgets: run-directory
schema, --config round trip, the closing report (bad input: test_bad_input.py)."""

import csv
import json
import re
import tomllib

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import TINY_SPACE

import jaxfalsify as jf
from jaxfalsify.cli import main

SUMMARY_KEYS = {"strategy", "space", "sut", "seed", "evaluations",
                "first_collision_evaluation", "best", "best_reached_evaluation", "n_nonfinite",
                "versions"}
BEST_KEYS = {"params", "reward", "collision", "min_distance", "final_distance",
             "high_risk_share_second_half"}


@pytest.fixture(scope="module")
def random_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "r"
    assert main(["run", "--strategy", "random", "--evaluations", "70", "--batch", "30",
                 "--seed", "3", "--out", str(out), "--quiet"]) == 0
    return out


def test_run_directory_schema(random_run):
    out = random_run
    ep = pq.read_table(out / "evaluations.parquet").to_pydict()
    sp = jf.load_space("paper")
    assert ep["evaluation"] == list(range(1, 71))
    assert ep["update"] == [i // 30 for i in range(70)]
    for name in sp.names:
        assert name in ep and f"{name}_idx" in ep
    for f in ("reward", "reward_rss", "reward_distance", "reward_collision", "collision",
              "min_distance", "final_distance", "high_risk_share",
              "high_risk_share_second_half"):
        assert len(ep[f]) == 70
    # the recorded outcome is the simulator's outcome of the recorded scenario
    idx = np.stack([ep[f"{n}_idx"] for n in sp.names], -1)
    again = jf.evaluate(sp.scenario(idx))
    np.testing.assert_array_equal(np.asarray(again.reward), np.asarray(ep["reward"], np.float32))
    s = json.loads((out / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(s) and BEST_KEYS <= set(s["best"])
    r = np.asarray(ep["reward"])
    assert s["best"]["reward"] == pytest.approx(r.max())
    assert s["evaluations"] == 70 and s["strategy"] == "random"
    col = np.asarray(ep["collision"])
    assert s["first_collision_evaluation"] == (int(np.argmax(col)) + 1 if col.any() else None)
    rows = list(csv.DictReader(open(out / "critical.csv")))
    assert len(rows) == len({tuple(i) for i in idx[col]})
    rewards = [float(row["reward"]) for row in rows]
    assert rewards == sorted(rewards, reverse=True)
    cfg = tomllib.loads((out / "config.toml").read_text())
    assert cfg["strategy"] == "random" and cfg["evaluations"] == 70 and cfg["seed"] == 3
    assert cfg["kind"] == "run" and cfg["sut_params"]["speed_limit"] == 40.0
    timing = json.loads((out / "timing.json").read_text())
    parts = sum(v for k, v in timing.items() if k.endswith("_seconds") and k != "total_seconds")
    assert timing["total_seconds"] == pytest.approx(parts) and timing["compile_seconds"] > 0
    # timing.json covers writing report.md: written after it, with a total at least the
    # report's own (which shows the wall time up to the report)
    assert (out / "report.md").stat().st_mtime_ns <= (out / "timing.json").stat().st_mtime_ns
    shown = float(re.search(r"\| wall time \| ([0-9.]+) s", (out / "report.md").read_text())[1])
    assert shown <= round(timing["total_seconds"], 1) and timing["figures_seconds"] > 0
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "complete" and status["evaluations_done"] == 70
    assert not (out / "checkpoint").exists()


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_config_round_trip_repeats_the_run(random_run, tmp_path):
    again = tmp_path / "again"
    assert main(["run", "--config", str(random_run / "config.toml"), "--out", str(again),
                 "--quiet"]) == 0
    a = pq.read_table(random_run / "evaluations.parquet")
    b = pq.read_table(again / "evaluations.parquet")
    assert a.equals(b)
    assert (random_run / "summary.json").read_bytes() == (again / "summary.json").read_bytes()
    # a flag overrides the config
    third = tmp_path / "third"
    assert main(["run", "--config", str(random_run / "config.toml"), "--seed", "4",
                 "--out", str(third), "--quiet"]) == 0
    assert not pq.read_table(third / "evaluations.parquet").equals(a)


def test_config_records_the_jax_settings_and_refuses_to_repeat_under_others(random_run,
                                                                             tmp_path, capsys):
    """config.toml's [jax] table holds this process's settings the draws depend on (oracle:
    jax.config itself); a --config whose recorded generator is another is refused in one line
    naming it, nothing written; with the line deleted it runs."""
    import tomllib

    import jax

    doc = tomllib.loads((random_run / "config.toml").read_text())
    assert doc["jax"]["jax_default_prng_impl"] == str(jax.config.jax_default_prng_impl)
    assert doc["jax"]["jax_threefry_partitionable"] == str(
        jax.config.jax_threefry_partitionable)
    text = (random_run / "config.toml").read_text()
    now = f'jax_default_prng_impl = "{jax.config.jax_default_prng_impl}"'
    other = tmp_path / "other.toml"
    other.write_text(text.replace(now, 'jax_default_prng_impl = "rbg"'))
    capsys.readouterr()
    assert main(["run", "--config", str(other), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the run had jax_default_prng_impl = rbg, this process has " \
        f"{jax.config.jax_default_prng_impl}" in err[0] and "JAX_DEFAULT_PRNG_IMPL=rbg" in err[0]
    assert not (tmp_path / "o").exists()
    # a recorded "None" (a setting left unset) is to be unset, not set to None; an unknown
    # setting is named
    precision = f'jax_default_matmul_precision = "{jax.config.jax_default_matmul_precision}"'
    assert precision in text and str(jax.config.jax_default_matmul_precision) == "None"
    from jaxfalsify.engine.problem import RunConfig
    with jax.default_matmul_precision("highest"):
        with pytest.raises(ValueError, match="unset JAX_DEFAULT_MATMUL_PRECISION to repeat"):
            RunConfig.from_toml(random_run / "config.toml", check_jax=True)
    other.write_text(text.replace(now, 'jax_bogus = "1"'))
    with pytest.raises(ValueError, match=r"\[jax\] jax_bogus: not a setting a run records"):
        RunConfig.from_toml(other, check_jax=True)
    other.write_text(text.replace(now + "\n", ""))
    assert main(["run", "--config", str(other), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    assert (tmp_path / "o" / "summary.json").read_bytes() == \
        (random_run / "summary.json").read_bytes()


def test_reinforce_paper_entry_run_and_report(tmp_path, capsys):
    out = tmp_path / "rl"
    assert main(["run", "--strategy", "reinforce/paper", "--evaluations", "50", "--out",
                 str(out), "--no-figures", "--strategy-param", "lr=0.02"]) == 0
    text = capsys.readouterr().out
    assert "Non-challenging" in text and "ego_offset" in text
    s = json.loads((out / "summary.json").read_text())
    assert s["strategy"] == "reinforce/paper" and s["batch"] == 25
    assert s["evaluations"] == 50
    cfg = tomllib.loads((out / "config.toml").read_text())["strategy_params"]
    assert cfg["lr"] == pytest.approx(0.02) and cfg["alpha"] == pytest.approx(1e-4)


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_compare_against_sweep_ground_truth(tmp_path, capsys):
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    out = tmp_path / "cmp"
    assert main(["compare", "--strategies", "random,cem", "--seeds", "2", "--evaluations",
                 "60", "--space", str(space), "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "compare.json").read_text())
    from jaxfalsify.engine.truth import sweep_arrays
    truth = sweep_arrays(jf.load_space(str(space)))
    assert result["n_collisions"] == int(truth["collision"].sum()) > 0
    assert [r["strategy"] for r in result["rows"]] == ["random", "cem"]
    for r in result["rows"]:
        assert r["seeds"] == 2 and 0 <= r["found_collision_share"] <= 1
        assert r["best_normalised_median"] <= 1.0 + 1e-6 and "best_over_global_max_median" not in r
        assert r["distinct_critical_median"] <= result["n_collisions"]
        assert [s["seed"] for s in r["per_seed"]] == [0, 1]
    assert "| random |" in (out / "compare.md").read_text()


def test_closing_report_and_report_md_agree(tmp_path, capsys):
    """One analysis for every output: the terminal's Table II and report.md's show the same
    best and typical scenarios, cell for cell."""
    out = tmp_path / "agree"
    assert main(["run", "--strategy", "random", "--evaluations", "120", "--batch", "40",
                 "--seed", "5", "--out", str(out)]) == 0
    text = capsys.readouterr().out.splitlines()
    md = (out / "report.md").read_text().splitlines()
    start = next(i for i, ln in enumerate(md) if ln.startswith("| parameter |"))
    end = next(i for i in range(start, len(md) + 1) if i == len(md) or not md[i].startswith("|"))
    md_rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in md[start + 2:end]]
    term_rows = [ln.split() for ln in text[1:len(md_rows) + 1]]
    assert len(md_rows) >= 10
    for m, t in zip(md_rows, term_rows):
        assert m[0] == t[0]
        assert " ".join(m[1:]).split() == t[1:], (m, t)
    import pyarrow.parquet as pq

    from jaxfalsify.outputs import analysis
    table = pq.read_table(out / "evaluations.parquet").to_pydict()
    ep = {k: np.asarray(v) for k, v in table.items()}
    typ = analysis.typical_non_critical(ep)
    assert md_rows[0][2] == f"{ep['ego_offset'][typ]:.0f} m"  # integers: no decimals
    assert md_rows[1][2] == f"{ep['ped_accel'][typ]:.3f}"  # declared: 3 decimals


def test_config_with_flags_drops_what_the_flag_replaces(tmp_path, monkeypatch):
    """``runs.configure`` (``run --config C`` with flags): a setting naming the same strategy
    or SUT another way keeps C's options; another strategy starts from its own options and
    batch; a space that varies a SUT parameter drops C's value for it (no clash with a flag
    that was never given); parameters merge name by name over C's; a setting that is not
    one is refused in one line."""
    from pathlib import Path

    from jaxfalsify.jobs import runs
    from jaxfalsify.suts.registry import recorded_spec

    rc = runs.RunConfig(strategy="reinforce/default", strategy_params={"hidden": 8}, batch=16)
    same = runs.configure(rc, strategy="reinforce")  # an alias: the same strategy
    assert (same.strategy, same.strategy_params, same.batch) == ("reinforce", {"hidden": 8}, 16)
    other = runs.configure(rc, strategy="random", seed=None)  # None: not given
    assert other == runs.RunConfig(strategy="random", batch=None)
    assert runs.configure(rc, strategy="random", batch=50).batch == 50  # the flag still wins
    merged = runs.configure(rc, strategy_params={"lr": 0.1})
    assert merged.strategy_params == {"hidden": 8, "lr": 0.1} and merged.batch == 16
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my_aeb.py").write_text("")
    mine = runs.RunConfig(sut=recorded_spec("my_aeb.py:AEB"), sut_params={"ttc_brake": 1.2})
    assert runs.configure(mine, sut="my_aeb.py:AEB").sut_params == {"ttc_brake": 1.2}
    assert runs.configure(mine, sut="sensor-aeb").sut_params == {}
    huge = Path(__file__).parents[2] / "experiments" / "suite" / "huge-aeb.toml"
    aeb = runs.RunConfig(sut="sensor-aeb", sut_params={"ttc_full": 2.0, "ttc_partial": 3.0,
                                                       "latency": 0.1})
    (tmp_path / "aeb.toml").write_text(aeb.to_toml())  # from a file, as --config reads it
    moved = runs.configure(tmp_path / "aeb.toml", space=str(huge))
    assert moved.sut_params == {"latency": 0.1}  # the space varies ttc_full and ttc_partial
    moved.build()  # and the run builds (it was refused: "--sut-param ttc_full: the space ...")
    # without a config every setting is applied to the defaults, nothing dropped
    assert runs.configure(None, sut="sensor-aeb", sut_params={"latency": 0.1}) == \
        runs.RunConfig(sut="sensor-aeb", sut_params={"latency": 0.1})
    # grid's default batch shrinks to a small space's size: another space resolves it anew
    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    grid = runs.RunConfig(strategy="grid").resolved()
    assert grid.batch == 200
    assert runs.configure(grid, space=str(tmp_path / "tiny.toml")).build().strategy.batch == 32
    with pytest.raises(ValueError, match="no run setting 'budget'"):
        runs.configure(None, budget=10)


def test_startup_does_not_count_a_program_that_ran_before_in_the_same_process():
    """``sleep 2 && exec python ...``: the process (one PID across exec) is over 2 s old, but
    the command's start-up is its own (oracle: the sleep's known length); without the sleep
    it is the process's age (within the slack)."""
    import subprocess
    import sys

    code = ("import jaxfalsify.base.progress as p; print(p.startup_seconds(), p.process_age())")
    out = subprocess.run(["bash", "-c", f"sleep 2 && exec {sys.executable} -c '{code}'"],
                         capture_output=True, text=True, check=True).stdout.split()
    startup, age = float(out[0]), float(out[1])
    assert age >= 2.0 and age - startup >= 1.95, (startup, age)  # the sleep is not start-up
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert float(out[0]) == pytest.approx(float(out[1]), abs=0.05)  # a plain start: its age


def test_a_jobs_startup_counts_the_command_line_up_to_the_job(monkeypatch):
    """What the command line does before the job (parsing, imports, resolving the config)
    is start-up in ``timing.json``: the job is given the process's start-up plus that time
    (oracle: a clock that advances by a known step on every reading)."""
    import itertools
    import time

    from jaxfalsify.jobs import runs

    ticks = itertools.count(1000.0, 0.25)  # every reading 0.25 s after the one before
    monkeypatch.setattr(time, "perf_counter", lambda: next(ticks))
    given = {}

    def execute(config, out, **kwargs):
        given["startup"] = kwargs["startup_seconds"]
        given["now"] = time.perf_counter()
        raise ValueError("stopped here")

    monkeypatch.setattr(runs, "execute", execute)
    assert main(["run", "--evaluations", "10"], startup=2.0) == 2
    # main's first reading (on entry) was 1000.0; the job's start-up was read just before
    # the stub's own reading, after the command line's work in between
    assert given["startup"] == pytest.approx(2.0 + (given["now"] - 0.25) - 1000.0)
    assert given["startup"] > 2.0


@pytest.mark.parametrize("env, says", [
    ({"JAX_PLATFORMS": "tpu"}, "JAX_PLATFORMS='tpu': Unable to initialize backend 'tpu'"),
    ({"JAX_DEFAULT_MATMUL_PRECISION": "bogus"},
     'Invalid value "bogus" for JAX flag jax_default_matmul_precision'),
    ({"JAX_ENABLE_X64": "maybe"}, "invalid truth value 'maybe' for environment 'JAX_ENABLE_X64'"),
    ({"XLA_FLAGS": "--xla_bogus_flag=1"},
     "XLA_FLAGS='--xla_bogus_flag=1': Unknown flag in XLA_FLAGS: --xla_bogus_flag=1"),
    ({"JAXFALSIFY_NO_CACHE": "maybe"}, "JAXFALSIFY_NO_CACHE='maybe': use 1 (no cache) or 0"),
])
def test_jax_settings_jax_refuses_give_one_line_and_exit_2(tmp_path, env, says):
    """A setting from the environment that JAX (or jaxfalsify) cannot use: one line naming it,
    exit 2, no run folder (a real process: JAX reads its settings once per process)."""
    import os
    import subprocess
    import sys

    out = tmp_path / "run"
    p = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--evaluations", "10",
                        "--out", str(out)], capture_output=True, text=True,
                       env={**os.environ, **env}, timeout=120)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and says in lines[0], p.stderr[-500:]
    assert not out.exists()


@pytest.mark.parametrize("argv", [
    ["run", "--strategy", "random", "--evaluations", "20", "--batch", "10", "--no-figures"],
    ["estimate", "--method", "mc", "--samples", "512", "--batch", "256"]])
def test_a_backend_that_cannot_start_touches_no_folder(tmp_path, argv):
    """``JAX_PLATFORMS`` naming a platform this machine lacks: one line, exit 2, checked
    before the output folder is touched: no new folder, and an earlier result in the folder
    given with ``--force`` stays as it was, byte for byte."""
    import os
    import subprocess
    import sys

    def cli(out, env=None, force=False):
        return subprocess.run([sys.executable, "-m", "jaxfalsify", *argv, "--quiet", "--out",
                               str(out), *(["--force"] if force else [])], capture_output=True,
                              text=True, env={**os.environ, **(env or {})}, timeout=300)

    bogus = {"JAX_PLATFORMS": "bogus"}
    p = cli(tmp_path / "new", bogus)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(lines) == 1 and "JAX_PLATFORMS='bogus'" in lines[0], \
        p.stderr[-500:]
    assert not (tmp_path / "new").exists()
    good = tmp_path / "good"
    assert cli(good).returncode == 0
    before = {f.relative_to(good): f.read_bytes() for f in good.rglob("*") if f.is_file()}
    p = cli(good, bogus, force=True)
    assert p.returncode == 2 and "JAX_PLATFORMS='bogus'" in p.stderr, p.stderr[-500:]
    after = {f.relative_to(good): f.read_bytes() for f in good.rglob("*") if f.is_file()}
    assert after == before and "summary.json" in {f.name for f in before}
