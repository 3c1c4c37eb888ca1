"""XLA's CPU thread count (:mod:`jaxfalsify.base.threads`): the count asked for is the number
of XLA's kernel threads the process runs (oracle: the operating system's list of the process's
threads), an ``NPROC`` already set is left alone, bad values are refused in one line, and
outcomes are the same bits on one thread as on two (oracle: the same scenarios evaluated in a
process with the other count)."""

import json
import subprocess
import sys

import pytest

from jaxfalsify.base import threads

PROBE = """
import collections, json, os
import numpy as np
import jaxfalsify as jf
rng = np.random.default_rng(0)
sc = dict(ego_offset=rng.uniform(0.5, 11.0, 512), ped_accel=rng.uniform(0.0, 0.11, 512),
          ped_speed=rng.uniform(0.5, 2.5, 512), ped_offset=rng.uniform(2.5, 5.0, 512),
          weather=rng.integers(0, 15, 512).astype(float))
out = jf.evaluate(sc, sut="sensor-aeb")
names = collections.Counter(open(f"/proc/self/task/{t}/comm").read().strip()
                            for t in os.listdir("/proc/self/task"))
print(json.dumps({"kernel_threads": names["tf_XLAEigen"], "nproc": os.environ.get("NPROC"),
                  "min_distance": out.min_distance.tobytes().hex(),
                  "reward": out.reward.tobytes().hex(),
                  "collision": out.collision.tobytes().hex()}))
"""


def probe(env):
    import os

    full = {k: v for k, v in os.environ.items() if k not in ("NPROC", threads.ENV)}
    full.update(env)
    out = subprocess.run([sys.executable, "-c", PROBE], env=full, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_count_asked_for_is_what_xla_runs_and_outcomes_do_not_move():
    one = probe({threads.ENV: "1"})
    two = probe({threads.ENV: "2"})
    assert (one["kernel_threads"], one["nproc"]) == (1, "1")
    assert (two["kernel_threads"], two["nproc"]) == (2, "2")
    for field in ("min_distance", "reward", "collision"):
        assert one[field] == two[field], field
    kept = probe({"NPROC": "3", threads.ENV: "1"})  # the user's own NPROC wins
    assert (kept["kernel_threads"], kept["nproc"]) == (3, "3")


def test_auto_is_one_thread_on_two_cores_or_fewer(monkeypatch):
    for n, expect in ((1, 1), (2, 1), (3, None), (16, None)):
        monkeypatch.setattr(threads, "cores", lambda n=n: n)
        env = {}
        assert threads.configure(env) == expect
        assert env == ({} if expect is None else {"NPROC": str(expect)})
    env = {"NPROC": "5"}
    assert threads.configure(env) is None and env == {"NPROC": "5"}


@pytest.mark.parametrize("value", ["0", "-1", "two", "1.5"])
def test_bad_values_are_refused_in_one_line(value):
    with pytest.raises(ValueError, match=rf"^JAXFALSIFY_XLA_THREADS='{value}': expected auto"):
        threads.configure({threads.ENV: value})


def test_more_threads_than_four_per_core_and_256_are_refused(monkeypatch):
    # XLA starts every thread asked for (100,000 took 19 GB): the bound is 4 per core, and at
    # least 256 (a few MB)
    for n_cores, limit in ((3, 256), (100, 400)):
        monkeypatch.setattr(threads, "cores", lambda n=n_cores: n)
        env = {threads.ENV: str(limit)}
        assert threads.configure(env) == limit and env["NPROC"] == str(limit)
        with pytest.raises(ValueError, match=rf"^JAXFALSIFY_XLA_THREADS='{limit + 1}': at most "
                                             rf"{limit} threads \(the larger of 256 and 4 per "
                                             rf"core of the {n_cores} "):
            threads.configure({threads.ENV: str(limit + 1)})
        with pytest.raises(ValueError, match=rf"^NPROC='100000': at most {limit} threads"):
            threads.configure({"NPROC": "100000"})
        env = {"NPROC": str(limit)}
        assert threads.configure(env) is None and env == {"NPROC": str(limit)}


def test_the_command_line_refuses_a_bad_value_with_exit_code_2(tmp_path):
    import os

    env = {**os.environ, threads.ENV: "many"}
    env.pop("NPROC", None)
    out = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--out", str(tmp_path / "r")],
                         env=env, capture_output=True, text=True)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        "jaxfalsify: error: JAXFALSIFY_XLA_THREADS='many': expected auto or a positive whole "
        "number of threads (set in the environment: fix or unset it)"]
    assert not (tmp_path / "r").exists()
    env = {**os.environ, "NPROC": "100000"}
    out = subprocess.run([sys.executable, "-m", "jaxfalsify", "run", "--out", str(tmp_path / "r")],
                         env=env, capture_output=True, text=True)
    limit = max(4 * threads.cores(), 256)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == [
        f"jaxfalsify: error: NPROC='100000': at most {limit} threads (the larger of 256 and 4 "
        f"per core of the {threads.cores()} this process may run on) (set in the environment: "
        "fix or unset it)"]
    assert not (tmp_path / "r").exists()
