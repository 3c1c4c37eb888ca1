"""A user's own SUT named by import path (experiments/example_aeb.py) through run, sweep and
compare; its parameters recorded and traced."""

import json
import tomllib
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import TINY_SPACE, space_file_fixture

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.engine import rundir
from jaxfalsify.engine.truth import sweep_arrays
from jaxfalsify.outputs import report
from jaxfalsify.suts import registry as sut_lib

EXAMPLE = Path(__file__).parents[2] / "experiments" / "example_aeb.py"
SPEC = f"{EXAMPLE}:AEB"


tiny = space_file_fixture(TINY_SPACE, "tiny")


def test_resolved_by_file_path_and_by_module(monkeypatch):
    by_file = sut_lib.resolve(SPEC)
    assert by_file.name == SPEC and "ttc_brake" in sut_lib.param_names(by_file)
    monkeypatch.chdir(EXAMPLE.parent)
    by_module = sut_lib.resolve("example_aeb:AEB")
    assert sut_lib.params_dict(by_module.default_params) == \
        sut_lib.params_dict(by_file.default_params)
    with pytest.raises(ValueError, match="has no attribute 'BRAKE'"):
        sut_lib.resolve(f"{EXAMPLE}:BRAKE")


def test_parameters_of_any_scalar_kind_resolve(tmp_path):
    """Named parameters may be numbers or booleans (a tuple or text is refused, in
    tests/cli/test_bad_input.py), and a parameter pytree that is neither a dataclass nor a
    mapping is taken as it is: each of these resolves, its defaults intact."""
    mod = tmp_path / "kinds.py"
    mod.write_text(
        "import dataclasses\nfrom typing import NamedTuple\n"
        "from jaxfalsify.suts.registry import SUT\n\n\n"
        "@dataclasses.dataclass(frozen=True)\nclass P:\n    gain: float = 2.0\n"
        "    on: bool = True\n\n\nclass T(NamedTuple):\n    gain: float = 3.0\n\n\n"
        "def act(obs, state, p, key):\n    return 0.0, state\n\n\n"
        "FLAGS = SUT('flags', act, default_params=P())\n"
        "TUPLE = SUT('tuple', act, default_params=T())\n"
        "MAPPED = SUT('mapped', act, default_params={'gain': 1.5, 'on': False})\n")
    assert sut_lib.resolve(f"{mod}:FLAGS").default_params.on is True
    assert sut_lib.resolve(f"{mod}:TUPLE").default_params.gain == 3.0
    assert sut_lib.resolve(f"{mod}:MAPPED").default_params == {"gain": 1.5, "on": False}


def test_a_sut_that_cannot_step_is_refused_before_it_runs(tmp_path):
    """A user's SUT is traced for one step (abstractly, vmapped over scenarios) with its
    resolved parameters: the
    contract's violations give a one-line ValueError naming the SUT; a bare act function
    that keeps it loads, and a SUT without defaults works with the parameters given."""
    import jax.numpy as jnp

    from jaxfalsify.base import pytree

    mod = tmp_path / "user_suts.py"
    mod.write_text(
        "import jax.numpy as jnp\n\n"
        "def coast(obs, state, params, key):\n    return jnp.float32(0.0), state\n\n"
        "def grows(obs, state, params, key):\n    return 0.0, (state, state)\n\n"
        "def needs_params(obs, state, params, key):\n    return -params.brake, state\n\n"
        "def no_tuple(obs, state, params, key):\n    return 0.0\n\n"
        "def unbatched(obs, state, params, key):\n    import jax, numpy as np\n"
        "    cmd = jax.pure_callback(lambda x: np.float32(0.0),\n"
        "                            jax.ShapeDtypeStruct((), jnp.float32), obs.ego_x)\n"
        "    return cmd, state\n")
    assert sut_lib.resolve(f"{mod}:coast").default_params is None
    for name, needle in [("grows", "new state differs in structure"),
                         ("needs_params", "a bare act function gets params=None"),
                         ("no_tuple", "expected \\(command, state\\)"),
                         # steps alone, not vmapped over scenarios as the simulator runs it
                         ("unbatched", "vmap is only supported for the pure_callback")]:
        with pytest.raises(ValueError, match=f"SUT '.*:{name}' fails on a step: .*{needle}"):
            sut_lib.make(f"{mod}:{name}")
    # a SUT object from Python is checked where its parameters are resolved, with them
    vector = sut_lib.SUT("vector", lambda obs, s, p, k: (jnp.zeros(3), s))
    with pytest.raises(ValueError, match="SUT 'vector' fails on a step: .*expected a scalar"):
        jf.evaluate({"ego_offset": 3.0}, sut=vector)

    @pytree.dataclass
    class Brake:
        brake: float = 3.0

    braking = sut_lib.SUT("braking", lambda obs, s, p, k: (-p.brake, s))  # no defaults
    out = jf.evaluate({"ego_offset": 3.0}, sut=braking, sut_params=Brake())
    assert np.isfinite(float(out.min_distance))


def test_run_records_the_sut_and_its_parameters(tiny, tmp_path):
    out = tmp_path / "run"
    assert main(["run", "--space", str(tiny), "--sut", SPEC, "--sut-param", "noise=0",
                 "--sut-param", "ttc_brake=1.2", "--strategy", "random", "--evaluations", "64",
                 "--batch", "16", "--out", str(out), "--quiet", "--no-figures"]) == 0
    cfg = tomllib.loads((out / "config.toml").read_text())
    assert cfg["sut"] == SPEC
    assert cfg["sut_params"]["ttc_brake"] == pytest.approx(1.2) and cfg["sut_params"]["noise"] == 0
    # the recorded outcomes are the simulator's for that SUT and calibration (noise off, so
    # the PRNG keys do not matter)
    ep = pq.read_table(out / "evaluations.parquet").to_pydict()
    sp = jf.load_space(str(tiny))
    idx = np.stack([ep[f"{n}_idx"] for n in sp.names], -1)
    again = jf.evaluate(sp.scenario(idx), sut=SPEC, sut_params={"noise": 0.0, "ttc_brake": 1.2})
    np.testing.assert_array_equal(np.asarray(again.reward), np.asarray(ep["reward"], np.float32))
    other = jf.evaluate(sp.scenario(idx), sut=SPEC, sut_params={"noise": 0.0, "ttc_brake": 0.2})
    assert not np.array_equal(np.asarray(other.collision), np.asarray(again.collision))
    # config.toml repeats the run
    again_out = tmp_path / "again"
    assert main(["run", "--config", str(out / "config.toml"), "--out", str(again_out),
                 "--quiet", "--no-figures"]) == 0
    assert (out / "summary.json").read_bytes() == (again_out / "summary.json").read_bytes()


def test_a_relative_sut_path_resumes_from_another_folder(tiny, tmp_path, monkeypatch):
    """config.toml records a SUT file named by a relative path as an absolute one, so a run
    interrupted in one working folder resumes from another and ends with the files of an
    uninterrupted run (the oracle: the same run made in one go with the absolute path)."""
    from jaxfalsify.jobs import runs

    calls = iter(range(10_000))
    monkeypatch.chdir(EXAMPLE.parent.parent)
    rc = runs.RunConfig(space=str(tiny), sut="experiments/example_aeb.py:AEB",
                        sut_params={"noise": 0.0}, strategy="random", evaluations=48,
                        batch=8, checkpoint_every=1)
    with pytest.raises(runs.Interrupted):
        runs.execute(rc, tmp_path / "cut", stop=lambda: next(calls) >= 2, figures=False)
    monkeypatch.chdir(tmp_path)
    again = runs.resume_config("cut")
    assert again.sut == SPEC
    runs.execute(again, "cut", resume=True, figures=False)
    runs.execute(runs.RunConfig(**{**rc.__dict__, "sut": SPEC}), "whole", figures=False)
    for f in ("config.toml", "summary.json", "evaluations.parquet"):
        assert (tmp_path / "cut" / f).read_bytes() == (tmp_path / "whole" / f).read_bytes(), f
    # a sweep records it the same way
    from jaxfalsify.engine.sweep_config import SweepConfig

    monkeypatch.chdir(EXAMPLE.parent)
    assert SweepConfig(sut="example_aeb.py:AEB").resolved().sut == SPEC


def test_noise_uses_the_key(tiny):
    """The SUT's key: another seed gives another draw of the sensor noise."""
    sp = jf.load_space(str(tiny))
    idx = sp.unravel(np.arange(sp.size))
    big = {"noise": 20.0}
    a = jf.evaluate(sp.scenario(idx), sut=SPEC, sut_params=big, key=0)
    b = jf.evaluate(sp.scenario(idx), sut=SPEC, sut_params=big, key=0)
    c = jf.evaluate(sp.scenario(idx), sut=SPEC, sut_params=big, key=1)
    np.testing.assert_array_equal(np.asarray(a.min_distance), np.asarray(b.min_distance))
    assert not np.array_equal(np.asarray(a.min_distance), np.asarray(c.min_distance))


def test_a_stochastic_runs_draws_are_resimulated_as_evaluated(tiny, tmp_path):
    """Replay, figures and export re-simulate a stochastic SUT's evaluation with the
    campaign's own draw: the key of the run's seed, offset by the evaluation number; the
    campaign's recorded outcomes are the oracle. report.md's simulate line carries the run's
    SUT parameters and says it draws other noise."""
    from jaxfalsify.engine.campaign import evaluation_key
    from jaxfalsify.engine.rundir import load_run, resimulate

    out = tmp_path / "noisy"
    assert main(["run", "--space", str(tiny), "--sut", SPEC, "--sut-param", "noise=3",
                 "--strategy", "random", "--evaluations", "48", "--batch", "16", "--seed", "5",
                 "--out", str(out), "--quiet", "--no-figures"]) == 0
    sp, rc, _, ep = load_run(out)
    rows = np.arange(len(ep["reward"]))
    scen = sp.scenario(np.stack([ep[f"{n}_idx"] for n in sp.names], -1))
    params = {"noise": 3.0}
    again = jf.evaluate(scen, sut=SPEC, sut_params=params, key=evaluation_key(5),
                        offsets=ep["evaluation"] - 1)
    np.testing.assert_array_equal(np.asarray(again.min_distance),
                                  np.asarray(ep["min_distance"], np.float32))
    np.testing.assert_array_equal(np.asarray(again.reward), np.asarray(ep["reward"], np.float32))
    plain_key = jf.evaluate(scen, sut=SPEC, sut_params=params)  # what replay used to show
    assert not np.array_equal(np.asarray(plain_key.min_distance), np.asarray(again.min_distance))
    traj = resimulate(sp, rc, ep, rows)
    gap = np.where(traj.valid, traj.distance, np.inf).min(-1)
    np.testing.assert_allclose(gap, np.asarray(again.min_distance), atol=1e-6)
    for bad, needle in [(np.zeros(3, np.int32), "do not match the batch shape"),
                        (ep["evaluation"] - 1.0, "whole numbers"),
                        (ep["evaluation"] - 2, r"0..2\*\*31-1")]:
        with pytest.raises(ValueError, match=needle):
            jf.evaluate(scen, sut=SPEC, sut_params=params, offsets=bad)
    from jaxfalsify.outputs.report import write_report

    report = write_report(out).read_text()
    assert "--sut-param noise=3" in report and "# a stochastic SUT" in report
    assert "ttc_brake" not in report.split("## Reproduce")[1]  # a default: not repeated


def test_resume_after_the_suts_code_changed_is_refused(tiny, tmp_path):
    """A checkpoint records the code it was written under (jaxfalsify's and the SUT's file):
    resuming after the SUT's file changed is refused instead of joining two versions'
    results; unchanged, the resume completes."""
    from jaxfalsify.io import checkpoints
    from jaxfalsify.jobs import runs

    mine = tmp_path / "my_aeb.py"
    mine.write_text(EXAMPLE.read_text())
    rc = runs.RunConfig(space=str(tiny), sut=f"{mine}:AEB", strategy="random", evaluations=32,
                        batch=8, checkpoint_every=1, sut_params={"noise": 0.0})
    calls = iter(range(100))
    for name in ("edited", "kept"):
        with pytest.raises(runs.Interrupted):
            runs.execute(rc, tmp_path / name, stop=lambda: next(calls) >= 2, figures=False)
        calls = iter(range(100))
    mine.write_text(EXAMPLE.read_text().replace("brake: float = 7.0", "brake: float = 3.5"))
    with pytest.raises(checkpoints.CheckpointError, match="the SUT's or jaxfalsify's source"):
        runs.execute(rc, tmp_path / "edited", resume=True, figures=False)
    mine.write_text(EXAMPLE.read_text())
    assert runs.execute(rc, tmp_path / "kept", resume=True, figures=False).result.n == 32
    # the same bytes in another folder (a project moved): the same code
    from jaxfalsify.io import cache

    moved = tmp_path / "elsewhere" / "my_aeb.py"
    moved.parent.mkdir()
    moved.write_text(EXAMPLE.read_text())
    a, b = sut_lib.resolve(f"{mine}:AEB"), sut_lib.resolve(f"{moved}:AEB")
    assert a.act.__module__ != b.act.__module__
    assert cache.source_hash(a.act, a.init) == cache.source_hash(b.act, b.init)


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_sweep_and_compare_by_import_path(tiny, tmp_path):
    out = tmp_path / "sw"
    assert main(["sweep", "--space", str(tiny), "--sut", SPEC, "--sut-param", "noise=0",
                 "--sut-param", "ttc_brake=0.2,2.0", "--out", str(out), "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    sp = jf.load_space(str(tiny))
    for row in s["calibrations"]:
        alone = sweep_arrays(sp, SPEC, {"noise": 0.0, "ttc_brake": row["ttc_brake"]})
        assert row["n_collisions"] == int(alone["collision"].sum())
    assert s["calibrations"][0]["n_collisions"] > s["calibrations"][1]["n_collisions"]
    cmp = tmp_path / "cmp"
    assert main(["compare", "--space", str(tiny), "--sut", SPEC, "--strategies", "random",
                 "--seeds", "2", "--evaluations", "40", "--out", str(cmp), "--quiet"]) == 0
    result = json.loads((cmp / "compare.json").read_text())
    assert result["sut"] == SPEC and [r["strategy"] for r in result["rows"]] == ["random"]


def _sut_with_helper(folder, module: str, helper: str, decel: float, body: str) -> None:
    """Write a user SUT ``module:AEB`` whose ``act`` (``body``) reads ``DECEL`` from a helper
    module it imports, ``helper`` (``DECEL = decel``)."""
    (folder / f"{helper}.py").write_text(f"DECEL = {decel}\n")
    (folder / f"{module}.py").write_text(
        f"import jax.numpy as jnp\nimport {helper}\nfrom jaxfalsify.suts.registry import SUT\n\n\n"
        f"def act(obs, state, params, key):\n{body}\n\n\n"
        "def init(key, params):\n    return jnp.bool_(False)\n\n\n"
        f"AEB = SUT('{module.replace('_', '-')}', act, init, None, stochastic=False)\n")


def test_program_cache_keys_on_the_users_code(tmp_path, monkeypatch):
    """The per-user program cache must never hand back a program built from other code: a
    user SUT's key changes when a helper module it imports changes (not only its own file),
    and a user's strategy class is keyed by its module and source, not by its name (a class
    called RandomSearch is not the built-in one)."""
    import dataclasses
    import importlib

    from jaxfalsify import search
    from jaxfalsify.engine import campaign
    from jaxfalsify.search.base import Strategy

    monkeypatch.syspath_prepend(str(tmp_path))
    _sut_with_helper(tmp_path, "helper_sut", "decel_helper", 5.0,
                     "    return jnp.float32(-decel_helper.DECEL), state")
    sut = sut_lib.resolve("helper_sut:AEB")
    before = sut_lib.cache_key(sut)
    assert before == sut_lib.cache_key(sut)  # stable while nothing changes
    (tmp_path / "decel_helper.py").write_text("DECEL = 0.0\n")
    assert sut_lib.cache_key(sut) != before
    assert sut_lib.cache_key(sut_lib.resolve("carla-tm")) == "builtin:carla-tm"

    mod = tmp_path / "user_strategy.py"
    mod.write_text(
        "import dataclasses\nimport jax.numpy as jnp\nfrom jaxfalsify.search.base import "
        "Strategy\n\n\n@dataclasses.dataclass(frozen=True)\nclass RandomSearch(Strategy):\n"
        "    def init(self, key, params):\n        return jnp.int32(0)\n\n"
        "    def ask(self, key, state, params):\n"
        "        return jnp.zeros((self.batch, len(self.shape)), jnp.int32), state\n\n"
        "    def tell(self, key, state, indices, rewards, params):\n        return state\n")
    user_cls = importlib.import_module("user_strategy").RandomSearch
    assert issubclass(user_cls, Strategy) and dataclasses.is_dataclass(user_cls)
    sp = jf.load_space(str(EXAMPLE.parent / "suite" / "island-dash.toml"))
    builtin = search.make("random", sp.shape, 8)[0]
    mine = user_cls(shape=builtin.shape, batch=8)
    assert repr(mine) == repr(builtin)  # the name alone cannot tell them apart
    key = lambda s: campaign.static_key(  # noqa: E731
        campaign.Campaign(sp.layout, sut_lib.resolve("carla-tm"), s, 2))
    assert key(mine) != key(builtin)
    first = key(mine)
    mod.write_text(mod.read_text().replace("jnp.int32(0)", "jnp.int32(1)"))
    assert key(mine) != first


def test_ground_truths_and_fingerprints_follow_helpers_and_parameter_order(tmp_path,
                                                                           monkeypatch):
    """The cached ground truth and a checkpoint's code fingerprint change when a helper module
    the user's SUT imports changes (a stale truth or a resume joining two versions' results
    was possible), and two spaces listing the same parameters in another order (another
    scenario numbering) get their own truths: each equals a fresh sweep of its own space."""
    from jaxfalsify.engine import truth
    from jaxfalsify.io import cache
    from jaxfalsify.scenario.space import space_from_dict

    monkeypatch.syspath_prepend(str(tmp_path))
    _sut_with_helper(tmp_path, "gt_sut", "gt_helper", 8.0,
                     "    brake = obs.ego_speed * 3.0 > jnp.abs(obs.ped_x - obs.ego_x)\n"
                     "    return jnp.where(brake, -gt_helper.DECEL, 0.0).astype(jnp.float32), "
                     "state")
    doc = {"parameters": {"ego_offset": {"values": [2.0, 6.0, 10.0]},
                          "ped_speed": {"values": [0.8, 1.2, 1.6, 2.0]}}}
    sp = space_from_dict(doc)
    swapped = space_from_dict({"parameters": dict(reversed(list(doc["parameters"].items())))})
    assert sp.names != swapped.names and sp.shape != swapped.shape
    sut = sut_lib.resolve("gt_sut:AEB")
    for space in (sp, swapped):
        got = truth.ground_truth(space, sut)
        np.testing.assert_array_equal(got["reward"], truth.sweep_arrays(space, sut)["reward"])
    before = cache.source_hash(sut.act, sut.init)
    truths = set((cache.folder() / "truth").iterdir())
    truth.ground_truth(sp, sut)
    assert set((cache.folder() / "truth").iterdir()) == truths  # the same code: cached
    (tmp_path / "gt_helper.py").write_text("DECEL = 0.5\n")  # only the helper changes
    assert cache.source_hash(sut.act, sut.init) != before  # a resume would be refused
    truth.ground_truth(sp, sut)  # and the truth is swept anew, under a key of its own
    assert len(set((cache.folder() / "truth").iterdir()) - truths) == 1


def test_a_sut_that_is_never_finite_gets_a_summary_not_a_traceback(tiny, tmp_path, capsys):
    """Every rollout NaN (the SUT commands NaN): the sweep and compare report no global
    maximum (None, zero ties) and count the non-finite rollouts instead of failing."""
    f = tmp_path / "nan_aeb.py"
    f.write_text("import jax.numpy as jnp\nfrom jaxfalsify.suts import registry as sut\n\n"
                 "def act(obs, state, params, key):\n"
                 "    return jnp.float32(jnp.nan) * obs.ego_speed, state\n\n"
                 "AEB = sut.SUT('nan-aeb', act, lambda key, params: jnp.int32(0),\n"
                 "              sut.AutopilotParams())\n")
    size = jf.load_space(str(tiny)).size
    assert main(["sweep", "--space", str(tiny), "--sut", f"{f}:AEB", "--out",
                 str(tmp_path / "sw"), "--quiet"]) == 0
    s = json.loads((tmp_path / "sw" / "summary.json").read_text())
    assert (s["n_nonfinite"], s["n_collisions"]) == (size, 0)
    assert (s["global_max_reward"], s["global_max_ties"], s["global_max_scenario"]) == \
        (None, 0, None)
    assert f"all {size} rollouts non-finite" in capsys.readouterr().out
    assert main(["compare", "--space", str(tiny), "--sut", f"{f}:AEB", "--strategies",
                 "random", "--seeds", "2", "--evaluations", "10", "--out",
                 str(tmp_path / "cmp"), "--quiet"]) == 0
    c = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert (c["n_nonfinite"], c["global_max_reward"], c["global_max_ties"]) == (size, None, 0)
    assert [s["best"] for s in c["rows"][0]["per_seed"]] == [None, None]
    md = (tmp_path / "cmp" / "compare.md").read_text()
    assert "No scenario of the space has a finite reward" in md
    assert main(["run", "--space", str(tiny), "--sut", f"{f}:AEB", "--strategy", "random",
                 "--evaluations", "20", "--no-figures", "--out", str(tmp_path / "run")]) == 0
    r = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert (r["n_nonfinite"], r["best"]["reward"], r["best_reached_evaluation"]) == \
        (20, None, None)
    assert "No finite reward: all 20 evaluations non-finite" in capsys.readouterr().out
    report.write_report(tmp_path / "run")
    assert "none finite: all 20 evaluations" in (tmp_path / "run" / "report.md").read_text()


SUT_DIM_SPACE = """name = "sutdim"
[parameters.ego_offset]
values = [7, 8, 9]
[parameters.ped_speed]
distribution = "uniform"
low = 0.5
high = 2.0
samples = 200
[parameters."sut.ttc_full"]
values = [0.5, 0.9, 1.5]
"""


@pytest.mark.slow  # a run, its resume, figures, a --config repeat and a sweep: ~40 s
def test_a_space_varying_a_sut_parameter_round_trips(tmp_path):
    """A space with a ``sut.NAME`` dimension: its run is interrupted and resumed, its
    figures re-simulate rows of different calibrations (each equal to simulating that
    calibration alone), ``--config`` repeats it, and an interrupted sweep resumes: the
    recorded config.toml leaves the varied parameter to the space."""
    from jaxfalsify.engine import sweep_config
    from jaxfalsify.jobs import runs, sweep

    space = tmp_path / "sutdim.toml"
    space.write_text(SUT_DIM_SPACE)
    rc = runs.RunConfig(space=str(space), sut="sensor-aeb", strategy="random",
                        evaluations=40, batch=10, checkpoint_every=1)
    calls = iter(range(100))
    with pytest.raises(runs.Interrupted):
        runs.execute(rc, tmp_path / "r", stop=lambda: next(calls) == 2)
    assert "ttc_full" not in tomllib.loads((tmp_path / "r" / "config.toml").read_text())[
        "sut_params"]
    runs.execute(runs.resume_config(tmp_path / "r"), tmp_path / "r", resume=True)
    assert (tmp_path / "r" / "report.md").exists()
    sp, rc2, _, ep = rundir.load_run(tmp_path / "r")
    rows = np.arange(12)
    traj = rundir.resimulate(sp, rc2, ep, rows)
    ttc = np.asarray(ep["sut.ttc_full"])[rows]
    assert len(np.unique(ttc)) > 1
    for v in np.unique(ttc):
        sel = rows[ttc == v]
        alone = jf.simulate({n: np.asarray(ep[n])[sel] for n in ("ego_offset", "ped_speed")},
                            sut="sensor-aeb", sut_params={"ttc_full": float(v)})
        np.testing.assert_array_equal(np.asarray(traj.distance)[sel], alone.distance)
    assert main(["run", "--config", str(tmp_path / "r" / "config.toml"), "--out",
                 str(tmp_path / "again"), "--quiet", "--no-figures"]) == 0
    assert (tmp_path / "again" / "summary.json").read_bytes() == \
        (tmp_path / "r" / "summary.json").read_bytes()
    sc = sweep_config.SweepConfig(space=str(space), sut="sensor-aeb", chunk=768)  # 3 chunks x 3
    calls = iter(range(100))
    with pytest.raises(runs.Interrupted):
        sweep.execute(sc, tmp_path / "s", stop=lambda: next(calls) == 1)
    config, _ = sweep.resume_config(tmp_path / "s")
    s = sweep.execute(config, tmp_path / "s", resume=True)
    assert s["n_scenarios"] == 1800 and "ttc_full" not in config.sut_params
    assert "ttc_full" not in s["sut_params"]
