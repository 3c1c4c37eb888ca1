"""The pieces ``reinforce/screened`` is composed of, each against an independent oracle: the
advantage functions (NumPy), the memory of evaluated scenarios (a Python ring buffer of
sets), the GP screen's history (a Python list); and the composition itself: a piece given as a
function does what the named one does."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxfalsify import search
from jaxfalsify.search.base import ADVANTAGES, resolve_advantage, standardised
from jaxfalsify.search.memory import NoRepeats, scenario_hash
from jaxfalsify.search.surrogate import GPScreen


def test_standardised_matches_numpy_and_is_zero_where_all_are_equal():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 9)).astype(np.float32)
    valid = rng.random((3, 9)) < 0.7
    x[2] = 0.25  # all equal: no advantage at all
    got = np.asarray(standardised(jnp.asarray(x), jnp.asarray(valid)))
    for row in range(2):
        v = x[row][valid[row]].astype(np.float64)
        want = np.where(valid[row], (x[row] - v.mean()) / (v.std() + 1e-8), 0.0)
        np.testing.assert_allclose(got[row], want, rtol=1e-5, atol=1e-6)
    assert np.all(got[2] == 0.0)


def test_an_advantage_is_a_name_or_a_function_and_a_bad_one_is_refused_in_one_line():
    assert resolve_advantage("normalised") is standardised
    f = lambda s, v: jnp.where(v, s, 0.0)  # noqa: E731
    assert resolve_advantage(f) is f
    with pytest.raises(ValueError, match="advantage must be one of rank, normalised") as e:
        search.make("reinforce/screened", (4, 4), advantage="median")
    assert "\n" not in str(e.value) and sorted(ADVANTAGES) == ["normalised", "rank"]


@pytest.mark.slow
def test_a_strategy_given_the_advantage_function_asks_as_with_its_name():
    shape = (10, 7, 12)

    def run(advantage):
        s, p = search.make("reinforce/screened", shape, advantage=advantage, surrogate=0)

        def step(st, k):
            idx, st = s.ask(k, st, p)
            rob = jnp.sum(jnp.abs(idx - jnp.array([8, 1, 10])), -1).astype(jnp.float32) - 1
            return s.tell_outcome(k, st, idx, -rob, rob, rob < 0, p), idx

        return jax.lax.scan(step, s.init(jax.random.key(0), p),
                            jax.random.split(jax.random.key(1), 5))[1]

    named = np.asarray(jax.jit(lambda: run("normalised"))())
    given = np.asarray(jax.jit(lambda: run(standardised))())
    np.testing.assert_array_equal(given, named)
    assert len(np.unique(named.reshape(-1, 3), axis=0)) > 32  # it moved: the test can fail


def test_no_repeats_remembers_the_last_size_hashes_like_a_ring_buffer():
    mem = NoRepeats(8)
    st = mem.init()
    rng = np.random.default_rng(1)
    ring: list[int] = []
    for _ in range(5):
        batch = rng.integers(0, 6, size=(3, 2)).astype(np.int32)
        h = np.asarray(scenario_hash(jnp.asarray(batch)))
        probe = rng.integers(0, 6, size=(10, 2)).astype(np.int32)
        ph = np.asarray(scenario_hash(jnp.asarray(probe)))
        got = np.asarray(mem.evaluated(st, jnp.asarray(ph)))
        np.testing.assert_array_equal(got, [int(x) in set(ring[-8:]) for x in ph])
        st = mem.remember(st, jnp.asarray(h))
        ring += [int(x) for x in h]
    assert int(st.written) == 15


def test_the_gp_screen_keeps_the_last_size_evaluations_with_non_finite_signals_emptied():
    screen = GPScreen(4, "se", (5, 5))
    st = screen.init()
    kept: list[tuple] = []
    rng = np.random.default_rng(2)
    for _ in range(3):
        idx = rng.integers(0, 5, size=(3, 2)).astype(np.int32)
        sig = rng.normal(size=3).astype(np.float32)
        sig[1] = np.nan
        st = screen.record(st, jnp.asarray(idx), jnp.asarray(sig))
        kept += [(tuple(i), s if np.isfinite(s) else -np.inf) for i, s in zip(idx, sig)]
    # slot = evaluation number mod 4: the last four evaluations, in ring order
    want = {n % 4: kept[n] for n in range(len(kept))}
    for slot, (i, s) in want.items():
        assert tuple(np.asarray(st.history[slot])) == i
        assert float(st.history_signal[slot]) == pytest.approx(s)
