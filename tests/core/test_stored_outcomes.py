"""Every outcome of a fixed sample of 3,000 scenarios of ``paper-extended`` (each built-in
SUT) is bit-for-bit the one stored in ``tests/data/reference_outcomes.npz``, whatever the batch
is cut into: the simulator's speed-ups change no outcome (oracle: outcomes stored from the
simulator as it was before them; NaN compared as NaN). One exception: ``final_distance``, the
centre distance, within 2 ulp, because its last bits depend on how XLA fuses the step (on CPUs
it contracts a multiply-add inside one kernel into a fused multiply-add, and before the step
stored its intermediate values the SUT's arithmetic shared a product with it; see
docs/performance.md). ``lanes``: the batch on one lane per scenario, or on refilled lanes (one
per 8 scenarios, at least 64)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import jaxfalsify as jf
from jaxfalsify.core import sim

STORED = Path(__file__).parents[1] / "data" / "reference_outcomes.npz"


@pytest.fixture(scope="module")
def stored():
    with np.load(STORED) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(params=["one per scenario", "refilled"])
def lanes(request, monkeypatch):
    if request.param == "refilled":
        monkeypatch.setattr(sim, "MIN_LANES", 64)
    else:
        monkeypatch.setattr(sim, "LANES_PER", 1)
    sim._batch_program.cache_clear()
    yield request.param
    sim._batch_program.cache_clear()


def _scenarios(index):
    """The concrete scenarios of ``paper-extended`` at flat ``index``."""
    sp = jf.load_space("paper-extended")
    idx = np.stack(np.unravel_index(index, sp.shape), -1)
    return {k: np.asarray(v, np.float32) for k, v in sp.scenario(idx).items()}


def _assert_as_stored(out, stored, sut, rows=slice(None)):
    """Every stored field of ``sut`` bit-for-bit (``final_distance`` within 2 ulp) at ``rows``."""
    for k in (k for k in stored if k.startswith(f"{sut}/")):
        got, want = np.asarray(getattr(out, k.split("/", 1)[1])), stored[k][rows]
        assert got.dtype == want.dtype, k
        if k.endswith("/final_distance"):
            assert np.array_equal(np.isnan(got), np.isnan(want)), k
            ok = ~np.isnan(want)
            np.testing.assert_array_max_ulp(got[ok], want[ok], maxulp=2)
            continue
        np.testing.assert_array_equal(got.view(np.uint8), want.view(np.uint8), err_msg=k)


@pytest.mark.parametrize("sut", ["none", "carla-tm", "sensor-aeb"])
@pytest.mark.parametrize("chunk", [3000, 1024])
def test_outcomes_are_bit_identical_to_the_stored_ones(stored, sut, chunk, lanes):
    assert (sim.lane_count(chunk) < chunk) == (lanes == "refilled")
    out = jf.evaluate(_scenarios(stored["index"]), sut=sut, chunk_size=chunk)
    fields = [k for k in stored if k.startswith(f"{sut}/")]
    assert len(fields) == len(vars(out)) - 1  # (min_rss_margin: stored before it existed)
    _assert_as_stored(out, stored, sut)


@pytest.mark.parametrize("sut", ["none", "carla-tm", "sensor-aeb"])
def test_an_odd_batch_is_padded_and_changes_no_outcome(stored, sut, monkeypatch):
    """A batch of 999 (padded to 1,000 scenarios by ``run_batch``) and one of 1 give the stored
    outcomes of the same scenarios."""
    calls = []
    program = sim._batch_program
    monkeypatch.setattr(sim, "_batch_program", lambda *a: calls.append(a[2]) or program(*a))
    sc = _scenarios(stored["index"][:1000])
    for lo, hi in ((0, 999), (999, 1000)):
        out = jf.evaluate({k: v[lo:hi] for k, v in sc.items()}, sut=sut)
        _assert_as_stored(out, stored, sut, slice(lo, hi))
    assert calls == [1000, 8]
