"""Bad input, driven through the real command line: one line naming the problem, exit code 2,
nothing written and nothing overwritten (every file under the working folder is compared
byte for byte before and after)."""

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import TINY_SPACE

from jaxfalsify.cli import main
from jaxfalsify.engine import sweep_config
from jaxfalsify.jobs import runs, sweep


def _stopper(n):
    calls = iter(range(10_000))
    return lambda: next(calls) >= n


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A working folder holding finished, unfinished and corrupted runs and sweeps."""
    w = tmp_path_factory.mktemp("bad-input")
    (w / "tiny.toml").write_text(TINY_SPACE)
    (w / "afile").write_text("not a folder\n")
    files = {
        "malformed.toml": 'strategy = "random"\nevaluations = \n',
        "unknown_key.toml": 'strategy = "random"\nlearning_rate = 3\n',
        "wrong_type.toml": 'strategy = "random"\nevaluations = "many"\n',
        "float_seed.toml": "seed = 1.5\n",
        "config_space_inverted.toml": ('[space]\nname = "x"\n[space.parameters.ped_accel]\n'
                                'distribution = "uniform"\nlow = 0.1\nhigh = 0.0\n'
                                'samples = 3\n'),
        "zero_batch.toml": 'strategy = "random"\nbatch = 0\n',
        "bad_option.toml": 'strategy = "cem"\n[strategy_params]\nelite_frac = 7.0\n',
        "bad_sut_param.toml": '[sut_params]\nwalker_time = -2.0\n',
        "bad_strategy.toml": 'strategy = "cme"\n',
        "bad_sut.toml": 'sut = "carla_tm"\n',
        "suite_bad_sut_param.toml": '[[entry]]\nspace = "paper"\nsut = "sensor-aeb"\n'
                                    'sut_params = { wings = 2.0 }\n',
        "space_malformed.toml": "[parameters.ped_speed\nvalues = [1]\n",
        "space_unknown_param.toml": "[parameters.ped_height]\nvalues = [1.7]\n",
        "space_unknown_key.toml": "[parameters.ped_speed]\nvalues = [1.2]\ncolour = 'red'\n",
        "space_wrong_type.toml": "[parameters.ped_speed]\nvalues = [1.2, 'fast']\n",
        "space_inverted.toml": ("[parameters.ped_speed]\ndistribution = 'uniform'\nlow = 2.0\n"
                                "high = 1.0\nsamples = 3\n"),
        "space_empty_range.toml": ("[parameters.ped_speed]\ndistribution = 'uniform'\n"
                                   "low = 1.0\nhigh = 1.0\nsamples = 3\n"),
        "space_empty_values.toml": "[parameters.ped_speed]\nvalues = []\n",
        "space_nan.toml": ("[parameters.ped_speed]\ndistribution = 'normal'\nmean = nan\n"
                           "sd = 0.2\nsamples = 3\n"),
        "space_inf.toml": ("[parameters.ped_speed]\ndistribution = 'uniform'\nlow = 1.0\n"
                           "high = inf\nsamples = 3\n"),
        "space_zero_samples.toml": ("[parameters.ped_speed]\ndistribution = 'uniform'\n"
                                    "low = 1.0\nhigh = 2.0\nsamples = 0\n"),
        "space_huge_integers.toml": ("[parameters.ego_offset]\ndistribution = 'integers'\n"
                                     "low = 1\nhigh = 1000000000000\nsamples = 3\n"),
        "space_huge_samples.toml": ("[parameters.ped_speed]\ndistribution = 'uniform'\n"
                                    "low = 1.0\nhigh = 2.0\nsamples = 10000000000\n"),
        "space_huge_product.toml": "".join(
            f"[parameters.{n}]\ndistribution = 'uniform'\nlow = 0.1\nhigh = 0.2\n"
            "samples = 100000\n" for n in ("ped_accel", "ped_speed", "ped_offset", "ego_offset")),
        "space_name_int.toml": "name = 5\n[parameters.ped_speed]\nvalues = [1.2]\n",
        "space_name_array.toml": "name = [1, 2]\n[parameters.ped_speed]\nvalues = [1.2]\n",
        "space_name_table.toml": "[name]\na = 1\n[parameters.ped_speed]\nvalues = [1.2]\n",
        "space_name_nul.toml": 'name = "a\\u0000b"\n[parameters.ped_speed]\nvalues = [1.2]\n',
        "space_name_long.toml": f'name = "{"x" * 300}"\n[parameters.ped_speed]\nvalues = [1.2]\n',
        "space_name_slash.toml": 'name = "../up"\n[parameters.ped_speed]\nvalues = [1.2]\n',
        "nested.toml": "x = " + "[" * 5000 + "]" * 5000 + "\n",
        "space_sut_twice.toml": ('[parameters."sut.ttc_full"]\nvalues = [1.0]\n'
                                 "[parameters.sut.ttc_full]\nvalues = [2.0]\n"),
        "space_sut_dim.toml": "[parameters.sut.ttc_full]\nvalues = [0.5, 1.5]\n",
        "space_int_overflow.toml": ("[parameters.weather]\ndistribution = 'integers'\nlow = 0\n"
                                    "high = 100000000000000000000\nsamples = 3\n"),
        "space_bigint_values.toml": "[parameters.ped_speed]\nvalues = [1" + "0" * 400 + "]\n",
        "space_beyond_float32.toml": "[parameters.sut.ttc_full]\nvalues = [1.0, 1e39]\n",
        "space_float32_twins.toml": "[parameters.ped_speed]\nvalues = [1.0, 1.00000001]\n",
    }
    for name, text in files.items():
        (w / name).write_text(text)
    (w / "callback_raises.py").write_text(
        "import jax\nimport jax.numpy as jnp\n\n\ndef _boom(x):\n"
        "    raise RuntimeError('sensor driver crashed')\n\n\n"
        "def act(obs, state, params, key):\n"
        "    return jax.pure_callback(_boom, jax.ShapeDtypeStruct((), jnp.float32), 0.0), state\n")
    (w / "req_callback_raises.py").write_text(
        "import jax\nimport jax.numpy as jnp\n\n\ndef _boom(x):\n"
        "    raise ValueError('logger offline')\n\n\n"
        "def req(outcome, params):\n"
        "    return jax.pure_callback(_boom, jax.ShapeDtypeStruct((), jnp.float32),\n"
        "                             outcome.min_distance, vmap_method='sequential')\n")
    (w / "state_change.py").write_text(
        "import jax.numpy as jnp\nfrom jaxfalsify import SUT\n\n\ndef init(key, params):\n"
        "    return jnp.int32(0)\n\n\ndef to_float(obs, state, params, key):\n"
        "    return 0.0, state.astype(jnp.float32)\n\n\ndef grow(obs, state, params, key):\n"
        "    return 0.0, jnp.zeros(3, jnp.int32)\n\n\n"
        "dtype_change = SUT('dtype_change', to_float, init, None)\n"
        "shape_change = SUT('shape_change', grow, init, None)\n")
    (w / "getattr_raises.py").write_text(
        "def __getattr__(name):\n    raise RuntimeError('no ' + name)\n")
    (w / "badsut.py").write_text(
        "import jax.numpy as jnp\n\n\ndef two_args(obs, state):\n    return 0.0, state\n\n\n"
        "def vector(obs, state, params, key):\n    return jnp.zeros(3), state\n\n\n"
        "class NeedsArgs:\n    def __init__(self, gain):\n        pass\n\n\n"
        "def factory_keyerror():\n    return {}['cfg']\n")
    (w / "exits.py").write_text("import sys\n\nsys.exit(3)\n")
    (w / "raises_valueerror.py").write_text("raise ValueError('kaboom')\n")
    (w / "odd_defaults.py").write_text(  # parameters that are not scalars
        "import dataclasses\nfrom jaxfalsify.suts.registry import SUT\n\n\n"
        "@dataclasses.dataclass(frozen=True)\nclass P:\n    gain: float = 1.0\n"
        "    w: tuple = (1.0, 2.0)\n\n\n"
        "def act(obs, state, p, key):\n    return 0.0, state\n\n\n"
        "ARR = SUT('arr', act, default_params=P())\n"
        "WORD = SUT('word', act, default_params={'gain': 1.0, 'mode': 'fast'})\n")
    (w / "odd_numbers.py").write_text(  # defaults float32 cannot hold
        "import dataclasses\nfrom jaxfalsify.core.requirements import Requirement\n"
        "from jaxfalsify.suts.registry import SUT\n\n\n"
        "def act(obs, state, p, key):\n    return 0.0, state\n\n\n"
        "NAN = SUT('nan', act, default_params={'gain': float('nan')})\n"
        "HUGE = SUT('huge', act, default_params={'gain': 1e39})\n"
        "NAN_REQ = Requirement('nan_req', lambda o, p: o.min_ttc - p['ttc'], "
        "{'ttc': float('inf')})\n")
    (w / "callback_req.py").write_text(  # traces alone, fails under vmap
        "import jax\nimport jax.numpy as jnp\n\n\n"
        "def gap(o, p):\n    return jax.pure_callback(lambda x: x, "
        "jax.ShapeDtypeStruct((), jnp.float32), o.min_distance)\n")
    (w / "clash.py").write_text(  # a SUT parameter named like a sweep.parquet column
        "from jaxfalsify.base import pytree\nfrom jaxfalsify.suts.registry import SUT\n\n\n"
        "@pytree.dataclass\nclass P:\n    steps: float = 1.0\n\n\n"
        "def act(obs, state, p, key):\n    return -p.steps, state\n\n\n"
        "AEB = SUT('clash', act, default_params=P())\n")
    (w / "latin1.toml").write_bytes("seed = 1 # caf\xe9\n".encode("latin-1"))
    (w / "a_folder.toml").mkdir()
    (w / "lock_is_folder" / ".lock").mkdir(parents=True)  # a folder where the lock goes
    (w / "victim.txt").write_text("the user's file\n")
    (w / "lock_is_link").mkdir()
    os.symlink(w / "victim.txt", w / "lock_is_link" / ".lock")  # never followed
    os.symlink(w / "nowhere", w / "dangling")  # --out through a link to nothing
    os.mkfifo(w / "fifo.toml")
    for folder, name in [("users_report", "report.md"), ("users_sweep", "sweep.parquet"),
                         ("users_figure", "figures/critical_regions.png"),
                         ("users_compare", "compare.md")]:  # a user's files, result names
        (w / folder / name).parent.mkdir(parents=True, exist_ok=True)
        (w / folder / name).write_text("the user's own\n")
    for name, text in {
        "suite_budget_str.toml": 'budgets = [1, "a"]\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_budget_nested.toml": 'budgets = [[1]]\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_budget_twice.toml": 'budgets = [10, 10]\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_exclude_unknown.toml": '[[entry]]\nspace = "tiny.toml"\nexclude = ["nope"]\n',
        "suite_exclude_all.toml": ('strategies = ["random", "cem"]\n[[entry]]\n'
                                   'space = "tiny.toml"\nexclude = ["cem", "random"]\n'),
        "suite_space_seed_str.toml": '[[entry]]\nspace = "tiny.toml"\nspace_seed = "a"\n',
        "suite_seeds_zero.toml": 'seeds = 0\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_strategies_int.toml": 'strategies = 5\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_strategies_nested.toml": ('strategies = [["random"]]\n[[entry]]\n'
                                         'space = "tiny.toml"\n'),
        "suite_strategies_str.toml": 'strategies = "random"\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_name_table.toml": 'name = {a = 1}\n[[entry]]\nspace = "tiny.toml"\n',
        "suite_twice.toml": ('[[entry]]\nspace = "tiny.toml"\nsut_params = {full_brake = 6}\n'
                             '[[entry]]\nspace = "tiny.toml"\nsut_params = {full_brake = 6.0}\n'),
    }.items():
        (w / name).write_text(text)
    # a finished run and sweep
    assert main(["run", "--space", str(w / "tiny.toml"), "--strategy", "random",
                 "--evaluations", "40", "--batch", "8", "--out", str(w / "done"), "--quiet",
                 "--no-figures"]) == 0
    assert main(["sweep", "--space", str(w / "tiny.toml"), "--out", str(w / "sweep_done"),
                 "--quiet"]) == 0
    # finished results whose status.json was damaged afterwards: never rerun over them
    for name, text in {"done_status_garbage": "not json\n", "done_status_int": '{"state": 5}',
                       "sweep_status_list": "[1, 2]"}.items():
        shutil.copytree(w / ("sweep_done" if name.startswith("sweep") else "done"), w / name)
        (w / name / "status.json").write_text(text)
    (w / "link_to_done").symlink_to(w / "done")
    shutil.copytree(w / "done", w / "deep_top" / "runs" / "A")  # a run two levels down
    # a finished run whose config.toml was edited afterwards (its space's values, its seed)
    for name, (old, new) in {"done_edited_values": ("1.237", "1.3"),
                             "done_edited_seed": ("\nseed = 0\n", "\nseed = 1\n"),
                             "done_edited_sut": ("\nspeed_limit = 40.0\n",
                                                 "\nspeed_limit = 5.0\n")}.items():
        shutil.copytree(w / "done", w / name)
        text = (w / name / "config.toml").read_text()
        assert old in text
        (w / name / "config.toml").write_text(text.replace(old, new))
    # a finished run whose figures or report cannot be written where they go
    shutil.copytree(w / "done", w / "done_report_is_folder")
    (w / "done_report_is_folder" / "report.md").mkdir()
    shutil.copytree(w / "done", w / "done_figures_is_file")
    (w / "done_figures_is_file" / "figures").write_text("a file where the figures go\n")
    # an unfinished run, interrupted after 2 of 5 checkpointed chunks (what the CLI leaves)
    rc = runs.RunConfig(space=str(w / "tiny.toml"), strategy="random", evaluations=40,
                        batch=8, checkpoint_every=1)
    out = w / "unfinished"
    with pytest.raises(runs.Interrupted):
        runs.execute(rc, out, stop=_stopper(2), figures=False)
    ck = Path("checkpoint")
    for name, damage in {
        "corrupt_carry": lambda d: (d / ck / "carry-000002.npz").write_bytes(
            (d / ck / "carry-000002.npz").read_bytes()[:100]),
        "corrupt_state": lambda d: (d / ck / "state.json").write_text("{not json"),
        "missing_records": lambda d: (d / ck / "records-000000.npz").unlink(),
        "foreign_checkpoint": lambda d: (d / ck / "state.json").write_text(
            (d / ck / "state.json").read_text().replace("seed = 0", "seed = 1")),
        "corrupt_config": lambda d: (d / "config.toml").write_text("strategy = [\n"),
    }.items():
        shutil.copytree(out, w / name)
        damage(w / name)
    # an unfinished sweep (1 of 98 chunks committed) and a corrupted copy
    with pytest.raises(runs.Interrupted):
        sweep.execute(sweep_config.SweepConfig(chunk=1024), w / "sweep_unfinished",
                      stop=_stopper(1))
    shutil.copytree(w / "sweep_unfinished", w / "sweep_corrupt")
    (w / "sweep_corrupt" / "checkpoint" / "state.json").write_text('{"format": 1}')
    return w


CASES = [
    # malformed TOML
    (["run", "--config", "malformed.toml"], "malformed TOML"),
    (["run", "--space", "space_malformed.toml"], "malformed TOML"),
    (["run", "--resume", "corrupt_config"], "malformed TOML"),
    # unknown keys
    (["run", "--config", "unknown_key.toml"], "unknown key 'learning_rate'"),
    (["sweep", "--space", "space_unknown_param.toml"], "unknown parameter 'ped_height'"),
    (["sweep", "--space", "space_unknown_key.toml"], "colour"),
    (["run", "--bogus"], "--bogus"),
    # wrong types
    (["run", "--config", "wrong_type.toml"], "wrong_type.toml: evaluations must be an integer"),
    (["run", "--config", "float_seed.toml"], "float_seed.toml: seed must be an integer"),
    (["run", "--config", "config_space_inverted.toml"],
     "config_space_inverted.toml: [space] parameters.ped_accel: empty or inverted range"),
    (["sweep", "--space", "space_wrong_type.toml"], "'fast'"),
    (["run", "--evaluations", "ten"], "--evaluations must be an integer"),
    (["sweep", "--chunk", "x"], "--chunk must be an integer"),
    (["simulate", "ped_speed=abc"], "ped_speed='abc'"),
    # empty or inverted ranges
    (["sweep", "--space", "space_inverted.toml"], "inverted"),
    (["sweep", "--space", "space_empty_range.toml"], "empty or inverted"),
    (["run", "--space", "space_empty_values.toml"], "values is empty"),
    # NaN / inf
    (["sweep", "--space", "space_nan.toml"], "not finite"),
    (["sweep", "--space", "space_inf.toml"], "not finite"),
    (["simulate", "ped_speed=inf"], "not finite"),
    (["simulate", "ped_speed=nan"], "not finite"),
    # zero or negative budgets, batches, sizes
    (["run", "--evaluations", "0"], "--evaluations must be >= 1"),
    (["run", "--evaluations", "-5"], "--evaluations must be >= 1"),
    (["run", "--batch", "0"], "--batch must be >= 1"),
    (["run", "--batch", "-4"], "--batch must be >= 1"),
    (["run", "--checkpoint-every", "0"], "--checkpoint-every must be >= 1"),
    (["run", "--config", "zero_batch.toml"], "zero_batch.toml: batch must be in 1..1000000"),
    (["run", "--config", "bad_option.toml"],
     "bad_option.toml: [strategy_params] of 'cem': elite_frac=7.0 is outside (0, 1]"),
    (["run", "--config", "bad_sut_param.toml"],
     "bad_sut_param.toml: [sut_params]: SUT 'carla-tm': walker_time=-2.0 is outside [0, inf)"),
    (["compare", "--suite", "suite_bad_sut_param.toml"],
     "suite_bad_sut_param.toml: entry[0].sut_params: SUT 'sensor-aeb' has no parameter 'wings'"),
    (["run", "--seed", "-1"], "--seed"),
    (["sweep", "--chunk", "0"], "--chunk must be >= 1"),
    (["sweep", "--space", "space_zero_samples.toml"], "samples must be a positive integer"),
    (["compare", "--evaluations", "0"], "--evaluations must be >= 1"),
    (["compare", "--seeds", "0"], "--seeds must be >= 1"),
    (["compare", "--jobs", "0"], "--jobs must be >= 1"),
    (["compare", "--jobs", "100000"], "--jobs must be <= 256 (got 100000)"),
    (["run", "--seed", "1_000"], "--seed must be an integer (got '1_000')"),
    (["run", "--seed", "\u0663"], "--seed must be an integer"),
    # a batch larger than the space where that matters
    (["run", "--space", "tiny.toml", "--strategy", "grid", "--batch", "64"],
     "exceeds the space's 32 scenarios"),
    # unknown names
    (["run", "--sut", "tesla"], "unknown SUT 'tesla'"),
    # a built-in SUT's own functions by import path (they need its state and parameters)
    (["run", "--sut", "jaxfalsify.suts.registry:carla_tm_act"],
     "is the 'carla-tm' SUT's act function"),
    (["simulate", "--sut", "jaxfalsify.suts.registry:none_act"],
     "is the 'none' SUT's act function"),
    (["sweep", "--sut", "jaxfalsify.suts.registry:sensor_aeb_act"],
     "is the 'sensor-aeb' SUT's act function"),
    (["run", "--strategy", "ga"], "unknown strategy 'ga'"),
    (["run", "--space", "moon"], "unknown space 'moon'"),
    (["run", "--strategy", "reinforce/fast"], "unknown strategy 'reinforce/fast'"),
    (["run", "--strategy-param", "elites=3"], "no option 'elites'"),
    (["run", "--strategy-param", "elite=3"], "elite=3 is outside (0, 1]"),
    (["run", "--strategy-param", "batch=0"], "'batch' is not a strategy option"),
    (["run", "--sut-param", "wings=2"], "has no parameter 'wings'"),
    (["run", "--sut-param", "full_brake"], "expected NAME=VALUE"),
    (["run", "--sut", "no_such_module:AEB"], "cannot import no_such_module"),
    (["sweep", "--sut", "tesla"], "unknown SUT 'tesla'"),
    (["sweep", "--space", "moon"], "unknown space 'moon'"),
    (["sweep", "--rows", "some"], "--rows"),
    (["compare", "--strategies", "random,ga"], "unknown strategy 'ga'"),
    (["compare", "--strategies", "random,cem,random"], "'random' given twice"),
    (["compare", "--strategies", "reinforce,reinforce/default"],
     "'reinforce/default' given twice ('reinforce' names it too)"),
    (["simulate", "speed=1"], "unknown parameter 'speed'"),
    (["simulate", "ego_offset=30", "ego_offset=40"], "ego_offset given twice"),
    (["simulate", "sut.ttc_full=1", "--sut", "sensor-aeb", "--sut-param", "ttc_full=2"],
     "sut.ttc_full given twice (also by --sut-param)"),
    (["simulate", "sut.ttc_full=fast", "--sut", "sensor-aeb"], "sut.ttc_full='fast' is not"),
    (["simulate", "--seed", "1", "--bogus"], "unrecognized arguments: --bogus"),
    # long flags are never abbreviated (compare --seed would have meant --seeds)
    (["compare", "--seed", "3"], "unrecognized arguments: --seed 3"),
    (["run", "--evaluation", "256"], "unrecognized arguments: --evaluation 256"),
    (["run", "--sut-param", "speed_limit=abc"], "--sut-param speed_limit='abc' is not a number"),
    (["run", "--sut-param", "speed_limit=30,40"], "a list of values is for sweep"),
    (["compare", "--sut-param", "speed_limit=x"], "--sut-param speed_limit='x' is not a number"),
    (["run", "--config", "bad_strategy.toml"], "bad_strategy.toml: unknown strategy 'cme'"),
    (["run", "--config", "bad_sut.toml"], "bad_sut.toml: unknown SUT 'carla_tm'"),
    (["compare", "--strategies", "cem", "--strategy-param", "cem:elite_frac=0.2",
      "--strategy-param", "cem:elite_frac=0.3"], "--strategy-param cem:elite_frac given twice"),
    (["replay", "done", "--scenario", "worst"], "worst"),
    (["export", "done", "--scenario", "worst", "--out", "x"], "--scenario 'worst'"),
    (["export", "done", "--ego", "wheel", "--out", "x"], "--ego 'wheel'"),
    # unwritable or impossible output folders
    (["run", "--out", "/proc/jaxfalsify-out"], "cannot write in /proc"),
    (["sweep", "--out", "/proc/jaxfalsify-out"], "cannot write in /proc"),
    (["run", "--out", "afile"], "exists and is not a folder"),
    (["sweep", "--out", "afile/sub"], "afile is not a folder"),
    # an existing run folder without --resume or --force
    (["run", "--out", "done", "--strategy", "random"], "already holds summary.json"),
    (["run", "--out", "unfinished"], "pass --resume unfinished"),
    (["sweep", "--space", "tiny.toml", "--out", "sweep_done"], "already holds summary.json"),
    (["sweep", "--chunk", "1024", "--out", "sweep_unfinished"], "pass --resume"),
    # resume: wrong folder, finished run, extra flags, corrupt checkpoints
    (["run", "--resume", "nowhere"], "no config.toml"),
    (["run", "--resume", "done"], "already complete"),
    (["run", "--resume", ""], "an empty path"),
    (["sweep", "--resume", " "], "an empty path"),
    (["replay", "done", "--window", "5", "--save", "x.rrd"], "without --campaign there are none"),
    # results read back under an edited config.toml: refused, not shown with other values
    (["replay", "done_edited_values", "--save", "x.rrd"],
     "done_edited_values/config.toml does not match the run's results: ped_speed of evaluation"),
    (["export", "done_edited_values", "--out", "x"], "but 1.3 in the space config.toml builds"),
    (["figures", "done_edited_values"], "does not match the run's results"),
    (["figures", "done_report_is_folder"], "report.md is a folder; move it away"),
    (["figures", "done_figures_is_file"], "figures is not a folder; move it away"),
    (["export", "done_edited_seed", "--out", "x"],
     "does not match the run's results: seed = 1 there, 0 in summary.json"),
    (["replay", "done_edited_sut", "--save", "x.rrd"],
     "does not match the run's results: sut_params.speed_limit = 5.0 there, 40.0 in"),
    # an empty value names nothing: refused, never taken for the default
    (["run", "--strategy", ""], "--strategy '': an empty value"),
    (["run", "--evaluator", " "], "--evaluator ' ': an empty value"),
    (["compare", "--evaluator", ""], "--evaluator '': an empty value"),
    (["simulate", "--sut", ""], "--sut '': an empty value"),
    (["replay", ""], "an empty path"),
    (["run", "--config", ""], "an empty path"),
    (["compare", "--budgets", "100,"], "--budgets '100,': comma-separated integers"),
    (["compare", "--budgets", ""], "--budgets '': an empty value"),
    (["compare", "--budgets", "8,8"], "budgets: 8 given twice"),
    # an option of one value given twice: refused, not the last one silently kept
    (["run", "--seed", "1", "--seed", "2"], "--seed given twice"),
    (["estimate", "--method", "exact", "--method", "mc"], "--method given twice"),
    (["estimate", "--method", "exact", "--samples", "5"], "--samples does not apply to"),
    # numbers the float32 programs cannot hold
    (["run", "--strategy", "cmaes", "--strategy-param", "std_init=1e39"],
     "std_init=1e+39 is beyond float32's range"),
    (["run", "--requirement", "clash", "--requirement-param", "epsilon=1e39"],
     "epsilon=1e+39 is beyond float32's range"),
    (["estimate", "--requirement", "rss", "--requirement-param", "margin=-1e39"],
     "margin=-1e+39 is beyond float32's range"),
    (["run", "--evaluator", "x.py:f", "--scheduler", ""], "--scheduler '': an empty value"),
    (["run", "--resume", "done_status_garbage"], "status.json is damaged (not JSON)"),
    (["run", "--resume", "done_status_int"], "status.json is damaged (state 5 is not one of"),
    (["sweep", "--resume", "sweep_status_list"], "status.json is damaged (state None"),
    (["run", "--out", "done_status_garbage"], "pass --resume"),
    (["run", "--resume", "unfinished", "--seed", "3"], "--seed cannot be combined"),
    (["run", "--out", "sweep_done"], "holds a sweep"),
    (["run", "--resume", "unfinished", "--force"], "--force cannot be combined"),
    (["run", "--resume", "corrupt_carry"], "carry-000002.npz does not match its commit record"),
    (["sweep", "--resume", "done"], "holds a run, not a sweep"),
    (["run", "--resume", "corrupt_state"], "state.json is corrupt"),
    (["run", "--resume", "missing_records"], "records-000000.npz is missing"),
    (["run", "--resume", "foreign_checkpoint"], "state.json was edited or damaged"),
    (["sweep", "--resume", "sweep_corrupt"], "corrupt"),
    (["sweep", "--resume", "sweep_done"], "already complete"),
    (["sweep", "--resume", "sweep_unfinished", "--sut", "none"], "--sut cannot be combined"),
    # sizes and ranges checked before anything is allocated
    (["sweep", "--space", "space_huge_integers.toml"], "16,777,216"),
    (["sweep", "--space", "space_int_overflow.toml"], "16,777,216"),
    (["sweep", "--space", "space_bigint_values.toml"], "not finite in float32"),
    (["sweep", "--space", "space_float32_twins.toml"], "values has duplicates (in float32"),
    (["sweep", "--space", "space_beyond_float32.toml", "--sut", "sensor-aeb"],
     "not finite in float32"),
    (["sweep", "--space", "space_sut_twice.toml", "--sut", "sensor-aeb"], "declared twice"),
    (["sweep", "--space", "space_sut_dim.toml", "--sut", "sensor-aeb", "--sut-param",
      "ttc_full=0.1,3.0"], "the space already varies it"),
    (["run", "--space", "space_sut_dim.toml", "--sut", "sensor-aeb", "--sut-param",
      "ttc_full=3.0"], "the space already varies it"),
    (["sweep", "--sut", "sensor-aeb", "--sut-param", "ttc_full=1,1e39"],
     "beyond float32's range"),
    (["sweep", "--sut", "sensor-aeb", "--sut-param", "ttc_full=1" + "0" * 400], "not finite"),
    (["sweep", "--space", "tiny.toml", "--sut", "clash.py:AEB", "--sut-param", "steps=1,2"],
     "has a column 'steps' already"),
    (["sweep", "--space", "space_huge_samples.toml"], "exceeds 100,000 values"),
    (["run", "--space", "space_huge_product.toml"], "at most 1e+18"),
    (["compare", "--strategy-param", "elite_frac=0.2"], "expected STRATEGY:NAME=VALUE"),
    (["compare", "--strategies", "cem", "--strategy-param", "cem:nope=1"], "no option 'nope'"),
    (["compare", "--strategies", "cem", "--strategy-param", "cem:batch=4"],
     "'batch' is not a strategy option"),
    (["compare", "--strategies", "cem", "--strategy-param", "anneal:t0=1"],
     "'anneal' is not among the strategies"),
    (["run", "--batch", "1000000000"], "batch must be in 1..1000000"),
    (["run", "--evaluations", "99999999999999999999"], "evaluations must be in 1..1000000000"),
    (["run", "--seed", "18446744073709551616"], "seed must be in 0..18446744073709551615"),
    (["sweep", "--chunk", "100000000"], "chunk must be in 1..16777216"),
    # unreadable inputs
    (["run", "--config", "a_folder.toml"], "is a folder"),
    (["run", "--config", "/dev/zero"], "not a regular file"),
    (["run", "--config", "fifo.toml"], "not a regular file"),
    (["run", "--config", "/proc/self/mem"], "/proc/self/mem"),
    (["run", "--config", "latin1.toml"], "latin1.toml: not UTF-8"),
    (["run", "--config", "nested.toml"], "nested.toml: malformed TOML"),
    (["sweep", "--space", "space_name_int.toml"], "name must be a string"),
    (["sweep", "--space", "space_name_array.toml"], "name must be a string"),
    (["sweep", "--space", "space_name_table.toml"], "name must be a string"),
    (["sweep", "--space", "space_name_nul.toml"], "printable"),
    (["sweep", "--space", "space_name_long.toml"], "1-64 printable"),
    (["sweep", "--space", "space_name_slash.toml"], "without /"),
    # output paths
    (["replay", "done", "--save", "/proc/x.rrd"], "cannot write in /proc"),
    (["replay", "done", "--save", "a_folder.toml"], "must end in .rrd"),
    (["replay", "done", "--save", "nowhere/x.rrd"], "no folder nowhere"),
    (["compare", "--out", "done", "--seeds", "1"], "holds a run"),
    (["sweep", "--out", "done"], "holds a run"),
    (["run", "--out", "done/figures/mine", "--quiet"],
     "--out done/figures/mine is inside done, which holds a run; choose a folder outside it"),
    (["estimate", "--out", "sweep_done/e", "--method", "mc"],
     "--out sweep_done/e is inside sweep_done, which holds a sweep"),
    (["run", "--out", ".", "--quiet"], "a run takes a folder of its own (choose another)"),
    (["sweep", "--out", "."], "a sweep takes a folder of its own"),
    (["run", "--out", "link_to_done/mine", "--quiet"],
     "is inside done, which holds a run; choose a folder outside it"),
    # distributed
    (["sweep", "--distributed", "--coordinator", "nohost", "--num-processes", "2",
      "--process-id", "0"], "expected HOST:PORT"),
    # a bad setting is refused before the process waits for a coordinator (a worker would
    # wait two minutes for one at 127.0.0.1:9, then name it instead of the setting)
    (["sweep", "--space", "tiny.toml", "--sut", "carla_tm", "--distributed", "--coordinator",
      "127.0.0.1:9", "--num-processes", "2", "--process-id", "1"], "unknown SUT 'carla_tm'"),
    # simulate validates like a space does
    (["simulate", "weather=99"], "weather=99 outside the allowed"),
    (["simulate", "weather=2.5"], "weather=2.5 must be an integer"),
    (["simulate", "ped_speed=-1"], "ped_speed=-1 outside the allowed"),
    (["simulate", "ped_offset=-100"], "outside the allowed"),
    (["simulate", "ped_change_step=-5"], "outside the allowed"),
    (["simulate", "ego_offset=1e30"], "ego_offset=1e+30 outside the allowed"),
    # a value just past a range's end is shown as given, not rounded into the range
    (["simulate", "weather=14.0000001"], "weather=14.0000001 outside the allowed [0, 14]"),
    (["simulate", "ped_speed=-0.1234567"], "ped_speed=-0.1234567 outside the allowed"),
    (["estimate", "--space", "tiny.toml", "--confidence", "1.0000001"],
     "--confidence 1.0000001: must be in (0, 1)"),
    # strategy options of the wrong type or outside their declared interval
    (["run", "--strategy", "reinforce/screened", "--strategy-param", "anchored=maybe"],
     "anchored='maybe' is not a boolean"),
    (["run", "--strategy-param", "hidden=1.5"], "hidden=1.5 is not a whole number"),
    (["run", "--strategy-param", "hidden=1e30"], "hidden=1e+30 is outside [1, 1024]"),
    # a learning rate whose Adam steps would overflow the controller's weights
    (["run", "--strategy-param", "lr=1e30"], "lr=1e+30 is outside [0, 10]"),
    (["run", "--strategy", "reinforce/paper", "--strategy-param", "lr=11"],
     "lr=11.0 is outside [0, 10]"),
    (["run", "--strategy", "reinforce/screened", "--strategy-param", "memory=99999999999"],
     "memory=99999999999 is outside"),
    (["run", "--strategy", "reinforce/screened", "--strategy-param", "advantage=3"],
     "advantage must be one of rank, normalised or a function (got 3)"),
    (["run", "--strategy", "cem", "--strategy-param", "elite_frac=1.5"],
     "elite_frac=1.5 is outside (0, 1]"),
    (["run", "--strategy-param", "lr=-1"], "lr=-1.0 is outside [0, 10]"),
    (["run", "--strategy", "anneal", "--strategy-param", "max_step=0"], "outside [1, inf)"),
    (["run", "--strategy", "cmaes", "--batch", "1"], "needs a population of at least 2"),
    (["run", "--strategy", "reinforce/screened", "--batch", "200", "--strategy-param",
      "resample=256", "--strategy-param", "explore=256"], "102,400 candidates"),
    (["compare", "--strategies", "cmaes", "--strategy-param", "cmaes:std_init=0"],
     "std_init=0.0 is outside (0, inf)"),
    # SUT parameters outside their declared interval, also in a calibration list
    (["run", "--sut-param", "speed_limit=-40"], "speed_limit=-40"),
    (["sweep", "--sut", "sensor-aeb", "--sut-param", "ttc_full=0.8,-1"], "ttc_full=-1"),
    # a user's SUT that cannot step: traced before it runs, before anything is written
    (["run", "--sut", "badsut.py:two_args"], "takes 2 positional arguments but 4"),
    # a user's SUT that raises at run time, inside the compiled rollout (a host callback)
    (["simulate", "--sut", "callback_raises.py:act"], "the SUT callback_raises.py:act raised at "
     "run time (in a host callback): RuntimeError: sensor driver crashed"),
    # a user's SUT whose state changes dtype or shape between steps
    (["run", "--sut", "state_change.py:dtype_change"],
     "SUT 'state_change.py:dtype_change' fails on a step: TypeError: act changes the state "
     "from int32[] to float32[]"),
    (["sweep", "--sut", "state_change.py:shape_change"],
     "act changes the state from int32[] to int32[3]"),
    (["compare", "--sut", "state_change.py:dtype_change", "--strategies", "random"],
     "act changes the state from int32[] to float32[]"),
    (["simulate", "--sut", "getattr_raises.py:mine"],
     "looking up 'mine' in getattr_raises.py raised RuntimeError: no mine"),
    (["sweep", "--sut", "badsut.py:vector"], "expected a scalar"),
    # a SUT class or factory that cannot be built without arguments, a module that exits
    (["run", "--sut", "badsut.py:NeedsArgs"],
     "SUT 'badsut.py:NeedsArgs' could not be built (called with no arguments): TypeError"),
    (["sweep", "--sut", "badsut.py:factory_keyerror"], "could not be built (called with no "
     "arguments): KeyError: 'cfg'"),
    (["simulate", "--sut", "datetime:datetime"], "could not be built"),
    (["run", "--sut", "exits.py:AEB"], "cannot import exits.py (SystemExit: 3)"),
    (["simulate", "--sut", "raises_valueerror.py:X"],
     "SUT 'raises_valueerror.py:X': cannot import raises_valueerror.py (ValueError: kaboom)"),
    (["estimate", "--requirement", "raises_valueerror.py:X"],
     "requirement 'raises_valueerror.py:X': cannot import raises_valueerror.py"),
    # a SUT's parameters are scalars: another default is named
    (["simulate", "--sut", "odd_defaults.py:ARR"],
     "SUT 'odd_defaults.py:ARR': parameter 'w' has the default (1.0, 2.0), not a number"),
    (["run", "--sut", "odd_defaults.py:WORD"],
     "SUT 'odd_defaults.py:WORD': parameter 'mode' has the default 'fast', not a number"),
    (["sweep", "--sut", "odd_defaults.py:ARR"], "parameter 'w' has the default"),
    # evaluator processes and retries are bounded (a process and its pipes per worker)
    (["run", "--evaluator", "odd_defaults.py:act", "--workers", "100000"],
     "--workers must be <= 256 (got 100000)"),
    (["run", "--evaluator", "odd_defaults.py:act", "--retries", "1000"],
     "--retries must be <= 100 (got 1000)"),
    (["sweep", "--space", "tiny.toml", "--requirement", "clash", "--requirement-param",
      "epsilon=1,2"], "epsilon='1,2' is not a number (one number: only sweep's --sut-param "
     "takes a list of values)"),
    # defaults a user's SUT or requirement gives that float32 cannot hold, found on loading
    (["run", "--sut", "odd_numbers.py:NAN", "--out", "run_new"],
     "SUT 'odd_numbers.py:NAN': parameter 'gain' has the default nan, which is not finite"),
    (["sweep", "--sut", "odd_numbers.py:HUGE", "--out", "run_new"],
     "parameter 'gain' has the default 1e+39, which is beyond float32's range"),
    (["estimate", "--requirement", "odd_numbers.py:NAN_REQ", "--out", "run_new"],
     "requirement 'odd_numbers.py:NAN_REQ': parameter 'ttc' has the default inf"),
    (["sweep", "--space", "tiny.toml", "--requirement", "callback_req.py:gap", "--out",
      "run_new"], "requirement 'callback_req.py:gap' fails on a batch of outcomes (vmapped)"),
    # numbers as a user types them: ASCII digits, no '_' separators
    (["run", "--sut-param", "speed_limit=3_0"], "--sut-param speed_limit='3_0' is not a number"),
    (["simulate", "ego_offset=\u0669"], "ego_offset='\u0669' is not a number"),
    (["estimate", "--confidence", "0.9_5"], "--confidence must be a number (got '0.9_5')"),
    (["compare", "--suite", "suite_twice.toml", "--entries", "tiny,tiny"],
     "--entries 'tiny,tiny': 'tiny' given twice"),
    # a run, sweep or estimate never takes a folder that holds another job's, at any depth
    (["estimate", "--out", "deep_top"], "--out deep_top holds a run in deep_top/runs/A"),
    (["run", "--out", "deep_top/runs"], "holds a run in deep_top/runs/A"),
    (["run", "--out", "/"], "--out / is the filesystem root"),
    (["simulate", "--sut-param", "speed_limit=1e-50"],
     "speed_limit=1e-50 is below float32's smallest normal number 1.18e-38"),
    (["run", "--checkpoint-every", "99999999999999999999999"],
     "--checkpoint-every must be <= 1000000000"),
    # empty lists and paths
    (["compare", "--strategies", ""], "--strategies '': an empty value"),
    (["compare", "--strategies", " , "], "no strategy named"),
    (["run", "--out", ""], "an empty path"),
    (["sweep", "--out", " "], "an empty path"),
    # every strategy of a comparison is built before its folder or a ground truth
    (["compare", "--space", "tiny.toml", "--strategies", "random,grid", "--seeds", "2",
      "--strategy-param", "grid:batch=64", "--evaluations", "64", "--out", "cmp_new"],
     "batch"),
    (["run", "--space", "tiny.toml", "--strategy", "grid", "--batch", "64", "--out",
      "cmp_new"], "batch=64 exceeds the space's 32 scenarios"),
    (["compare", "--strategies", "random", "--seeds", "10000", "--evaluations", "1000000",
      "--out", "cmp_new"], "lower --seeds or --evaluations"),
    (["run", "--evaluations", "1000000000", "--out", "run_new"], "lower --evaluations"),
    # a user's files under the names a result would take: never overwritten without --force
    (["run", "--space", "tiny.toml", "--out", "users_report"],
     "--out users_report already holds report.md (not written by jaxfalsify)"),
    (["run", "--space", "tiny.toml", "--out", "users_figure"],
     "already holds figures/critical_regions.png"),
    (["sweep", "--space", "tiny.toml", "--out", "users_sweep"], "already holds sweep.parquet"),
    (["compare", "--space", "tiny.toml", "--seeds", "1", "--out", "users_compare"],
     "already holds compare.md"),
    # malformed suites
    (["compare", "--suite", "suite_budget_str.toml"], "budgets must be an integer (got 'a')"),
    (["compare", "--suite", "suite_budget_nested.toml"], "budgets must be an integer"),
    (["compare", "--suite", "suite_budget_twice.toml"],
     "suite_budget_twice.toml: budgets: 10 given twice"),
    (["compare", "--suite", "suite_exclude_unknown.toml"],
     "suite_exclude_unknown.toml: entry[0].exclude: unknown strategy 'nope'"),
    (["compare", "--suite", "suite_exclude_all.toml"],
     "entry[0].exclude leaves none of the strategies (random, cem) to run"),
    (["compare", "--suite", "suite_space_seed_str.toml"],
     "suite_space_seed_str.toml: entry[0].space_seed must be an integer (got 'a')"),
    (["compare", "--suite", "suite_seeds_zero.toml"],
     "suite_seeds_zero.toml: seeds must be in 1..10000 (got 0)"),
    (["compare", "--suite", "suite_strategies_int.toml"], "strategies must be a list"),
    (["compare", "--suite", "suite_strategies_nested.toml"], "strategies must be a list"),
    (["compare", "--suite", "suite_strategies_str.toml"], "strategies must be a list"),
    (["compare", "--suite", "suite_name_table.toml"], "name must be a string"),
    (["compare", "--suite", "suite_twice.toml"], "entry[1] repeats entry[0]"),
    (["compare", "--strategies", "random,"], "--strategies 'random,': an empty strategy name"),
    (["compare", "--strategies", "random,,cem"], "an empty strategy name between commas"),
    (["replay", "done", "--scenarios", "99999", "--save", "x.rrd"],
     "--scenarios 99999: the run has"),
    # the lock file: never a folder, never followed through a link
    (["run", "--space", "tiny.toml", "--out", "lock_is_folder"], "lock file"),
    (["run", "--space", "tiny.toml", "--out", "lock_is_link"], "lock file"),
    (["run", "--space", "tiny.toml", "--out", "dangling"], "is a link to nothing"),
]


def _snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest()
                                       if p.is_file() else "dir")
            for p in sorted(root.rglob("*"))}


@pytest.mark.parametrize("argv, blocker", [
    (["run", "--strategy", "random", "--evaluations", "64"], "figures/critical_regions.png"),
    (["run", "--strategy", "random", "--evaluations", "64"], "summary.json"),
    (["sweep", "--space", "tiny.toml"], "sweep.parquet"),
    (["compare", "--strategies", "random", "--seeds", "1", "--evaluations", "64",
      "--space", "tiny.toml"], "compare.md"),
    (["estimate", "--space", "tiny.toml", "--method", "mc"], "timing.json"),
])
def test_a_folder_where_a_result_file_goes_is_refused_before_the_work(argv, blocker, tmp_path,
                                                                       world, capsys,
                                                                       monkeypatch):
    """A folder under the name of a file the job writes would fail the job's last writes
    after all its work: refused first, with --force too, in one line naming it, and nothing
    written. (Files written on request only, best.rrd with --rerun and replay's campaign.rrd,
    are not in the way of a run without them.)"""
    monkeypatch.chdir(world)
    out = tmp_path / "out"
    (out / blocker).mkdir(parents=True)
    before = _snapshot(out)
    assert main([*argv, "--out", str(out), "--force", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{out / blocker} is a folder where the" in err[0], err
    assert _snapshot(out) == before


@pytest.mark.parametrize("argv, needle", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_input_one_line_exit_2_nothing_written(argv, needle, world, capsys, monkeypatch):
    monkeypatch.chdir(world)
    before = _snapshot(world)
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("jaxfalsify: error: "), err
    assert needle in err, err
    assert _snapshot(world) == before


def test_console_script_exit_code_and_stderr(world):
    r = subprocess.run([sys.executable, "-m", "jaxfalsify.cli", "run", "--resume",
                        "corrupt_state"], capture_output=True, text=True, cwd=world)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.startswith("jaxfalsify: error: ") and len(r.stderr.splitlines()) == 1


def test_broken_pipe_is_quiet(world):
    """A reader that goes away (``jaxfalsify ... | head``): no error message, the exit status
    of a process killed by SIGPIPE (128 + 13), as other command-line tools end."""
    import signal

    proc = subprocess.Popen([sys.executable, "-m", "jaxfalsify.cli", "simulate", "ego_offset=9"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=world)
    proc.stdout.close()  # nobody reads: the first write fails with EPIPE
    err = proc.stderr.read().decode()
    assert proc.wait() == 128 + signal.SIGPIPE, err
    assert err == ""


def test_library_misuse_gives_one_line_errors_naming_the_argument(tmp_path):
    """The Python API's entry points name a wrong argument in one line instead of failing
    deep inside JAX: the config's type, a strategy's shape, the key, scenario values, SUT
    parameters given as NumPy scalars (accepted) or as another SUT's parameter object."""
    import jax
    import numpy as np

    import jaxfalsify as jf
    from jaxfalsify import search
    from jaxfalsify.jobs import compare
    from jaxfalsify.suts.registry import CarlaTMParams, SensorAEBParams

    for fn, cls in ((runs.execute, "problem.RunConfig"),
                    (sweep.execute, "sweep_config.SweepConfig"),
                    (compare.execute, "compare.CompareConfig")):
        with pytest.raises(ValueError, match=f"config must be a {cls} \\(got dict\\)"):
            fn({"strategy": "cem"}, tmp_path / "never")
    assert not (tmp_path / "never").exists()
    for shape in ((10, -1), (10, 0, 5), "abc", None, (2.5, 3)):
        with pytest.raises(ValueError, match="shape must be the values per parameter"):
            search.make("random", shape, 4)
    with pytest.raises(ValueError, match="wrap it with jax.random.wrap_key_data"):
        jf.evaluate({"ego_offset": 3.0}, key=jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match="key must be a typed PRNG key .* \\(got str\\)"):
        jf.evaluate({"ego_offset": 3.0}, key="abc")
    for v in ("3", True):
        with pytest.raises(ValueError, match="ego_offset=.*values must be numbers"):
            jf.evaluate({"ego_offset": v})
    with pytest.raises(ValueError, match="takes SensorAEBParams \\(got CarlaTMParams\\)"):
        jf.evaluate({"ego_offset": 3.0}, sut="sensor-aeb", sut_params=CarlaTMParams())
    with pytest.raises(ValueError, match="ttc_full=-5.0 is outside \\[0, inf\\)"):
        jf.evaluate({"ego_offset": 3.0}, sut="sensor-aeb",
                    sut_params=SensorAEBParams(ttc_full=-5.0))
    # NumPy scalars are numbers: the same outcome as the Python float
    a = jf.evaluate({"ego_offset": 3.0}, sut="sensor-aeb", sut_params={"ttc_full": 1.25})
    b = jf.evaluate({"ego_offset": 3.0}, sut="sensor-aeb",
                    sut_params={"ttc_full": np.float64(1.25)})
    assert float(a.min_distance) == float(b.min_distance)


def test_an_interrupt_while_starting_is_one_line(tmp_path):
    """Ctrl-C while JAX is still being imported (before the command's own handler exists):
    one line and exit 130 from ``python -m jaxfalsify``; a library user's import re-raises.
    The interrupt is made deterministic by a stand-in ``jax`` package that raises it."""
    fake = tmp_path / "fake" / "jax"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("raise KeyboardInterrupt\n")
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "fake")}
    r = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--out", "x"], env=env,
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 130 and r.stdout == ""
    assert r.stderr.splitlines() == ["jaxfalsify: interrupted while starting; nothing was written"]
    assert not (tmp_path / "x").exists()
    r = subprocess.run([sys.executable, "-c", "import jaxfalsify"], env=env,
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode != 0 and r.stderr.strip().endswith("KeyboardInterrupt")


def test_no_cache_writes_no_cache_folder(tmp_path):
    """``jaxfalsify --no-cache ...`` leaves the per-user cache folder uncreated."""
    env = {**os.environ, "JAXFALSIFY_CACHE_DIR": str(tmp_path / "cache")}
    r = subprocess.run([sys.executable, "-m", "jaxfalsify", "--no-cache", "simulate",
                        "ego_offset=5"], env=env, capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert '"collision"' in r.stdout and not (tmp_path / "cache").exists()


@pytest.mark.parametrize("argv", [
    ["run", "--strategy", "random", "--evaluations", "20", "--batch", "10", "--out", "cb",
     "--no-figures"],
    ["sweep", "--out", "cb"],
    ["compare", "--seeds", "1", "--evaluations", "20", "--strategies", "random", "--out", "cb"]])
def test_a_sut_raising_at_run_time_is_one_line_and_leaves_nothing(argv, world, capsys,
                                                                   monkeypatch):
    """A user's SUT that raises inside the compiled rollout (a host callback): one line naming
    the SUT and its exception, exit 2, and the output folder this command created is gone; in
    a folder that existed, only the user's own files are left."""
    monkeypatch.chdir(world)
    assert main([*argv, "--sut", "callback_raises.py:act", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("jaxfalsify: error: the SUT callback_raises.py:act raised at run time (in a "
                   "host callback): RuntimeError: sensor driver crashed"), err
    assert not (world / "cb").exists()
    (world / "cb").mkdir()
    (world / "cb" / "notes.txt").write_text("mine")
    assert main([*argv, "--sut", "callback_raises.py:act", "--quiet"]) == 2
    assert "sensor driver crashed" in capsys.readouterr().err
    assert [p.name for p in (world / "cb").iterdir()] == ["notes.txt"]
    shutil.rmtree(world / "cb")


def _files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".lock"}


@pytest.mark.parametrize("argv", [
    ["run", "--strategy", "random", "--evaluations", "20", "--batch", "10", "--out", "fk",
     "--no-figures"],
    ["sweep", "--out", "fk"],
    ["compare", "--seeds", "1", "--evaluations", "20", "--strategies", "random", "--out", "fk"],
    ["estimate", "--method", "mc", "--samples", "512", "--batch", "256", "--out", "fk"]])
def test_force_then_a_sut_raising_keeps_the_earlier_results(argv, world, capsys, monkeypatch):
    """``--force`` over complete results, then the user's SUT raises at run time: one line,
    exit 2, and every earlier file as it was, byte for byte (run, sweep and estimate set them
    aside and put them back; a comparison writes nothing before its end), nothing else left;
    ``--force`` with a working SUT then replaces them and leaves no set-aside copy."""
    monkeypatch.chdir(world)
    assert main([*argv, "--quiet"]) == 0
    before = _files(world / "fk")
    assert "config.toml" in before and len(before) >= 3
    capsys.readouterr()
    assert main([*argv, "--force", "--sut", "callback_raises.py:act", "--quiet"]) == 2
    assert "sensor driver crashed" in capsys.readouterr().err
    assert _files(world / "fk") == before
    assert not (world / "fk" / ".earlier").exists()
    assert main([*argv, "--force", "--seed", "1", "--quiet"] if argv[0] != "compare" else
                [*argv, "--force", "--quiet"]) == 0
    after = _files(world / "fk")
    assert sorted(after) == sorted(before) and not (world / "fk" / ".earlier").exists()
    changed = "compare.json" if argv[0] == "compare" else "config.toml"  # seed 1, or timings
    assert after[changed] != before[changed]
    shutil.rmtree(world / "fk")


@pytest.mark.parametrize("argv", [
    ["run", "--strategy", "random", "--evaluations", "20", "--batch", "10", "--out", "rq",
     "--no-figures"],
    ["estimate", "--method", "mc", "--samples", "512", "--batch", "256", "--out", "rq"]])
@pytest.mark.parametrize("user_sut", [False, True])
def test_a_requirement_raising_at_run_time_is_named_not_the_sut(argv, user_sut, world, capsys,
                                                                 monkeypatch):
    """A user's requirement that raises inside the compiled program (a host callback): the
    one line names the requirement by its import path (also beside a user SUT, which the
    traceback tells apart), exit 2, and the folder this command created is gone."""
    monkeypatch.chdir(world)
    extra = []
    if user_sut:  # a user SUT of its own file, which does not raise
        (world / "quiet_sut.py").write_text(
            "def act(obs, state, params, key):\n    return 0.0, state\n")
        extra = ["--sut", "quiet_sut.py:act"]
    assert main([*argv, *extra, "--requirement", "req_callback_raises.py:req", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("jaxfalsify: error: the requirement req_callback_raises.py:req raised at run "
                   "time (in a host callback): ValueError: logger offline"), err
    assert not (world / "rq").exists()


def test_a_folder_of_another_kind_is_named_with_its_article(world, capsys, monkeypatch):
    """An estimate's folder given to run and sweep: one line naming what it holds, with the
    right article ("an estimate", "a run"), exit 2, the estimate untouched."""
    monkeypatch.chdir(world)
    assert main(["estimate", "--method", "mc", "--samples", "512", "--batch", "256",
                 "--out", "est_kind", "--quiet"]) == 0
    capsys.readouterr()
    before = (world / "est_kind" / "summary.json").read_bytes()
    for cmd, kind in (("run", "a run"), ("sweep", "a sweep")):
        assert main([cmd, "--out", "est_kind", "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (f"jaxfalsify: error: --out est_kind holds an estimate; {kind} is never "
                       "written into it (choose another folder)"), err
    assert (world / "est_kind" / "summary.json").read_bytes() == before
