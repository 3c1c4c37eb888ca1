"""Nothing lost, nothing silently wrong.

* Fuzzing (hypothesis, derandomised): malformed space and config TOML and random flag values
  through the real command line give exit 2, one line starting ``jaxfalsify: error:``, no
  traceback, and no file of the working folder changed.
* Random damage to checkpoints (bit flips, truncation, swapped, copied and foreign files,
  edited commit records, deletions): a resume is refused with one line, or it ends identical to
  the uninterrupted run — never exit 0 with other results.
* Locks: a second writer of a folder (resume, force, another kind) is refused with the
  holder's pid while the first process runs; after a kill -9 the folder is free again.
* A failed write (disk full) gives one line naming the file, and status.json says failed.
"""

import contextlib
import errno
import hashlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace as dataclasses_replace
from pathlib import Path

import jax
import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import TINY_SPACE
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.engine import sweep_config
from jaxfalsify.io.checkpoints import CampaignCheckpoint, write_commit
from jaxfalsify.io.files import atomic_path, replace_files, write_atomic
from jaxfalsify.jobs import runs, sweep

FAST = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=list(HealthCheck))
SLOW = settings(max_examples=200, deadline=None, derandomize=True,
                suppress_health_check=list(HealthCheck))


def _snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest()
                                       if p.is_file() else "dir")
            for p in sorted(root.rglob("*")) if not p.is_fifo()}


def cli(argv) -> tuple[int, str]:
    """``main(argv)`` with stderr captured (no pytest fixture: hypothesis calls it often)."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main([str(a) for a in argv])
    return code, err.getvalue()


def assert_one_line_error(code: int, err: str) -> None:
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxfalsify: error: "), err
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    w = tmp_path_factory.mktemp("fuzz")
    (w / "afile").write_text("in the way of every --out\n")
    (w / "tiny.toml").write_text(TINY_SPACE)
    return w


# ----------------------------------------------------------------------------- fuzzing
KEYS = ["name", "description", "parameters", "ego_offset", "ped_speed", "ped_accel", "weather",
        "distribution", "low", "high", "mean", "sd", "samples", "values", "decimals", "unit",
        "strategy", "sut", "seed", "evaluations", "batch", "space", "space_seed", "kind",
        "sut_params", "strategy_params", "checkpoint_every", "bogus", ""]
SCALARS = st.one_of(
    st.integers(-2**70, 2**70), st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12), st.booleans(),
    st.sampled_from(["uniform", "normal", "integers", "values", "paper", "random", "carla-tm",
                     "reinforce/paper", "m", "m/s", "../x", "a:b", "x.toml"]))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4),
    st.dictionaries(st.sampled_from(KEYS), inner, max_size=4)), max_leaves=12)
DOCS = st.dictionaries(st.sampled_from(KEYS), VALUES, max_size=6)


def toml_text(doc, prefix="") -> str:
    """A TOML writer that also writes what our configs never hold (nan, inf, odd keys)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return "nan" if v != v else ("inf" if v == float("inf") else
                                         "-inf" if v == float("-inf") else repr(v))
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{json.dumps(k)} = {value(x)}" for k, x in v.items()) + "}"
        return str(v)

    return "".join(f"{json.dumps(k)} = {value(v)}\n" for k, v in doc.items())


def _fuzz_file(workdir: Path, data: bytes, command: list[str]) -> None:
    f = workdir / "fuzzed.toml"
    f.write_bytes(data)
    before = _snapshot(workdir)
    code, err = cli(command + [f, "--out", workdir / "afile"])
    assert_one_line_error(code, err)
    assert _snapshot(workdir) == before


@FAST
@given(DOCS, st.one_of(st.none(), st.binary(max_size=64)), st.booleans())
def test_fuzzed_toml_through_the_cli(workdir, doc, raw, as_space):
    data = toml_text(doc).encode() if raw is None else raw
    if as_space:
        _fuzz_file(workdir, data, ["sweep", "--quiet", "--space"])
    else:
        _fuzz_file(workdir, data, ["run", "--quiet", "--no-figures", "--config"])


FLAG_VALUES = st.sampled_from(["", "0", "-1", "1", "3", "1e30", "nan", "inf", "abc", "../x",
                               "tiny.toml", "paper", "random", "reinforce/paper", "a=b", "=",
                               "lr=nan", "ttc_full=0.8,0.8", "x" * 300, "9" * 30, "1,2",
                               "carla-tm", "nowhere:AEB", "collisions", "\x00", "/dev/zero"])
FLAGS = {
    "run": ["--space", "--space-seed", "--sut", "--sut-param", "--strategy",
            "--strategy-param", "--evaluations", "--batch", "--seed", "--checkpoint-every",
            "--config", "--resume"],
    "sweep": ["--space", "--space-seed", "--sut", "--sut-param", "--seed", "--chunk", "--rows",
              "--resume"],
    "compare": ["--strategies", "--seeds", "--evaluations", "--space", "--space-seed", "--sut",
                "--sut-param"],
}


@FAST
@given(st.sampled_from(sorted(FLAGS)), st.data())
def test_fuzzed_flags_through_the_cli(workdir, command, data):
    flags = data.draw(st.lists(st.sampled_from(FLAGS[command]), min_size=1, max_size=4))
    argv = [command, "--quiet"]
    for f in flags:
        argv += [f, data.draw(FLAG_VALUES)]
    if "--resume" not in flags:
        argv += ["--out", "afile"]  # a valid combination must still not run or write
    cwd = os.getcwd()
    os.chdir(workdir)
    try:
        before = _snapshot(workdir)
        code, err = cli(argv)
        assert_one_line_error(code, err)
        assert _snapshot(workdir) == before
    finally:
        os.chdir(cwd)


# ----------------------------------------------------------------------------- damage
def _stopper(n):
    calls = iter(range(10_000))
    return lambda: next(calls) >= n


RUN = dict(strategy="reinforce", evaluations=200, batch=20, checkpoint_every=1)


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """An uninterrupted run and sweep (the oracles), and interrupted ones to damage, plus
    interrupted ones of another seed (foreign files of the same shapes)."""
    base = tmp_path_factory.mktemp("damage")
    space = base / "tiny.toml"
    space.write_text(TINY_SPACE)
    made = {}
    for seed, name in ((3, "run"), (4, "foreign_run")):
        rc = runs.RunConfig(space=str(space), seed=seed, **RUN)
        with pytest.raises(runs.Interrupted):
            runs.execute(rc, base / name, stop=_stopper(4), figures=False)
    runs.execute(runs.RunConfig(space=str(space), seed=3, **RUN), base / "run_ref",
                 figures=False)
    for seed, name in ((0, "sweep"), (1, "foreign_sweep")):
        with pytest.raises(runs.Interrupted):
            sweep.execute(sweep_config.SweepConfig(chunk=4096, seed=seed), base / name,
                          stop=_stopper(5))
    sweep.execute(sweep_config.SweepConfig(chunk=4096), base / "sweep_ref")
    made["base"] = base
    return made


def _files(ck: Path, pattern: str) -> list[Path]:
    return sorted(ck.glob(pattern))


def damage(folder: Path, foreign: Path, kind: str, rng: np.random.Generator) -> str:
    """Apply one random damage of ``kind`` to ``folder/checkpoint``; returns what was done."""
    ck, fck = folder / "checkpoint", foreign / "checkpoint"
    data_glob = "records-*.npz" if (ck / "carry-000004.npz").exists() else "rows-*.parquet"
    data = _files(ck, data_glob)
    every = [p for p in ck.iterdir() if p.is_file()]
    pick = lambda xs: xs[int(rng.integers(len(xs)))]  # noqa: E731
    if kind == "bitflip":
        f = pick(every)
        b = bytearray(f.read_bytes())
        i = int(rng.integers(len(b)))
        b[i] ^= 1 << int(rng.integers(8))
        f.write_bytes(bytes(b))
        return f"flip a bit of {f.name} at {i}"
    if kind == "truncate":
        f = pick(every)
        n = int(rng.integers(f.stat().st_size))
        f.write_bytes(f.read_bytes()[:n])
        return f"truncate {f.name} to {n}"
    if kind == "swap":
        a, b = rng.choice(len(data), 2, replace=False)
        x, y = data[a].read_bytes(), data[b].read_bytes()
        data[a].write_bytes(y)
        data[b].write_bytes(x)
        return f"swap {data[a].name} and {data[b].name}"
    if kind == "copy":
        a, b = rng.choice(len(data), 2, replace=False)
        shutil.copyfile(data[a], data[b])
        return f"copy {data[a].name} over {data[b].name}"
    if kind == "foreign_file":
        f = pick([p for p in every if p.name != "state.json" and (fck / p.name).exists()])
        shutil.copyfile(fck / f.name, f)
        return f"{f.name} from another seed"
    if kind == "foreign_state":
        shutil.copyfile(fck / "state.json", ck / "state.json")
        return "state.json from another seed"
    if kind == "edit_state":
        doc = json.loads((ck / "state.json").read_text())
        key = pick([k for k in ("chunks_done", "evaluations_done", "scenarios_done") if k in doc])
        doc[key] += int(rng.choice([-1, 1, -2]))
        (ck / "state.json").write_text(json.dumps(doc))
        return f"edit {key} in state.json"
    if kind == "reseal_state":  # an edit that also recomputes the seal: files must still match
        doc = json.loads((ck / "state.json").read_text())
        name = pick(sorted(doc["files"]))
        doc["files"][name]["sha256"] = "0" * 64
        write_commit(ck / "state.json", {k: v for k, v in doc.items()
                                         if k not in ("sha256", "format")})
        return f"resealed state.json with a wrong hash for {name}"
    if kind == "reseal_edit":  # a consistent forgery of the numbers, seal recomputed
        doc = json.loads((ck / "state.json").read_text())
        if "totals" in doc and rng.random() < 0.7:
            field = pick(["collisions", "nonfinite", "best_ties", "best_row"])
            if field == "best_row":  # the scenario kept, its outcome or values forged
                name = pick(["reward", "collision", "min_distance", "ped_speed"])
                row = doc["totals"][0]["best_row"]
                row[name] = (not row[name]) if isinstance(row[name], bool) else 9.9
                field = f"best_row.{name}"
            else:
                doc["totals"][0][field] += int(rng.choice([1, 7]))
            what = f"totals.{field}"
        else:
            what = pick([k for k in ("chunks_done", "evaluations_done", "scenarios_done")
                         if k in doc])
            doc[what] += int(rng.choice([-1, 1]))
        write_commit(ck / "state.json", {k: v for k, v in doc.items()
                                         if k not in ("sha256", "format")})
        return f"edited {what} in state.json and resealed it"
    if kind == "delete":
        f = pick(every)
        f.unlink()
        return f"delete {f.name}"
    raise AssertionError(kind)


KINDS = ["bitflip", "truncate", "swap", "copy", "foreign_file", "foreign_state", "edit_state",
         "reseal_state", "reseal_edit", "delete"]


def _same_parquet(a: Path, b: Path) -> bool:
    ta, tb = pq.read_table(a), pq.read_table(b)
    return ta.schema.equals(tb.schema) and all(
        np.array_equal(ta.column(c).to_numpy(), tb.column(c).to_numpy(), equal_nan=True)
        for c in ta.column_names)


def _resume_damaged(checkpoints, what: str, kind: str, seed: int) -> None:
    base = checkpoints["base"]
    tmp = Path(tempfile.mkdtemp(dir=base))
    folder = tmp / what
    shutil.copytree(base / what, folder)
    done = damage(folder, base / f"foreign_{what}", kind, np.random.default_rng(seed))
    code, err = cli([what, "--resume", folder, "--quiet"]
                    + (["--no-figures"] if what == "run" else []))
    if code == 0:  # accepted: then it must be exactly the uninterrupted result
        ref = base / f"{what}_ref"
        assert (folder / "summary.json").read_bytes() == (ref / "summary.json").read_bytes(), done
        table = "evaluations.parquet" if what == "run" else "sweep.parquet"
        assert _same_parquet(folder / table, ref / table), done
    else:
        assert_one_line_error(code, err)
        assert "checkpoint" in err or "state.json" in err, (done, err)
    shutil.rmtree(tmp)


@FAST
@given(st.sampled_from(KINDS), st.integers(0, 2**31))
def test_damaged_run_checkpoint_is_refused_or_resumes_identically(checkpoints, kind, seed):
    _resume_damaged(checkpoints, "run", kind, seed)


@settings(max_examples=15, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(st.sampled_from(KINDS), st.integers(0, 2**31))
def test_damaged_sweep_checkpoint_is_refused_or_resumes_identically(checkpoints, kind, seed):
    _resume_damaged(checkpoints, "sweep", kind, seed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_resealed_forged_totals_are_refused(checkpoints, seed):
    """A consistent forgery (numbers edited, the record's seal recomputed) of a sweep's
    running totals: the totals are recomputed from the verified rows files on resume."""
    _resume_damaged(checkpoints, "sweep", "reseal_edit", seed)


@pytest.mark.parametrize("name", ["reward", "collision", "ped_speed"])
def test_resealed_forged_best_row_is_refused(checkpoints, name):
    """The best row of a sweep's totals forged (the scenario kept, its outcome or a value
    edited) and the seal recomputed: refused, never a summary with the forged row."""
    base = checkpoints["base"]
    tmp = Path(tempfile.mkdtemp(dir=base))
    shutil.copytree(base / "sweep", tmp / "sweep")
    ck = tmp / "sweep" / "checkpoint" / "state.json"
    doc = json.loads(ck.read_text())
    row = doc["totals"][0]["best_row"]
    row[name] = (not row[name]) if isinstance(row[name], bool) else 0.9
    write_commit(ck, {k: v for k, v in doc.items() if k not in ("sha256", "format")})
    code, err = cli(["sweep", "--resume", tmp / "sweep", "--quiet"])
    assert_one_line_error(code, err)
    assert "totals disagree with its rows files" in err, err
    shutil.rmtree(tmp)


@pytest.mark.slow
@SLOW
@given(st.sampled_from(["run", "sweep"]), st.sampled_from(KINDS), st.integers(0, 2**31))
def test_damaged_checkpoints_many(checkpoints, what, kind, seed):
    _resume_damaged(checkpoints, what, kind, seed)


# ----------------------------------------------------------------------------- locks
def _wait_for(path: Path, proc, timeout=300):
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.poll() is None, proc.communicate()[1][-2000:]
        assert time.monotonic() < deadline
        time.sleep(0.02)


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_a_second_writer_is_refused_with_the_holders_pid(tmp_path):
    out = tmp_path / "sw"
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    first = subprocess.Popen([sys.executable, "-m", "jaxfalsify.cli", "sweep", "--space",
                              "paper-extended", "--chunk", "4096", "--quiet", "--out", str(out)],
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_for(out / "checkpoint" / "state.json", first)
        for argv in (["sweep", "--resume", out], ["sweep", "--out", out, "--force"],
                     ["compare", "--out", out, "--force"]):
            code, err = cli(argv)
            assert_one_line_error(code, err)
        code, err = cli(["sweep", "--resume", out])
        assert f"being written by process {first.pid}" in err
        # a second real process is refused the same way
        r = subprocess.run([sys.executable, "-m", "jaxfalsify.cli", "sweep", "--resume",
                            str(out)], env=env, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and f"process {first.pid}" in r.stderr
        assert (out / "checkpoint").exists()  # --force deleted nothing
    finally:
        first.send_signal(signal.SIGKILL)
        first.communicate()
    # kill -9 leaves no stale lock: the folder resumes
    assert json.loads((out / "status.json").read_text())["state"] == "running"
    with pytest.raises(runs.Interrupted):
        sweep.execute(sweep.resume_config(out)[0], out, resume=True, stop=_stopper(1))


# ----------------------------------------------------------------------------- full disk
def test_a_full_disk_gives_one_line_and_a_truthful_status(tmp_path, monkeypatch, capsys):
    def full(path, columns):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(runs, "write_parquet", full)
    out = tmp_path / "r"
    assert main(["run", "--strategy", "random", "--evaluations", "40", "--batch", "20",
                 "--out", str(out), "--quiet", "--no-figures"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and "evaluations.parquet" in err[0]
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "failed" and "ENOSPC" not in status["state"]
    assert not (out / "evaluations.parquet").exists() and not (out / "summary.json").exists()


def test_a_full_disk_during_the_search_marks_the_run_failed(tmp_path, monkeypatch, capsys):
    """ENOSPC while committing a checkpoint (during the search, not at the end): one line,
    exit 1, and status.json says failed, not running."""
    real = CampaignCheckpoint.save
    calls = iter(range(100))

    def full_on_second(self, *a, **kw):
        if next(calls) == 1:
            raise OSError(errno.ENOSPC, "No space left on device", str(self.folder))
        return real(self, *a, **kw)

    monkeypatch.setattr(CampaignCheckpoint, "save", full_on_second)
    out = tmp_path / "r"
    assert main(["run", "--strategy", "random", "--evaluations", "80", "--batch", "20",
                 "--checkpoint-every", "1", "--out", str(out), "--quiet",
                 "--no-figures"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0]
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "failed" and "No space left" in status["error"]


# ------------------------------------------------------------ the per-user cache, damaged
def test_a_damaged_cached_program_is_rebuilt_not_run(tmp_path, monkeypatch):
    """A bit flipped anywhere in an exported program of the per-user cache: the entry fails
    its SHA-256 and is exported again, so the program computes what the code says (a flip
    inside a constant used to run silently with the wrong constant)."""
    import jax.numpy as jnp

    from jaxfalsify.io import cache

    monkeypatch.setenv("JAXFALSIFY_CACHE_DIR", str(tmp_path))
    table = np.linspace(0.0, 1.0, 64, dtype=np.float32)  # a constant baked into the program

    def fn(x):
        return x * jnp.asarray(table) + 1.0

    x = np.arange(64, dtype=np.float32)
    want = x.astype(np.float64) * table + 1.0
    aval = (jax.ShapeDtypeStruct((64,), jnp.float32),)
    prog = lambda: cache.exported_jit(fn, "damage", {"t": 1}, aval, lambda: (x,))  # noqa: E731
    ref = np.asarray(prog()(x))
    np.testing.assert_allclose(ref, want, rtol=1e-6)  # (XLA may fuse the multiply-add)
    [entry] = list((tmp_path / "exports").glob("damage-*.bin"))
    sealed = entry.read_bytes()
    rng = np.random.default_rng(0)
    for i in rng.choice(len(sealed), 12, replace=False):
        b = bytearray(sealed)
        b[int(i)] ^= 1 << int(rng.integers(8))
        entry.write_bytes(bytes(b))
        np.testing.assert_array_equal(np.asarray(prog()(x)), ref, err_msg=f"byte {i}")
        assert entry.read_bytes() == sealed  # exported again, sealed again


def test_a_damaged_ground_truth_entry_is_swept_again(tmp_path, monkeypatch):
    from jaxfalsify.engine.truth import ground_truth

    monkeypatch.setenv("JAXFALSIFY_CACHE_DIR", str(tmp_path))
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    sp = jf.load_space(str(space))
    first = ground_truth(sp, "carla-tm", None)
    [entry] = list((tmp_path / "truth").glob("*.npz"))
    b = bytearray(entry.read_bytes())
    b[len(b) // 3] ^= 0x10
    entry.write_bytes(bytes(b))
    again = ground_truth(sp, "carla-tm", None)  # was: zipfile.BadZipFile (Bad CRC-32)
    for k in first:
        np.testing.assert_array_equal(again[k], first[k])


# ----------------------------------------------------------------- --force and resume
def test_force_keeps_a_users_own_folders(tmp_path):
    """--force clears jaxfalsify's files and folders only: a user's `checkpoints/` and
    `figures/` in a folder that never held a run are not a run's checkpoint or figures."""
    out = tmp_path / "mine"
    (out / "checkpoints").mkdir(parents=True)
    (out / "checkpoints" / "model.pt").write_text("weights")
    (out / "figures").mkdir()
    (out / "figures" / "plot.png").write_text("png")
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    args = ["run", "--space", space, "--strategy", "random", "--evaluations", "16", "--batch",
            "8", "--out", out, "--quiet", "--no-figures"]
    assert cli(args)[0] == 0  # not an unfinished run: nothing to resume or force
    assert cli(args + ["--force"])[0] == 0
    assert (out / "checkpoints" / "model.pt").read_text() == "weights"
    assert (out / "figures" / "plot.png").read_text() == "png"


def test_force_removes_the_earlier_runs_recordings(tmp_path):
    out = tmp_path / "run"
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    args = ["run", "--space", space, "--strategy", "random", "--evaluations", "16", "--batch",
            "8", "--out", out, "--quiet", "--no-figures"]
    assert cli(args)[0] == 0
    for name in ("replay-best.rrd", "campaign.rrd"):
        (out / name).write_bytes(b"an earlier run's recording")
    assert cli(args + ["--force"])[0] == 0
    assert not (out / "replay-best.rrd").exists() and not (out / "campaign.rrd").exists()


def test_force_sets_complete_results_aside_until_the_new_run_completes(tmp_path, monkeypatch):
    """--force moves a complete run's files (its figures by name, replay's recordings) into
    `.earlier/`, byte for byte, while a user's own figure stays; a forced run that fails
    keeps them there and its status.json names them; once it completes (resumed) they are
    gone."""
    from jaxfalsify.io import store
    from jaxfalsify.outputs import figures

    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    out = tmp_path / "run"
    rc = runs.RunConfig(space=str(space), strategy="random", evaluations=32, batch=8)
    runs.execute(rc, out, figures=False)
    (out / "figures").mkdir()
    (out / "figures" / store.FIGURES[0][0]).write_bytes(b"an earlier figure")
    (out / "figures" / "plot.png").write_bytes(b"the user's own")
    (out / "replay-best.rrd").write_bytes(b"an earlier recording")
    before = {str(q.relative_to(out)): q.read_bytes() for q in out.rglob("*")
              if q.is_file() and q.name != ".lock"}

    def broken(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(figures, "make_figures", broken)
    with pytest.raises(KeyboardInterrupt):
        runs.execute(dataclasses_replace(rc, seed=1), out, force=True)
    monkeypatch.undo()
    kept = {str(q.relative_to(out / ".earlier")): q.read_bytes()
            for q in (out / ".earlier").rglob("*") if q.is_file()}
    assert kept == {k: v for k, v in before.items() if k != "figures/plot.png"}
    assert (out / "figures" / "plot.png").read_bytes() == b"the user's own"
    status = json.loads((out / "status.json").read_text())
    assert status["state"] == "failed" and status["earlier_results"].startswith(".earlier/")
    code, err = cli(["run", "--resume", out, "--quiet", "--no-figures"])
    assert code == 0, err
    assert not (out / ".earlier").exists()
    assert (out / "figures" / "plot.png").read_bytes() == b"the user's own"
    assert json.loads((out / "summary.json").read_text()) != json.loads(before["summary.json"])


def _estimate_folder(out: Path, text: str, state: str = "complete") -> None:
    """A folder as an estimate leaves it: config.toml, summary.json, timing.json, status."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.toml").write_text('kind = "estimate"\n')
    for name in ("summary.json", "timing.json"):
        (out / name).write_text(f"{text} {name}")
    (out / "status.json").write_text(json.dumps({"state": state}))


def _contents(folder: Path) -> dict[str, str]:
    return {str(q.relative_to(folder)): q.read_text() for q in sorted(folder.rglob("*"))
            if q.is_file()}


def test_set_aside_keeps_the_last_complete_results(tmp_path):
    """`.earlier` holds the last complete results: a forced job that did not complete is
    cleared, not set aside over them; complete results replace an older `.earlier`; a
    completed job drops it; put_back restores it over a failed job's files."""
    from jaxfalsify.io import store

    out = tmp_path / "e"
    _estimate_folder(out, "A")
    a = _contents(out)
    store.set_aside(out, "estimate")
    assert _contents(out) == {f".earlier/{k}": v for k, v in a.items()}
    _estimate_folder(out, "B", state="interrupted")  # the forced job, interrupted
    store.set_aside(out, "estimate")  # forced again: B is not complete, A stays
    assert _contents(out) == {f".earlier/{k}": v for k, v in a.items()}
    _estimate_folder(out, "C", state="running")
    store.write_status(out, "estimate", "failed", error="boom")
    assert json.loads((out / "status.json").read_text())["earlier_results"].startswith(
        ".earlier/")
    store.clear(out, "estimate")
    assert store.put_back(out) and _contents(out) == a  # as discard does
    _estimate_folder(out, "D")
    (out / ".earlier").mkdir()
    (out / ".earlier" / "summary.json").write_text("stale")
    d = _contents(out)
    store.set_aside(out, "estimate")  # D is complete: it replaces the stale copy
    assert _contents(out) == {f".earlier/{k}": v for k, v in d.items()
                              if not k.startswith(".earlier")}
    _estimate_folder(out, "E", state="running")
    store.write_status(out, "estimate", "complete")
    assert not (out / ".earlier").exists() and "E summary.json" in _contents(out).values()


def test_the_folder_check_follows_the_real_path(tmp_path):
    """An output folder is inside a run folder by where it really is: `done/../x` is not,
    a link into `done/figures` is; the folder holding `done` takes no run itself; a
    `.earlier` that is a file is refused with --force."""
    from jaxfalsify.io import store

    done = tmp_path / "done"
    (done / "figures").mkdir(parents=True)
    (done / "config.toml").write_text('kind = "run"\n')
    (done / "summary.json").write_text("{}")
    store.check_out(done / ".." / "x", "run")  # no error
    with pytest.raises(store.FolderError, match=r"holds a run in .*done; a run takes a folder"):
        store.check_out(tmp_path, "run")  # the folder holding it: `--out runs`
    store.check_out(tmp_path, "compare")  # a comparison holds its own runs
    (tmp_path / "link").symlink_to(done / "figures")
    with pytest.raises(store.FolderError, match="which holds a run"):
        store.check_out(tmp_path / "link" / "x", "run")
    _estimate_folder(tmp_path / "e", "A")
    (tmp_path / "e" / ".earlier").write_text("mine")
    with pytest.raises(store.FolderError, match=r"\.earlier is not a folder"):
        store.check_out(tmp_path / "e", "estimate", force=True)


def test_a_run_that_failed_while_writing_resumes(tmp_path, monkeypatch):
    """The search finished, summary.json was written, the figures failed: status.json says
    failed and how to resume, and the resume finishes the outputs (identical results)."""
    from jaxfalsify.outputs import figures

    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    rc = runs.RunConfig(space=str(space), strategy="random", evaluations=32, batch=8)
    runs.execute(rc, tmp_path / "ref", figures=False)

    def broken(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(figures, "make_figures", broken)
    with pytest.raises(KeyboardInterrupt):
        runs.execute(rc, tmp_path / "run")
    status = json.loads((tmp_path / "run" / "status.json").read_text())
    assert status["state"] == "failed" and (tmp_path / "run" / "summary.json").exists()
    monkeypatch.undo()
    code, err = cli(["run", "--resume", tmp_path / "run", "--quiet", "--no-figures"])
    assert code == 0, err
    assert json.loads((tmp_path / "run" / "status.json").read_text())["state"] == "complete"
    assert (tmp_path / "run" / "summary.json").read_bytes() == \
        (tmp_path / "ref" / "summary.json").read_bytes()
    assert cli(["run", "--resume", tmp_path / "run", "--quiet"])[1].strip().endswith(
        "already complete (summary.json)")


def test_a_failed_write_names_its_file(tmp_path, monkeypatch):
    """A write that fails inside an open file (ENOSPC carries no file name) is reported with
    the path being written, and leaves neither the file nor its temporary behind."""
    class Full(io.BytesIO):
        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    real = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda fd, mode: (os.close(fd), Full())[1])
    with pytest.raises(OSError) as e:
        write_atomic(tmp_path / "summary.json", "{}")
    assert e.value.filename == str(tmp_path / "summary.json") and e.value.errno == errno.ENOSPC
    monkeypatch.setattr(os, "fdopen", real)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError) as e:
        with atomic_path(tmp_path / "figure.png"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert e.value.filename == str(tmp_path / "figure.png")
    assert list(tmp_path.iterdir()) == []


def test_a_recording_that_cannot_be_written_is_one_line_and_no_file(tmp_path, monkeypatch,
                                                                      capsys):
    """replay --save on a full disk: exit 1, one line naming the file, and no file under its
    name (rerun's own file sink once left a truncated one and the command said it wrote it);
    with room, a recording rerun reads back, holding the scenario's world and metrics."""
    run = tmp_path / "run"
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    assert cli(["run", "--space", space, "--strategy", "random", "--evaluations", "16",
                "--batch", "8", "--out", run, "--quiet", "--no-figures"])[0] == 0

    class Full(io.BytesIO):
        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device")

    real = os.fdopen
    monkeypatch.setattr(os, "fdopen", lambda fd, mode: (os.close(fd), Full())[1])
    for args, name in ((["replay", str(run), "--save", str(tmp_path / "best.rrd")], "best.rrd"),
                       (["replay", str(run), "--campaign"], "campaign.rrd")):
        capsys.readouterr()
        assert main(args) == 1, args
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and name in err[0] and "No space left on device" in err[0], err
    monkeypatch.setattr(os, "fdopen", real)
    assert not (tmp_path / "best.rrd").exists() and not (run / "campaign.rrd").exists()
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".best.rrd")]
    assert main(["replay", str(run), "--save", str(tmp_path / "best.rrd")]) == 0
    from rerun.chunk import RrdReader

    entities = {c.entity_path for c in RrdReader(tmp_path / "best.rrd").stream().to_chunks()}
    assert {"/world/ego", "/world/pedestrian", "/metrics/distance"} <= entities


def test_an_undamaged_sweep_checkpoint_resumes_identically(checkpoints):
    """The recount of a sweep's totals from its rows files accepts an honest checkpoint
    (float32 columns read back, NaN collision times of a non-colliding best row)."""
    base = checkpoints["base"]
    tmp = Path(tempfile.mkdtemp(dir=base))
    shutil.copytree(base / "sweep", tmp / "sweep")
    code, err = cli(["sweep", "--resume", tmp / "sweep", "--quiet"])
    assert code == 0, err
    ref = base / "sweep_ref"
    assert (tmp / "sweep" / "summary.json").read_bytes() == (ref / "summary.json").read_bytes()
    assert _same_parquet(tmp / "sweep" / "sweep.parquet", ref / "sweep.parquet")
    shutil.rmtree(tmp)


def test_the_resume_command_is_quoted_for_a_shell(tmp_path):
    """A folder name with a space: the printed and recorded resume command, split as a shell
    splits it, names that folder."""
    import json
    import shlex

    from jaxfalsify.io import store

    out = tmp_path / "my run"
    out.mkdir()
    store.write_status(out, "run", "interrupted")
    cmd = json.loads((out / "status.json").read_text())["resume"]
    assert shlex.split(cmd) == ["jaxfalsify", "run", "--resume", str(out)]
    # a relative name that starts with "-" gets "./", so it is not read as a flag
    from jaxfalsify.cli import build_parser

    assert shlex.split(store.shell_path(Path("-x")))[0] == "./-x"
    args = build_parser().parse_args(shlex.split(f"run --resume {store.shell_path('-x')}"))
    assert args.resume is not None and str(args.resume) in ("-x", "./-x")


def test_default_folders_of_the_same_second_do_not_collide(tmp_path):
    """Two commands started in the same second get ``base`` and ``base-2`` (each created
    exclusively), not one folder that the second then calls an unfinished run of its own."""
    from jaxfalsify.io import store

    base = tmp_path / "runs" / "20261124-094511-random"
    a, la = store.open_new_folder(base, "run")
    b, lb = store.open_new_folder(base, "run")
    try:
        assert (a, b) == (base, base.with_name(base.name + "-2"))
        assert a.is_dir() and b.is_dir()
    finally:
        la.release()
        lb.release()


@pytest.mark.slow  # two fresh processes, each compiling
def test_a_cached_program_is_not_reused_under_another_prng(tmp_path):
    """JAX's PRNG implementation sets the shape of key data: a sweep program cached under the
    default one is not handed to a process using rbg (it failed with a shape mismatch)."""
    import subprocess
    import sys

    from conftest import TINY_SPACE

    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    env = {**os.environ, "JAXFALSIFY_CACHE_DIR": str(tmp_path / "cache")}
    for k, impl in enumerate(("threefry2x32", "rbg")):
        r = subprocess.run([sys.executable, "-m", "jaxfalsify", "sweep", "--space", "tiny.toml",
                            "--out", f"s{k}", "--quiet"], cwd=tmp_path, capture_output=True,
                           text=True, env={**env, "JAX_DEFAULT_PRNG_IMPL": impl})
        assert r.returncode == 0, r.stderr


def test_replace_files_publishes_a_set_or_puts_the_earlier_one_back(tmp_path):
    """replace_files (the export's swap): the earlier set goes, other files stay, the
    new set appears; when a move fails half-way the earlier set is back byte for byte and
    none of the new files is left."""
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "a.xosc").write_text("old a")
    (folder / "b.xosc").write_text("old b")
    (folder / "notes.txt").write_text("mine")
    is_old = lambda name: name.endswith(".xosc")  # noqa: E731
    stage = Path(tempfile.mkdtemp(dir=folder, prefix=".stage-"))
    (stage / "a.xosc").write_text("new a")
    (stage / "c.xosc").write_text("new c")
    got = replace_files([stage / "a.xosc", stage / "c.xosc"], folder, is_old)
    assert got == [folder / "a.xosc", folder / "c.xosc"]
    assert {p.name: p.read_text() for p in folder.iterdir() if p.is_file()} == {
        "a.xosc": "new a", "c.xosc": "new c", "notes.txt": "mine"}
    assert [p.name for p in stage.iterdir()] == []  # nothing left aside
    # a staged file that is gone makes the second move fail: everything as before
    (stage / "d.xosc").write_text("new d")
    with pytest.raises(FileNotFoundError):
        replace_files([stage / "d.xosc", stage / "missing.xosc"], folder, is_old)
    assert {p.name: p.read_text() for p in folder.iterdir() if p.is_file()} == {
        "a.xosc": "new a", "c.xosc": "new c", "notes.txt": "mine"}
    assert [p.name for p in stage.iterdir()] == []
    assert sorted(p.name for p in folder.iterdir() if p.is_dir()) == [stage.name]
    with pytest.raises(ValueError, match="no files to publish"):  # would only delete
        replace_files([], folder, is_old)
    # an earlier file that cannot be put back is kept aside, and the error says where
    (stage / "e.xosc").write_text("new e")
    real = os.replace

    def flaky(src, dst):
        if Path(src).name == "missing.xosc" or (Path(src).parent.name.startswith(".replaced-")
                                                and Path(src).name == "c.xosc"):
            raise OSError(5, "Input/output error")
        return real(src, dst)

    with pytest.MonkeyPatch.context() as m:
        m.setattr(os, "replace", flaky)
        with pytest.raises(OSError, match="could not be put back; they are in") as e:
            replace_files([stage / "e.xosc", stage / "missing.xosc"], folder, is_old)
    kept = Path(str(e.value).rsplit(" ", 1)[-1])
    assert kept.parent == folder and (kept / "c.xosc").read_text() == "new c"
    assert (folder / "a.xosc").read_text() == "new a" and not (folder / "e.xosc").exists()


@pytest.mark.parametrize("what", ["run", "sweep"])
def test_a_file_in_place_of_the_checkpoint_folder_is_refused_and_status_kept(checkpoints,
                                                                             what):
    """``checkpoint/`` replaced by a file: ``--resume`` exits 2 with one line naming the
    damaged checkpoint, and status.json is left as it was (nothing rewritten while failing)."""
    tmp = Path(tempfile.mkdtemp(dir=checkpoints["base"]))
    folder = tmp / what
    shutil.copytree(checkpoints["base"] / what, folder)
    shutil.rmtree(folder / "checkpoint")
    (folder / "checkpoint").write_text("not a checkpoint\n")
    status = (folder / "status.json").read_bytes()
    code, err = cli([what, "--resume", folder, "--quiet"]
                    + (["--no-figures"] if what == "run" else []))
    assert_one_line_error(code, err)
    assert f"checkpoint {folder / 'checkpoint'} is damaged: not a folder" in err, err
    assert (folder / "status.json").read_bytes() == status
    shutil.rmtree(tmp)
