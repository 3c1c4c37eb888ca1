"""Sizes within the documented ranges that would not fit in memory are refused before anything
runs, with the memory they would need (oracles: the bytes of a state actually allocated, the
available memory set by the test)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from jaxfalsify.base import config as cfg
from jaxfalsify.cli import main
from jaxfalsify.jobs import runs


def _allocated_state_bytes(rc: runs.RunConfig) -> int:
    b = rc.build()
    state = b.strategy.init(jax.random.key(0), b.strategy_params)
    return sum(np.asarray(x).nbytes for x in jax.tree.leaves(state))


def test_the_state_estimate_is_the_state_a_strategy_allocates(monkeypatch):
    rc = runs.RunConfig(strategy="reinforce/screened", batch=64, evaluations=128,
                        strategy_params={"hidden": 48, "learners": 4})
    real = _allocated_state_bytes(rc)
    # just enough memory for three copies of that state: accepted; one byte less: refused
    monkeypatch.setattr(cfg, "available_memory", lambda: 2 * runs.STATE_COPIES * real)
    runs.check_strategy_memory(rc.build(), rc.strategy, rc.strategy_params)
    monkeypatch.setattr(cfg, "available_memory", lambda: 2 * runs.STATE_COPIES * real - 2)
    with pytest.raises(ValueError, match=r"the state of reinforce/screened \(hidden=48, "
                                         r"learners=4\) needs about"):
        runs.check_strategy_memory(rc.build(), rc.strategy, rc.strategy_params)


@pytest.mark.parametrize("command", ["run", "compare"])
def test_a_strategy_too_large_for_memory_is_refused_before_anything_runs(command, tmp_path,
                                                                         monkeypatch, capsys):
    """hidden=1024 x learners=1024 of reinforce/screened (both at the top of their documented
    ranges): 1024 LSTMs of 1024 units, with Adam's moments, far beyond this machine."""
    out = tmp_path / "big"
    flags = (["--strategy", "reinforce/screened", "--strategy-param", "hidden=1024",
              "--strategy-param", "learners=1024"] if command == "run" else
             ["--strategies", "reinforce/screened,random", "--strategy-param",
              "reinforce/screened:hidden=1024", "--strategy-param",
              "reinforce/screened:learners=1024", "--seeds", "1"])
    monkeypatch.setattr(cfg, "available_memory", lambda: 8 * 2**30)
    assert main([command, *flags, "--batch", "1024", "--evaluations", "2048", "--out", str(out),
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # the recurrent weights alone: 1024 learners x 4 gates x 1024 x 1024 float32, with Adam's
    # two moments: 48 GiB, counted STATE_COPIES times
    need = float(err[0].split("needs about ")[1].split(" GiB")[0])
    assert len(err) == 1 and "hidden=1024, learners=1024" in err[0], err
    assert need >= runs.STATE_COPIES * 3 * 1024 * 4 * 1024 * 1024 * 4 / 2**30
    assert not out.exists()
