"""Per-user cache entries are used only by the configuration they were built for: an entry of
another configuration put under this one's name (each file intact) is rebuilt, never loaded
(oracles: the function's own results, an uncached sweep)."""

from __future__ import annotations

import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxfalsify.core import sim
from jaxfalsify.engine import truth
from jaxfalsify.io import cache
from jaxfalsify.scenario.space import space_from_dict
from jaxfalsify.suts import registry as sut_lib


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXFALSIFY_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv("JAXFALSIFY_NO_CACHE", raising=False)
    return tmp_path / "cache"


def _program(fn, tag):
    x = np.zeros(3, np.float32)
    return cache.exported_jit(fn, "swap", {"tag": tag}, (x,), lambda: (x,))


def test_a_program_of_another_configuration_under_this_name_is_rebuilt(own_cache, capsys):
    def plus(x):
        return [x + 1.0]

    def times(x):
        return [x * 2.0]

    _program(plus, "plus")
    _program(times, "times")
    files = {p.name: p for p in (own_cache / "exports").glob("swap-*.bin")}
    assert len(files) == 2
    a, b = sorted(files.values())
    # which file is which: load each as its own configuration first
    x = jnp.arange(3.0)
    got_plus = np.asarray(_program(plus, "plus")(x)[0])
    assert got_plus.tolist() == [1.0, 2.0, 3.0]
    # swap the two entries (both intact, both sealed)
    tmp = a.with_suffix(".tmp")
    shutil.copy(a, tmp)
    shutil.copy(b, a)
    shutil.copy(tmp, b)
    tmp.unlink()
    capsys.readouterr()
    assert np.asarray(_program(plus, "plus")(x)[0]).tolist() == [1.0, 2.0, 3.0]
    assert np.asarray(_program(times, "times")(x)[0]).tolist() == [0.0, 2.0, 4.0]
    said = capsys.readouterr().err.splitlines()  # one line per rebuilt entry, naming it
    assert sorted(line.split()[3] for line in said) == sorted(str(p) for p in (a, b))
    assert all("rebuilding" in line for line in said)
    # a matching entry is used without a word
    _program(plus, "plus")
    assert capsys.readouterr().err == ""


SPACE = {"name": "tiny-truth", "parameters": {
    "ego_offset": {"distribution": "integers", "low": 1, "high": 4, "samples": 4},
    "ped_speed": {"distribution": "uniform", "low": 0.8, "high": 2.0, "samples": 5}}}


def test_a_ground_truth_of_another_space_under_this_name_is_swept_again(own_cache, capsys):
    s0, s1 = space_from_dict(SPACE, seed=0), space_from_dict(SPACE, seed=1)
    assert not all(np.array_equal(a, b) for a, b in zip(s0.values, s1.values))
    truth.ground_truth(s0)
    other = truth.ground_truth(s1)
    entries = sorted((own_cache / "truth").glob("*.npz"), key=lambda p: p.stat().st_mtime)
    assert len(entries) == 2
    shutil.copy(entries[1], entries[0])  # seed 1's entry under seed 0's name
    want = truth.sweep_arrays(s0, sut_lib.resolve("carla-tm"), None, sim.WORLD,
                              fields=truth.TRUTH_FIELDS)
    assert any(not np.array_equal(other[k], want[k]) for k in truth.TRUTH_FIELDS)  # power
    capsys.readouterr()
    got = truth.ground_truth(s0)
    said = capsys.readouterr().err.splitlines()
    assert len(said) == 1 and str(entries[0]) in said[0] and "rebuilding" in said[0]
    for k in truth.TRUTH_FIELDS:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_the_code_hash_covers_every_module_of_the_package_and_none_is_user_code():
    """A compiled program is keyed on the package's own source: every module of every layer
    folder counts (oracle: the modules ``pkgutil`` walks), and none of them is taken for a
    user's module (whose file would be hashed apart)."""
    import importlib
    import pkgutil

    import jaxfalsify

    mods = [m.name for m in pkgutil.walk_packages(jaxfalsify.__path__, "jaxfalsify.")]
    files = {Path(importlib.import_module(m).__file__).resolve() for m in mods
             if m != "jaxfalsify.__main__"} | {Path(jaxfalsify.__file__).resolve()}
    assert len(files) > 50
    covered = {f.resolve() for f in cache.package_files()}
    assert files - covered == set()
    roots = cache._installed_roots()  # code identified by versions and code_hash
    assert [f for f in files if not str(f).startswith(roots)] == []
