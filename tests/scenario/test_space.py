"""Logical scenario spaces: built-ins (Table I), index <-> value maps, TOML, and bad input."""

import re

import jax
import numpy as np
import pytest

import jaxfalsify as jf
from jaxfalsify.scenario.space import space_from_dict


@pytest.fixture(scope="module")
def paper():
    return jf.load_space("paper", seed=0)


def test_paper_space_is_table_one(paper):
    assert paper.names == ("ego_offset", "ped_accel", "ped_speed", "ped_offset", "weather")
    assert paper.shape == (10, 10, 25, 4, 10)
    assert paper.size == 100_000
    v = dict(zip(paper.names, paper.values))
    np.testing.assert_array_equal(v["ego_offset"], np.arange(1, 11))
    np.testing.assert_array_equal(v["ped_offset"], [3.0, 3.5, 4.0, 4.5])
    assert np.all((v["ped_accel"] >= 0) & (v["ped_accel"] <= 0.1))
    w = v["weather"]
    assert len(set(w.tolist())) == 10 and np.all(w == np.round(w))
    assert w.min() >= 0 and w.max() <= 14
    for name in ("ped_accel", "ped_speed"):  # rounded to 3 decimals as the original
        np.testing.assert_allclose(v[name], np.round(v[name].astype(np.float64), 3), atol=1e-6)
    # 25 draws of N(1.46, 0.24): a loose check that the distribution was used
    assert 1.2 < v["ped_speed"].mean() < 1.7


def test_paper_extended_size():
    sp = jf.load_space("paper-extended")
    assert sp.size == 2_000_000
    assert sp.names[-2:] == ("ped_speed_change", "ped_change_step")


def test_seed_determinism_and_dependence():
    a, b = jf.load_space("paper", seed=1), jf.load_space("paper", seed=1)
    c = jf.load_space("paper", seed=2)
    assert a.table == b.table
    assert a.table != c.table


def test_ravel_unravel_match_numpy(paper):
    """The jit-safe layout and the host-side space agree with NumPy's own."""
    flat = np.random.default_rng(0).integers(0, paper.size, 1000)
    idx = np.asarray(jax.jit(paper.layout.unravel)(flat))
    np.testing.assert_array_equal(idx, np.stack(np.unravel_index(flat, paper.shape), -1))
    np.testing.assert_array_equal(paper.unravel(flat), idx)
    np.testing.assert_array_equal(np.asarray(jax.jit(paper.layout.ravel)(idx)), flat)
    np.testing.assert_array_equal(paper.ravel(idx), flat)


def test_decode_matches_indexing_batched_and_unbatched(paper):
    idx = np.array([[3, 1, 24, 2, 9], [0, 0, 0, 0, 0]])
    dec = jax.jit(paper.layout.decode)(idx, paper.table_array)
    host = paper.decode(idx)
    for name in paper.names:
        np.testing.assert_array_equal(np.asarray(dec[name]), host[name])
    for p, name in enumerate(paper.names):
        np.testing.assert_array_equal(np.asarray(dec[name]), paper.values[p][idx[:, p]])
    one = paper.decode(idx[0])
    assert {k: float(v) for k, v in one.items()} == {k: float(v[0]) for k, v in dec.items()}


@pytest.mark.parametrize("idx, needle", [
    ([10, 0, 0, 0, 0], "index 10 of ego_offset is outside 0..9"),
    ([-1, 0, 0, 0, 0], "index -1 of ego_offset is outside 0..9"),
    ([[0, 0, 0, 0, 0], [0, 0, 25, 0, 0]], "index 25 of ped_speed is outside 0..24"),
    ([1, 2, 3], "have 5 entries"),
    ([1.5, 0, 0, 0, 0], "whole numbers"),
])
def test_host_decode_refuses_indices_outside_the_table(paper, idx, needle):
    """Host-side decoding checks each index against its parameter's value count (the table's
    padding or NumPy's wrap-around would otherwise return a wrong value silently)."""
    assert paper.shape[0] == 10 and paper.shape[2] == 25
    for f in (paper.decode, paper.ravel):
        with pytest.raises(ValueError, match=re.escape(needle)):
            f(idx)
    # the last valid index of every parameter decodes to its largest table entry
    last = np.asarray(paper.shape) - 1
    assert [float(paper.decode(last)[n]) for n in paper.names] == \
        [float(np.float32(v[-1])) for v in paper.values]


def test_enumeration_in_chunks_covers_space_once(paper):
    spans = list(paper.chunks(30_000))
    assert spans[0] == (0, 30_000) and spans[-1] == (90_000, 100_000)
    assert sum(e - b for b, e in spans) == paper.size


def test_bounds_and_nearest(paper):
    lo, hi = paper.bounds
    np.testing.assert_array_equal(lo, 0)
    np.testing.assert_array_equal(hi, np.array(paper.shape) - 1)
    idx = np.array([4, 7, 11, 1, 3])
    vals = {k: float(v) for k, v in paper.decode(idx).items()}
    back = paper.decode(paper.nearest(vals))  # duplicate draws may map to the first copy
    assert {k: float(v) for k, v in back.items()} == vals


def test_toml_space(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text("""
name = "mine"
[parameters.ego_offset]
distribution = "uniform"
low = 2
high = 6
samples = 3
[parameters.ped_speed]
values = [1.0, 1.5]
[parameters.weather]
distribution = "integers"
low = 0
high = 14
samples = 2
""")
    sp = jf.load_space(f, seed=5)
    assert sp.name == "mine" and sp.shape == (3, 2, 2) and sp.size == 12
    sc = sp.scenario(np.zeros(3, np.int32))
    assert float(sc["ped_offset"]) == 3.5  # undeclared -> default
    # the written description rebuilds the same space
    assert space_from_dict(sp.describe(), seed=5).table == sp.table


BAD = [
    ({"parameters": {"ego_speed": {"values": [1]}}}, "ego_speed"),
    ({"parameters": {"ped_speed": {"distribution": "gamma", "low": 0, "high": 1,
                                   "samples": 2}}}, "gamma"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": 2, "high": 1,
                                   "samples": 2}}}, "inverted"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": 1, "high": 1,
                                   "samples": 2}}}, "empty or inverted"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": 0, "high": 1,
                                   "samples": 0}}}, "samples"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": 0, "high": 1,
                                   "samples": -3}}}, "samples"),
    ({"parameters": {"ped_speed": {"distribution": "normal", "mean": float("nan"), "sd": 1,
                                   "samples": 2}}}, "not finite"),
    ({"parameters": {"ped_speed": {"distribution": "normal", "mean": 1.4, "sd": 0,
                                   "samples": 2}}}, "sd"),
    ({"parameters": {"ped_speed": {"values": []}}}, "empty"),
    ({"parameters": {"ped_speed": {"values": [1, 1]}}}, "duplicates"),
    ({"parameters": {"ped_speed": {"values": [1, "x"]}}}, "'x'"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": 0, "samples": 2}}},
     "parameters.ped_speed.high"),
    ({"parameters": {"ped_speed": {"values": [1], "colour": "red"}}}, "colour"),
    ({"parameters": {"ped_speed": {"values": [9.0]}}}, "outside"),
    ({"parameters": {"weather": {"values": [1.5]}}}, "integers"),
    ({"parameters": {"weather": {"distribution": "integers", "low": 0, "high": 3,
                                 "samples": 5}}}, "exceeds"),
    ({"parameters": {"ped_speed": {"unit": "km/h", "values": [1]}}}, "km/h"),
    ({"parameters": {"weather": {"distribution": "integers", "low": 3, "high": 2,
                                 "samples": 1}}}, "empty or inverted"),
    ({"parameters": {"weather": {"distribution": "integers", "low": 0, "high": 3,
                                 "samples": 2, "decimals": 2}}}, "decimals applies"),
    ({"parameters": {"ped_speed": {"values": [1.0], "decimals": 2}}}, "decimals applies"),
    ({"parameters": {"ped_speed": {"values": [1e39]}}}, "not finite in float32"),
    ({"parameters": {"ped_speed": {"values": [1.0, 1e39]}}}, "ped_speed.values[1]: 1e+39"),
    ({"parameters": {"ped_speed": {"distribution": "uniform", "low": "1", "high": 2,
                                   "samples": 2}}}, "parameters.ped_speed.low: '1' is not"),
    ({"parameters": {"ped_speed": {"distribution": "normal", "mean": 1.4, "sd": True,
                                   "samples": 2}}}, "parameters.ped_speed.sd: True is not"),
    ({"parameters": {"ped_speed": {"distribution": "values", "low": 1.0, "high": 2.0,
                                   "samples": 2}}}, "parameters.ped_speed.values is missing"),
    ({"parameters": {"ped\nspeed": {"values": [1.0]}}}, "'ped\\nspeed' is not a parameter"),
    ({"parameters": {}}, "parameters"),
    ({"params": {}}, "params"),
]


def test_an_integer_range_of_one_value():
    sp = space_from_dict({"parameters": {"weather": {"distribution": "integers", "low": 3,
                                                     "high": 3, "samples": 1}}})
    assert sp.shape == (1,) and sp.table == ((3.0,),)


@pytest.mark.parametrize("doc, needle", BAD)
def test_bad_space_gives_one_line_error_naming_the_key(doc, needle):
    with pytest.raises(ValueError) as e:
        space_from_dict(doc)
    msg = str(e.value)
    assert needle in msg and "\n" not in msg


def test_malformed_toml_and_unknown_names(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[parameters.ped_speed\nvalues = [1]")
    with pytest.raises(ValueError, match="malformed TOML"):
        jf.load_space(f)
    with pytest.raises(ValueError, match="unknown space 'nope'"):
        jf.load_space("nope")
    with pytest.raises(ValueError, match="seed"):
        jf.load_space("paper", seed=-1)


def test_a_valid_space_file_with_megabytes_of_comments_loads(tmp_path):
    """Comments count towards no limit a person would reach: 10 MB of them before a valid
    space (oracle: the same space without the comments); a file over the 64 MiB guard is
    refused in one line naming it."""
    from jaxfalsify.scenario.space import load_space

    body = ('name = "c"\n[parameters.ego_offset]\ndistribution = "integers"\nlow = 1\n'
            'high = 5\nsamples = 5\n')
    plain = tmp_path / "plain.toml"
    plain.write_text(body)
    commented = tmp_path / "commented.toml"
    commented.write_text(("# " + "x" * 98 + "\n") * 100_000 + body)
    assert commented.stat().st_size > 10_000_000
    assert load_space(str(commented)).values[0].tolist() == \
        load_space(str(plain)).values[0].tolist()
    huge = tmp_path / "huge.toml"
    with open(huge, "wb") as f:
        f.truncate((64 << 20) + 1)
    with pytest.raises(ValueError, match=r"huge.toml: larger than 64 MiB"):
        load_space(str(huge))
