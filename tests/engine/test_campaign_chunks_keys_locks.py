"""The campaign loop, its cache keys, fingerprints, progress and folder lock: each test
compares against an independent oracle (another chunking, the summary, the lock holder's own
pid, a fresh process)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from jaxfalsify.engine import campaign
from jaxfalsify.io import store
from jaxfalsify.io.files import write_atomic
from jaxfalsify.jobs import runs


def test_a_second_writer_is_told_the_holders_pid_not_to_resume(tmp_path):
    """A folder being written looks unfinished (status.json says running); the second writer
    must be told who writes it, whatever check it reaches first."""
    out = tmp_path / "run"
    holder = store.open_folder(out, "run")  # this process holds the lock, as a run would
    try:
        write_atomic(out / "config.toml", "kind = \"run\"\n")
        store.write_status(out, "run", "running", evaluations=10)
        with pytest.raises(store.FolderError) as e:
            store.open_folder(out, "run")
        assert f"being written by process {os.getpid()}" in str(e.value)
    finally:
        holder.release()
    with pytest.raises(store.FolderError) as e:  # once released: the folder is unfinished
        store.open_folder(out, "run")
    assert "unfinished" in str(e.value)


class _Recorder(runs.Progress):
    def __init__(self):
        self.last = None

    def update(self, done, **stats):
        self.last = (done, stats)


@pytest.mark.parametrize("evaluations", [1, 53])
def test_the_progress_bar_counts_what_the_summary_counts(tmp_path, evaluations):
    """The last batch's overflow (past the budget) is discarded: the bar's collisions and best
    reward are the summary's."""
    bar = _Recorder()
    o = runs.execute(runs.RunConfig(strategy="random", evaluations=evaluations, batch=25,
                                    checkpoint_every=1), tmp_path / "run", progress=bar,
                     figures=False)
    done, stats = bar.last
    assert done == evaluations == o.summary["evaluations"]
    assert stats["collisions"] == o.summary["n_collisions"]
    assert stats["best"] == f"{o.summary['best']['reward']:.4f}"


# ----------------------------------------------------------------------------- JAX settings
_RUN = """
import json, sys
from jaxfalsify.jobs import runs
o = runs.execute(runs.RunConfig(strategy="random", evaluations=40, batch=8, seed=4),
                 sys.argv[1], figures=False)
print(json.dumps(o.result.indices.tolist()))
"""


def _run_in(tmp_path, name, cache_dir, **env):
    e = {**os.environ, "JAXFALSIFY_CACHE_DIR": str(cache_dir), **env}
    p = subprocess.run([sys.executable, "-c", _RUN, str(tmp_path / name)], env=e,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout.strip().splitlines()[-1]


@pytest.mark.slow
def test_a_warm_cache_does_not_change_results_under_other_jax_settings(tmp_path):
    """JAX_THREEFRY_PARTITIONABLE=0 draws other random numbers: with a cache warmed under the
    default setting, a run gives what it gives with no cache at all (never the cached
    program of the other setting)."""
    cache_dir = tmp_path / "cache"
    default = _run_in(tmp_path, "a", cache_dir)
    warm = _run_in(tmp_path, "b", cache_dir, JAX_THREEFRY_PARTITIONABLE="0")
    cold = _run_in(tmp_path, "c", tmp_path / "other-cache", JAXFALSIFY_NO_CACHE="1",
                   JAX_THREEFRY_PARTITIONABLE="0")
    assert warm == cold
    assert default != cold  # (the setting does change the draws: the test can tell)


def test_64_bit_mode_is_refused_in_one_line(tmp_path):
    env = {**os.environ, "JAX_ENABLE_X64": "1",
           "JAXFALSIFY_CACHE_DIR": str(tmp_path / "cache")}
    p = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--strategy", "random",
                        "--evaluations", "5", "--out", str(tmp_path / "run")], env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 2
    assert p.stderr.strip().count("\n") == 0 and "JAX_ENABLE_X64" in p.stderr
    assert not (tmp_path / "run").exists()
    p = subprocess.run([sys.executable, "-c", _RUN, str(tmp_path / "lib")], env=env,
                       capture_output=True, text=True, timeout=600)
    assert p.returncode != 0 and "ValueError: jaxfalsify runs in float32" in p.stderr
    assert not (tmp_path / "lib").exists()


def _interrupted_run(out):
    rc = runs.RunConfig(strategy="random", evaluations=64, batch=16, checkpoint_every=1,
                        seed=2)
    calls = iter(range(100))
    with pytest.raises(runs.Interrupted):
        runs.execute(rc, out, stop=lambda: next(calls) == 2, figures=False)


@pytest.mark.parametrize("env, named", [
    ({"JAX_THREEFRY_PARTITIONABLE": "0"}, "jax_threefry_partitionable"),
    ({"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"},
     "local_devices")])
def test_a_resume_under_other_settings_or_devices_is_refused(tmp_path, env, named):
    import jax

    if "XLA_FLAGS" in env and jax.default_backend() != "cpu":
        pytest.skip("forced host devices are CPUs")
    out = tmp_path / "run"
    _interrupted_run(out)
    p = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--resume", str(out),
                        "--quiet"], env={**os.environ, **env}, capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 2, p.stderr[-2000:]
    assert p.stderr.strip().count("\n") == 0 and named in p.stderr
    # and under this process's own settings it resumes
    runs.execute(runs.resume_config(out), out, resume=True, figures=False)


# ----------------------------------------------------------------------------- chunking
@pytest.mark.parametrize("n_updates", [1, 2, 61, 1009, 10007, 125, 1000])
@pytest.mark.parametrize("every", [None, 1, 7, 100])
def test_the_chunks_run_every_update_once_the_first_alone(n_updates, every):
    """The plan's chunks, listed update by update, against the updates the budget needs: each
    update in exactly one chunk, in order; the first chunk one update, the others the length
    asked (about 20 chunks when not asked), the last the rest; evaluations committed after
    each chunk counted by hand."""
    p = campaign.plan(n_updates * 32 - 5, 32, every=every)
    assert p.n_updates == n_updates
    want = min(every, n_updates) if every else max(1, n_updates // 20)
    ran = [u for c in range(p.n_chunks) for u in range(p.start(c), p.start(c) + p.updates_in(c))]
    assert ran == list(range(n_updates))
    lengths = [p.updates_in(c) for c in range(p.n_chunks)]
    assert lengths[0] == 1 and all(n == want for n in lengths[1:-1])
    assert 1 <= lengths[-1] <= want and p.updates_per_chunk == want
    done = [min(sum(lengths[:c]) * 32, n_updates * 32 - 5) for c in range(p.n_chunks + 1)]
    assert [p.done_after(c) for c in range(p.n_chunks + 1)] == done


@pytest.mark.parametrize("strategy", [  # the default's two campaign programs: ~45 s
    "random", pytest.param("reinforce/default", marks=pytest.mark.slow)])
def test_a_partial_last_chunk_changes_no_result_and_resumes(tmp_path, strategy):
    """62 updates in chunks of 3 after the first (the last chunk shorter) give the files of
    the same run checkpointed every update (62 chunks); stopped after 5 chunks and resumed,
    the same again."""
    kw = dict(strategy=strategy, evaluations=62 * 8 - 3, batch=8, seed=3)
    p = runs.RunConfig(**kw).build().plan
    assert p.updates_in(p.n_chunks - 1) < p.updates_per_chunk > 1
    runs.execute(runs.RunConfig(**kw), tmp_path / "chunked", figures=False)
    runs.execute(runs.RunConfig(**kw, checkpoint_every=1), tmp_path / "every", figures=False)
    calls = iter(range(1000))
    with pytest.raises(runs.Interrupted):
        runs.execute(runs.RunConfig(**kw), tmp_path / "resumed", figures=False,
                     stop=lambda: next(calls) == 5)
    runs.execute(runs.resume_config(tmp_path / "resumed"), tmp_path / "resumed", resume=True,
                 figures=False)
    import pyarrow.parquet as pq

    ref = pq.read_table(tmp_path / "every" / "evaluations.parquet")
    for name in ("chunked", "resumed"):
        assert pq.read_table(tmp_path / name / "evaluations.parquet").equals(ref), name
        for f in ("summary.json", "critical.csv"):
            assert (tmp_path / name / f).read_bytes() == (tmp_path / "every" / f).read_bytes()


@pytest.mark.slow
def test_jax_compilation_cache_dir_is_respected_and_the_off_switch_writes_nothing(tmp_path):
    """JAX's own JAX_COMPILATION_CACHE_DIR takes the executables (the per-user folder keeps
    only jaxfalsify's exported programs); without it they go under the per-user folder's
    jax/; with JAXFALSIFY_NO_CACHE=1 neither folder is created."""
    def simulate(given):
        env = {k: v for k, v in os.environ.items()
               if k not in ("JAX_COMPILATION_CACHE_DIR", "JAXFALSIFY_NO_CACHE")}
        env.update({k: v for k, v in given.items() if v is not None})
        r = subprocess.run([sys.executable, "-m", "jaxfalsify", "simulate", "ego_offset=9"],
                           env=env, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]

    def files(folder):
        return [p for p in Path(folder).rglob("*") if p.is_file()] if Path(folder).exists() \
            else []

    own, jaxs = tmp_path / "own", tmp_path / "jaxcc"
    simulate({"JAXFALSIFY_CACHE_DIR": str(own), "JAX_COMPILATION_CACHE_DIR": str(jaxs),
              "JAXFALSIFY_NO_CACHE": None})
    assert files(jaxs) and not files(own / "jax")
    simulate({"JAXFALSIFY_CACHE_DIR": str(tmp_path / "own2"), "JAX_COMPILATION_CACHE_DIR": None,
              "JAXFALSIFY_NO_CACHE": None})
    assert files(tmp_path / "own2" / "jax")
    simulate({"JAXFALSIFY_CACHE_DIR": str(tmp_path / "off"), "JAX_COMPILATION_CACHE_DIR": None,
              "JAXFALSIFY_NO_CACHE": "1"})
    assert not (tmp_path / "off").exists()
