"""Host evaluators for the tests of jaxfalsify.jobs.evaluators (loaded by file path in worker
processes). Each returns the robustness ``ped_speed - 1.5`` (negative: violated), an oracle the
tests compute themselves, and misbehaves on chosen scenarios."""

import os
import time
from pathlib import Path

import numpy as np


def plain(s):
    return np.asarray(s["ped_speed"]) - 1.5


def with_signals(s):
    rob = plain(s)
    return {"robustness": rob, "collision": rob < -0.2, "reward": -2.0 * rob,
            "min_distance": np.abs(rob)}


def raises_fast(s):
    """Raises for a batch holding a scenario with ped_speed > 1.8."""
    if np.any(np.asarray(s["ped_speed"]) > 1.8):
        raise RuntimeError("walker too fast for this simulator")
    return plain(s)


def hangs_fast(s):
    """Hangs (60 s) on a batch holding a scenario with ped_speed > 1.8."""
    if np.any(np.asarray(s["ped_speed"]) > 1.8):
        time.sleep(60)
    return plain(s)


def dies_fast(s):
    """Its process exits on a batch holding a scenario with ped_speed > 1.8."""
    if np.any(np.asarray(s["ped_speed"]) > 1.8):
        os._exit(3)
    return plain(s)


def flaky(s):
    """Fails the first time it sees each scenario (a marker file per scenario in the folder
    $FLAKY_DIR), then succeeds."""
    d = Path(os.environ["FLAKY_DIR"])
    keys = [f"{a:.6f}-{b:.6f}" for a, b in zip(s["ped_speed"], s["ego_offset"])]
    fresh = [k for k in keys if not (d / k).exists()]
    for k in fresh:
        (d / k).touch()
    if fresh:
        raise RuntimeError("first try fails")
    return plain(s)


def wrong_length(s):
    return plain(s)[:-1]


def two_args(s, extra):
    return plain(s)


NOT_CALLABLE = 3


def nan_fast(s):
    """NaN robustness for ped_speed > 1.6."""
    rob = plain(s)
    return np.where(np.asarray(s["ped_speed"]) > 1.6, np.nan, rob)


def signals_raise_fast(s):
    """with_signals, raising for a batch holding a scenario with ped_speed > 1.8."""
    raises_fast(s)
    return with_signals(s)


def exits_after_reply(s):
    """Replies, then its process exits 0.2 s later (a worker that dies while idle)."""
    import threading

    threading.Timer(0.2, os._exit, args=(0,)).start()
    return plain(s)


def with_trajectory(s):
    """plain, with a trajectory: t = 0.1 k, distance = |robustness| + t, 5 steps (NaN after
    the third for ped_speed < 1.5); raises for ped_speed > 1.65."""
    if np.any(np.asarray(s["ped_speed"]) > 1.65):
        raise RuntimeError("walker too fast for this simulator")
    rob = plain(s)
    t = np.tile(np.arange(1, 6) * 0.1, (len(rob), 1))
    d = np.abs(rob)[:, None] + t
    d[rob < 0, 3:] = np.nan
    return {"robustness": rob, "trajectory": {"t": t, "distance": d}}


def bad_trajectory(s):
    rob = plain(s)
    return {"robustness": rob, "trajectory": {"distance": np.zeros((len(rob) + 1, 4))}}


def nan_collision(s):
    """A collision flag that is neither true nor false (NaN), once per batch."""
    rob = plain(s)
    flag = (rob < 0).astype(float)
    flag[0] = np.nan
    return {"robustness": rob, "collision": flag}


def scalar(s):
    """One robustness for the whole batch: a float, not an array of shape (n,)."""
    return float(np.min(plain(s)))


def returns_none(s):
    """A missing return."""
    plain(s)
