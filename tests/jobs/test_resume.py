"""Resume: an interrupted campaign or sweep, continued from its checkpoint, ends with exactly
the files an uninterrupted one writes. The oracle is the uninterrupted run with the same config
and seed; interruptions are real (SIGKILL and SIGINT sent to a subprocess, or an exception
raised between chunks in-process)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import TINY_SPACE, run_campaign  # noqa: F401

import jaxfalsify as jf
from jaxfalsify import search
from jaxfalsify.cli import main
from jaxfalsify.engine import campaign
from jaxfalsify.io.checkpoints import CampaignCheckpoint
from jaxfalsify.jobs import runs

FAST_RESUME = ("random",)  # the rest in the slow pass (test_trust resumes reinforce/default)


@pytest.mark.parametrize("strategy", [
    s if s in FAST_RESUME else pytest.param(s, marks=pytest.mark.slow) for s in search.REGISTRY])
def test_every_strategy_resumes_bit_identically(strategy, tmp_path):
    """Stop after 2 of 5 chunks, restore the carry (strategy + optimiser state, PRNG keys,
    update count, the batch not yet told) from disk, continue: every recorded field equals the
    uninterrupted run's."""
    rc = runs.RunConfig(strategy=strategy, evaluations=16 * 8 - 5, batch=16,
                        checkpoint_every=2, seed=5)  # 8 updates (chunks 1, 2, 2, 2, 1), a
    # partial last batch
    b = rc.build()
    ref = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan, 5)
    ck = CampaignCheckpoint(tmp_path / "checkpoint", {"test": strategy})
    chunks = iter(range(100))
    with pytest.raises(campaign.Stopped):
        campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan, 5,
                     checkpoint=ck, stop=lambda: next(chunks) == 2)
    assert json.loads((ck.folder / "state.json").read_text())["chunks_done"] == 2
    resumed = runs.restore(ck, b, 5)
    assert len(resumed[1]) == 2
    res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan, 5,
                       checkpoint=ck, resumed=resumed)
    np.testing.assert_array_equal(res.indices, ref.indices)
    for f in campaign.RECORD_FIELDS:
        np.testing.assert_array_equal(res.fields[f], ref.fields[f], err_msg=f)


@pytest.mark.parametrize("strategy", ["random", pytest.param("reinforce", marks=pytest.mark.slow)])
def test_results_do_not_depend_on_chunking(strategy):
    """Checkpointing every update or every 5 updates runs the same update function."""
    sp = jf.load_space("paper")
    a = run_campaign(sp, strategy, batch=20, evaluations=200, seed=2, every=1)
    b = run_campaign(sp, strategy, batch=20, evaluations=200, seed=2, every=5)
    np.testing.assert_array_equal(a.indices, b.indices)
    for f in campaign.RECORD_FIELDS:
        np.testing.assert_array_equal(a.fields[f], b.fields[f], err_msg=f)


def _wait_for_chunks(proc, state: Path, n: int, what: str):
    """Block until ``state`` (a checkpoint's state.json) says ``n`` chunks are committed."""
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"{what} ended before it could be interrupted"
        try:
            if json.loads(state.read_text())["chunks_done"] >= n:
                return
        except (FileNotFoundError, json.JSONDecodeError):
            pass
        time.sleep(0.02)
    proc.kill()
    raise AssertionError(f"{what} wrote no checkpoint within 300 s")


def _cli(args, **kw):
    """``jaxfalsify ARGS`` in a subprocess (sharing the test session's per-user cache) on this
    process's backend: its files are compared bit for bit with in-process runs, and float32
    results differ in the last bits between backends (a GPU and the CPU did, on an H100)."""
    env = dict(os.environ)
    return subprocess.Popen([sys.executable, "-m", "jaxfalsify.cli", *args], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)


def _interrupt(args, out: Path, chunks: int, sig) -> tuple[int, str]:
    """Start ``jaxfalsify ARGS --out OUT`` in a subprocess, send ``sig`` once its checkpoint
    holds ``chunks`` chunks; returns (exit code, stderr)."""
    proc = _cli([*args, "--out", str(out)])
    _wait_for_chunks(proc, out / "checkpoint" / "state.json", chunks, " ".join(args[:1]))
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err


RUN_ARGS = ["run", "--evaluations", "1200", "--batch", "20", "--checkpoint-every", "1",
            "--seed", "7", "--no-figures", "--quiet"]


def _same_table(a: Path, b: Path):
    """Same columns, same values bit for bit (NaN where the other has NaN)."""
    ta, tb = pq.read_table(a), pq.read_table(b)
    assert ta.schema.equals(tb.schema) and ta.num_rows == tb.num_rows
    for name in ta.column_names:
        np.testing.assert_array_equal(ta.column(name).to_numpy(), tb.column(name).to_numpy(),
                                      err_msg=name)


def _same_run(a: Path, b: Path):
    assert (a / "summary.json").read_bytes() == (b / "summary.json").read_bytes()
    tb = pq.read_table(b / "evaluations.parquet")
    assert tb.column("evaluation").to_pylist() == list(range(1, 1201))  # no gaps, no duplicates
    _same_table(a / "evaluations.parquet", b / "evaluations.parquet")
    assert (a / "critical.csv").read_text() == (b / "critical.csv").read_text()
    assert (a / "config.toml").read_text() == (b / "config.toml").read_text()


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_sigkilled_run_resumes_to_identical_results(tmp_path, capsys):
    reference, out = tmp_path / "reference", tmp_path / "killed"
    uninterrupted = _cli([*RUN_ARGS, "--out", str(reference)])  # side by side
    rc, _ = _interrupt(RUN_ARGS, out, 3, signal.SIGKILL)
    assert rc == -signal.SIGKILL
    assert not (out / "summary.json").exists() and not (out / "evaluations.parquet").exists()
    # the unfinished folder is neither reused nor silently overwritten
    assert main([*RUN_ARGS, "--out", str(out)]) == 2
    assert f"--resume {out}" in capsys.readouterr().err
    resume = _cli(["run", "--resume", str(out), "--quiet", "--no-figures"])
    for p in (uninterrupted, resume):
        _, err = p.communicate(timeout=600)
        assert p.returncode == 0, err[-2000:]
    _same_run(reference, out)
    assert json.loads((out / "timing.json").read_text())["resumed_from_evaluation"] >= 60
    assert json.loads((out / "status.json").read_text())["state"] == "complete"
    assert not (out / "checkpoint").exists()
    assert main(["run", "--resume", str(out)]) == 2  # complete: nothing to resume
    assert "already complete" in capsys.readouterr().err


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_sigint_or_sigterm_leaves_a_resumable_run(tmp_path, sig, code):
    # 600 chunks of 2 (about 2.5 ms each): the signal lands long before the end even when
    # this process is slow to see the second checkpoint on a loaded machine
    args = [a if a != "20" else "2" for a in RUN_ARGS] + ["--strategy", "random"]
    assert args[args.index("--batch") + 1] == "2"
    reference = tmp_path / "reference"
    assert main([*args, "--out", str(reference)]) == 0
    out = tmp_path / "interrupted"
    rc, err = _interrupt(args, out, 2, sig)
    assert rc == code
    assert err.strip().splitlines()[-1].endswith(f"resumable: jaxfalsify run --resume {out}")
    status = json.loads((out / "status.json").read_text())
    saved = json.loads((out / "checkpoint" / "state.json").read_text())
    assert status["state"] == "interrupted"
    assert status["evaluations_done"] == saved["evaluations_done"] < 1200
    assert not (out / "summary.json").exists()
    assert main(["run", "--resume", str(out), "--quiet", "--no-figures"]) == 0
    _same_run(reference, out)


SWEEP_ARGS = ["sweep", "--space", "paper", "--chunk", "1024", "--quiet"]


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_sigkilled_sweep_resumes_to_identical_results(tmp_path, capsys):
    ref = tmp_path / "reference"
    assert main([*SWEEP_ARGS, "--out", str(ref)]) == 0
    out = tmp_path / "killed"
    assert _interrupt(SWEEP_ARGS, out, 3, signal.SIGKILL)[0] == -signal.SIGKILL
    assert not (out / "summary.json").exists() and not (out / "sweep.parquet").exists()
    assert main([*SWEEP_ARGS, "--out", str(out)]) == 2
    assert f"--resume {out}" in capsys.readouterr().err
    assert main(["sweep", "--resume", str(out), "--quiet"]) == 0
    assert (ref / "summary.json").read_bytes() == (out / "summary.json").read_bytes()
    b = pq.read_table(out / "sweep.parquet")
    assert b.column("scenario").to_pylist() == list(range(100_000))
    _same_table(ref / "sweep.parquet", out / "sweep.parquet")
    assert json.loads((out / "timing.json").read_text())["resumed_from_scenario"] > 0
    assert sorted(os.listdir(out)) == [".lock", "config.toml", "status.json", "summary.json",
                                       "sweep.parquet", "timing.json"]
    assert json.loads((out / "status.json").read_text())["state"] == "complete"


def test_sweep_summary_does_not_depend_on_chunk_size(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert main(["sweep", "--space", "paper", "--chunk", "4096", "--quiet", "--out", str(a)]) == 0
    assert main(["sweep", "--space", "paper", "--quiet", "--out", str(b)]) == 0
    assert (a / "summary.json").read_bytes() == (b / "summary.json").read_bytes()
    _same_table(a / "sweep.parquet", b / "sweep.parquet")


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_library_run_interrupt_resume_equals_cli(tmp_path):
    """``runs.execute`` stopped between chunks and resumed gives exactly the files the CLI
    writes for the same configuration in one go."""
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    cli_out, lib = tmp_path / "cli", tmp_path / "lib"
    assert main(["run", "--space", str(space), "--strategy", "reinforce", "--evaluations",
                 "200", "--batch", "20", "--checkpoint-every", "1", "--seed", "3", "--out",
                 str(cli_out), "--quiet"]) == 0
    rc = runs.RunConfig(space=str(space), strategy="reinforce", evaluations=200, batch=20,
                        checkpoint_every=1, seed=3)
    calls = iter(range(100))
    with pytest.raises(runs.Interrupted) as e:
        runs.execute(rc, lib, stop=lambda: next(calls) == 4)
    assert e.value.done == 80 and e.value.resume == f"jaxfalsify run --resume {lib}"
    assert json.loads((lib / "status.json").read_text())["state"] == "interrupted"
    o = runs.execute(runs.resume_config(lib), lib, resume=True)
    assert o.timing["resumed_from_evaluation"] == 80
    assert (cli_out / "summary.json").read_bytes() == (lib / "summary.json").read_bytes()
    for f in ("config.toml", "critical.csv"):
        assert (cli_out / f).read_text() == (lib / f).read_text(), f
    _same_table(cli_out / "evaluations.parquet", lib / "evaluations.parquet")
    assert sorted(os.listdir(cli_out / "figures")) == sorted(os.listdir(lib / "figures"))
    strip = lambda t: [ln for ln in t.splitlines()  # noqa: E731  (paths and times differ)
                       if not any(w in ln for w in ("wall time", "jaxfalsify", "run `"))]
    assert strip((cli_out / "report.md").read_text()) == strip((lib / "report.md").read_text())


def test_a_signal_during_the_last_chunk_still_interrupts_and_resumes(tmp_path):
    """stop() turns true only after the last chunk (a SIGINT/SIGTERM that arrived while it
    ran): the run commits, says interrupted with every evaluation saved, raises Interrupted;
    --resume finishes it to the uninterrupted run's files."""
    rc = runs.RunConfig(strategy="random", evaluations=64, batch=16, checkpoint_every=1, seed=2)
    n_chunks = rc.build().plan.n_chunks
    calls = iter(range(1000))
    with pytest.raises(runs.Interrupted):
        runs.execute(rc, tmp_path / "late", stop=lambda: next(calls) >= n_chunks,
                     figures=False)
    status = json.loads((tmp_path / "late" / "status.json").read_text())
    assert status["state"] == "interrupted" and status["evaluations_done"] == 64
    runs.execute(runs.resume_config(tmp_path / "late"), tmp_path / "late", resume=True,
                 figures=False)
    runs.execute(rc, tmp_path / "ref", figures=False)
    for f in ("summary.json", "critical.csv"):
        assert (tmp_path / "late" / f).read_bytes() == (tmp_path / "ref" / f).read_bytes(), f


def test_a_run_that_inherited_an_ignored_sigint_keeps_ignoring_it(tmp_path):
    """A script's background job (``cmd &``) starts with SIGINT ignored: a SIGINT sent to it
    mid-run changes nothing, and the run completes with the same files as an undisturbed one
    (SIGTERM still stops runs: the other tests)."""
    args = [*RUN_ARGS, "--strategy", "random"]
    reference = tmp_path / "reference"
    assert main([*args, "--out", str(reference)]) == 0
    out = tmp_path / "ignoring"
    # started as a shell's background job is: SIGINT ignored, inherited across exec (no
    # preexec_fn: forking a multithreaded JAX process can deadlock)
    proc = subprocess.Popen(["bash", "-c", 'trap "" INT; exec "$0" "$@"', sys.executable, "-m",
                             "jaxfalsify.cli", *args, "--out", str(out)], env=dict(os.environ),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_chunks(proc, out / "checkpoint" / "state.json", 2, "run")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-2000:]
    _same_run(reference, out)
