"""Two processes on 127.0.0.1 (jax.distributed, gloo CPU collectives): the union of their
sweep parts is exactly the single-process sweep."""

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import jaxfalsify as jf
from jaxfalsify.engine.truth import sweep_arrays

# the processes run on CPUs (gloo collectives); a bit-for-bit comparison with this process
# needs it on the same backend (float32 last bits differ between a GPU and the CPU)
ON_CPU = pytest.mark.skipif(jax.default_backend() != "cpu",
                            reason="compares CPU processes with this process's backend")

SPACE = """
[parameters.ego_offset]
values = [5, 7, 9]
[parameters.ped_speed]
values = [1.0, 1.237, 1.5, 1.808, 2.0]
[parameters.ped_offset]
values = [3.5, 4.0, 4.5]
[parameters.weather]
values = [0, 8]
"""


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_all(procs) -> None:
    """Wait for both processes; on a failure show each one's stderr (the cause is often in
    the other process)."""
    errs = [p.communicate(timeout=300)[1] for p in procs]
    for i, p in enumerate(procs):
        assert p.returncode == 0, f"process {i}: {errs[i][-1500:]}\nother: {errs[1 - i][-1500:]}"


def _two_process_sweep(tmp_path, *extra) -> Path:
    """``jaxfalsify sweep`` of SPACE on 2 processes (CPU, gloo); returns its folder."""
    space = tmp_path / "space.toml"
    space.write_text(SPACE)
    out = tmp_path / "dist"
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen(
        [sys.executable, "-m", "jaxfalsify.cli", "sweep", "--space", str(space), "--out",
         str(out), "--quiet", *extra, "--distributed", "--coordinator",
         f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    _wait_all(procs)
    return out


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
@ON_CPU
def test_two_process_sweep_union_equals_single_process(tmp_path):
    out = _two_process_sweep(tmp_path, "--chunk", "16")
    parts = sorted(out.glob("sweep.part-*-of-00002.parquet"))
    assert len(parts) == 2
    union = pa.concat_tables([pq.read_table(p) for p in parts]).to_pydict()
    sp = jf.load_space(tmp_path / "space.toml")
    single = sweep_arrays(sp)
    assert union["scenario"] == list(range(sp.size))  # no gaps, no duplicates, in order
    for k, v in single.items():
        np.testing.assert_array_equal(np.asarray(union[k]), v, err_msg=k)
    s = json.loads((out / "summary.json").read_text())
    assert s["processes"] == 2 and s["n_scenarios"] == sp.size
    assert s["n_collisions"] == int(single["collision"].sum())
    r = np.where(np.isnan(single["reward"]), -np.inf, single["reward"])
    assert s["global_max_scenario"]["scenario"] == int(np.argmax(r))


@pytest.mark.slow
@ON_CPU
def test_two_process_summary_only_sweep_equals_single_process(tmp_path):
    """``--rows none`` on 2 processes: each reduces its share on the device (process 0's
    share ends inside its compiled chunk); the merged summary equals one process's sweep that
    keeps every row. No ``--chunk``: choosing the default must wait for the distributed
    start-up (which must come before JAX's backend starts)."""
    from jaxfalsify.cli import main

    out = _two_process_sweep(tmp_path, "--rows", "none")
    assert not list(out.glob("*.parquet"))
    single = tmp_path / "single"
    assert main(["sweep", "--space", str(tmp_path / "space.toml"), "--out", str(single),
                 "--quiet"]) == 0
    a, b = (json.loads((d / "summary.json").read_text()) for d in (out, single))
    assert (a.pop("processes"), b.pop("processes")) == (2, 1)
    assert (a.pop("rows"), b.pop("rows")) == ("none", "all")
    assert (a.pop("parts"), b.pop("parts")) == ([], ["sweep.parquet"])
    assert a["n_collisions"] > 0 and a == b


def test_distributed_flags_need_their_values(capsys):
    from jaxfalsify.cli import main

    assert main(["sweep", "--distributed", "--num-processes", "2", "--process-id", "0",
                 "--out", "/tmp/never"]) == 2
    assert "--coordinator" in capsys.readouterr().err
    assert main(["sweep", "--process-id", "1"]) == 2
    assert "need --distributed" in capsys.readouterr().err


@pytest.mark.slow
@ON_CPU
def test_two_process_compare_equals_single_process(tmp_path):
    from jaxfalsify.cli import main

    space = tmp_path / "space.toml"
    space.write_text(SPACE)
    common = ["compare", "--strategies", "cem", "--seeds", "3", "--evaluations", "40",
              "--space", str(space), "--quiet"]
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen(
        [sys.executable, "-m", "jaxfalsify.cli", *common, "--out", str(tmp_path / "multi"),
         "--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
         "--process-id", str(i)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True) for i in range(2)]
    # the single-process comparison runs here meanwhile
    assert main(common + ["--out", str(tmp_path / "single")]) == 0
    _wait_all(procs)
    single = json.loads((tmp_path / "single" / "compare.json").read_text())
    multi = json.loads((tmp_path / "multi" / "compare.json").read_text())
    assert multi["processes"] == 2
    from jaxfalsify.jobs.compare_stats import without_times

    for a, b in zip(single["rows"], multi["rows"]):
        a, b = without_times(a), without_times(b)  # measured seconds differ between runs
        assert a == b and len(a["per_seed"]) == 3


@pytest.mark.slow
@ON_CPU
def test_two_process_sweep_killed_and_resumed_equals_single_process(tmp_path):
    """Both processes SIGKILLed mid-way, then resumed (each from its own checkpoint): the union
    of the parts is still exactly the single-process sweep."""
    import signal
    import time

    out = tmp_path / "dist"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)

    def start(extra):
        port = _free_port()
        return [subprocess.Popen(
            [sys.executable, "-m", "jaxfalsify.cli", "sweep", *extra, "--quiet",
             "--distributed", "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
             "--process-id", str(i)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True) for i in range(2)]

    procs = start(["--space", "paper", "--out", str(out), "--chunk", "1024"])  # 49 chunks each
    states = [out / f"checkpoint-part-{i:05d}-of-00002" / "state.json" for i in range(2)]

    def chunks_done(state):
        try:
            return json.loads(state.read_text())["chunks_done"]
        except (FileNotFoundError, json.JSONDecodeError):
            return 0

    deadline = time.monotonic() + 300
    while min(chunks_done(s) for s in states) < 2:
        assert time.monotonic() < deadline and all(p.poll() is None for p in procs)
        time.sleep(0.02)
    for p in procs:
        p.send_signal(signal.SIGKILL)
        p.communicate()
    assert not (out / "summary.json").exists()
    _wait_all(start(["--resume", str(out)]))
    parts = sorted(out.glob("sweep.part-*-of-00002.parquet"))
    union = pa.concat_tables([pq.read_table(p) for p in parts]).to_pydict()
    single = sweep_arrays(jf.load_space("paper"))
    assert union["scenario"] == list(range(100_000))
    for k, v in single.items():
        np.testing.assert_array_equal(np.asarray(union[k]), v, err_msg=k)
    assert json.loads((out / "timing.json").read_text())["resumed_from_scenario"] > 0


def test_an_unreachable_coordinator_fails_in_time_with_one_line():
    """Process 1 of 2 pointed at a port nobody listens on: a one-line error after the
    initialisation timeout, not a hang."""
    code = ("from jaxfalsify.base.distributed import initialize\n"
            "try:\n    initialize('127.0.0.1:%d', 2, 1, timeout=3)\n"
            "except ValueError as e:\n    print('ERR', e)\n" % _free_port())
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=120)
    out = r.stdout.strip().splitlines()
    assert out and out[-1].startswith("ERR --coordinator 127.0.0.1:"), (r.stdout, r.stderr[-500:])
    assert "not reachable within 3 s" in out[-1]


@pytest.mark.parametrize("command", ["sweep", "compare"])
def test_the_cli_waits_for_an_unreachable_coordinator_as_long_as_it_is_told(tmp_path, command):
    """``--coordinator-timeout 2``: a line saying what it waits for, then one error line
    naming the coordinator, exit 2, and no output folder."""
    port = _free_port()
    out = tmp_path / "out"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-m", "jaxfalsify", command, "--distributed",
                        "--coordinator", f"127.0.0.1:{port}", "--num-processes", "2",
                        "--process-id", "1", "--coordinator-timeout", "2", "--out", str(out)],
                       capture_output=True, text=True, env=env, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 2, r.stderr[-800:]
    assert lines[0].startswith(f"jaxfalsify: waiting up to 2 s for the coordinator "
                               f"127.0.0.1:{port}")
    assert lines[1].startswith(f"jaxfalsify: error: --coordinator 127.0.0.1:{port}: not "
                               "reachable within 2 s")
    assert not out.exists()


def _two_processes(tmp_path, args_of) -> list:
    """Start 2 ``jaxfalsify`` processes (CPU, gloo) with ``args_of(i)``; returns
    ``[(returncode, stderr)]``."""
    port = _free_port()
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    procs = [subprocess.Popen(
        [sys.executable, "-m", "jaxfalsify.cli", *args_of(i), "--distributed", "--coordinator",
         f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    return [(p.returncode, err) for p in procs for err in [p.communicate(timeout=300)[1]]]


@pytest.mark.slow
@ON_CPU
def test_processes_started_with_other_flags_stop_before_any_work(tmp_path):
    """Another --space-seed on one process (sweep) or another --seeds (compare): every process
    exits 2 with one line naming the mismatch, and no folder is written."""
    space = tmp_path / "space.toml"
    space.write_text(SPACE.replace("values = [1.0, 1.237, 1.5, 1.808, 2.0]",
                                   "distribution = 'uniform'\nlow = 1.0\nhigh = 2.0\n"
                                   "samples = 5"))
    sweep = lambda i: ["sweep", "--space", str(space), "--out", str(tmp_path / "s"),  # noqa
                       "--quiet", "--space-seed", str(i)]
    compare = lambda i: ["compare", "--space", str(space), "--out", str(tmp_path / "c"),  # noqa
                         "--strategies", "random", "--evaluations", "16", "--quiet",
                         "--seeds", str(2 + 2 * i)]
    for args_of, folder in ((sweep, "s"), (compare, "c")):
        for code, err in _two_processes(tmp_path, args_of):
            lines = err.strip().splitlines()
            assert code == 2 and len(lines) == 1, err[-1500:]
            assert "was started with another" in lines[0] and "configuration" in lines[0]
        assert not (tmp_path / folder).exists()


@pytest.mark.slow
@ON_CPU
def test_a_process_without_scenarios_writes_no_part(tmp_path):
    """More processes than scenarios: the empty share writes no Parquet part and summary.json
    lists only the parts that exist, each readable, together the single-process sweep."""
    space = tmp_path / "one.toml"
    space.write_text("[parameters.ped_speed]\nvalues = [1.237]\n")
    out = tmp_path / "one"
    for code, err in _two_processes(tmp_path, lambda i: ["sweep", "--space", str(space),
                                                         "--out", str(out), "--quiet"]):
        assert code == 0, err[-1500:]
    parts = json.loads((out / "summary.json").read_text())["parts"]
    assert parts == ["sweep.part-00001-of-00002.parquet"]
    assert sorted(p.name for p in out.glob("sweep.part-*")) == parts
    rows = pq.read_table(out / parts[0]).to_pydict()
    alone = sweep_arrays(jf.load_space(str(space)))
    assert rows["scenario"] == [0] and rows["reward"] == [float(alone["reward"][0])]


@pytest.mark.parametrize("var", ["JAX_NUM_PROCESSES", "JAX_PROCESS_ID"])
def test_a_non_integer_process_variable_is_named(monkeypatch, var):
    from jaxfalsify.base.distributed import initialize

    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "127.0.0.1:1234")
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    monkeypatch.setenv("JAX_PROCESS_ID", "0")
    monkeypatch.setenv(var, "abc")
    with pytest.raises(ValueError) as e:
        initialize()
    assert var in str(e.value) and "\n" not in str(e.value)


def test_checking_a_comparison_leaves_the_backend_to_jax_distributed():
    """A comparison is checked before ``jax.distributed.initialize`` (so a bad flag stops a
    process before the others wait for it), and JAX refuses to initialise after its backend
    started: checking every built-in strategy's configuration must not start it (with JAX
    limited to CPUs, as a test's processes are)."""
    code = ("from jax._src import xla_bridge as xb\n"
            "from jaxfalsify import search\n"
            "from jaxfalsify.jobs.compare import CompareConfig\n"
            "CompareConfig(strategies=tuple(search.REGISTRY), evaluations=64, seeds=2).check()\n"
            "print('started' if xb._backends else 'not started')\n")
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.stdout.strip().splitlines()[-1:] == ["not started"], (r.stdout, r.stderr[-800:])
