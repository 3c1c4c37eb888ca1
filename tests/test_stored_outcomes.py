"""Every outcome of a fixed sample of 3,000 scenarios of ``paper-extended`` (each built-in
SUT) is bit-for-bit the one stored in ``tests/data/reference_outcomes.npz``, whatever the batch
is cut into: the simulator's speed-ups change no outcome (oracle: outcomes stored from the
simulator as it was before them; NaN compared as NaN)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import jaxfalsify as jf

STORED = Path(__file__).parent / "data" / "reference_outcomes.npz"


@pytest.fixture(scope="module")
def stored():
    with np.load(STORED) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("sut", ["none", "carla-tm", "sensor-aeb"])
@pytest.mark.parametrize("chunk", [3000, 1024])
def test_outcomes_are_bit_identical_to_the_stored_ones(stored, sut, chunk):
    sp = jf.load_space("paper-extended")
    idx = np.stack(np.unravel_index(stored["index"], sp.shape), -1)
    sc = {k: np.asarray(v, np.float32) for k, v in sp.scenario(idx).items()}
    out = jf.evaluate(sc, sut=sut, chunk_size=chunk)
    fields = [k for k in stored if k.startswith(f"{sut}/")]
    assert len(fields) == len(vars(out))
    for k in fields:
        got, want = np.asarray(getattr(out, k.split("/", 1)[1])), stored[k]
        assert got.dtype == want.dtype, k
        np.testing.assert_array_equal(got.view(np.uint8), want.view(np.uint8), err_msg=k)
