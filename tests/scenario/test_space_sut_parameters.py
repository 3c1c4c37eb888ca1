"""Spaces, calibration sweeps and their configs: calibration order on resume, rounding inside
the declared range, NumPy SUT parameters in config.toml, a space's SUT parameters against the
SUT's ranges, and one-line errors for malformed parameter tables."""

import json
import math
import tomllib

import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import space_file_fixture

import jaxfalsify as jf
from jaxfalsify.base import config as cfg
from jaxfalsify.cli import main
from jaxfalsify.core import sim
from jaxfalsify.engine import problem, sweep_config, truth
from jaxfalsify.io import checkpoints
from jaxfalsify.jobs import runs, sweep
from jaxfalsify.scenario import space
from jaxfalsify.suts import registry as sut_lib

# 3 x 25 x 4 x 2 = 600 scenarios: three chunks of at most 256 (x 4 calibrations per call)
SPACE = """
name = "fix"
[parameters.ego_offset]
values = [7, 8, 9]
[parameters.ped_speed]
distribution = "normal"
mean = 1.46
sd = 0.3
samples = 25
[parameters.ped_offset]
values = [3.0, 3.5, 4.0, 4.5]
[parameters.weather]
values = [0, 8]
"""


fix_space = space_file_fixture(SPACE, "fix")


def _rows(path):
    return {k: np.asarray(v) for k, v in pq.read_table(path).to_pydict().items()}


def _interrupted_then_resumed(config, out, after_chunks=1):
    calls = iter(range(1, 10**6))
    with pytest.raises(runs.Interrupted):
        sweep.execute(config, out, stop=lambda: next(calls) >= after_chunks)
    assert json.loads((out / "status.json").read_text())["state"] == "interrupted"
    again, _ = sweep.resume_config(out)
    return sweep.execute(again, out, resume=True)


def _summary(out):
    s = json.loads((out / "summary.json").read_text())
    s.pop("versions")
    return s


# --- 1. calibrations in one canonical order, at start and on resume
@pytest.mark.parametrize("rows", ["none", "all"])
def test_resume_with_sut_params_in_non_declared_order_equals_uninterrupted(fix_space, tmp_path,
                                                                           rows):
    """Two swept SUT parameters given in an order other than the SUT's (sensor-aeb declares
    latency before ttc_full): the resumed sweep's config.toml lists them in declared order,
    and the calibrations keep their numbers, so interrupted + resumed == uninterrupted."""
    names = sut_lib.param_names(sut_lib.resolve("sensor-aeb"))
    assert names.index("ttc_full") > names.index("latency")  # the order given differs
    given = {"ttc_full": [0.8, 1.2], "latency": [0.1, 0.3]}
    conf = sweep_config.SweepConfig(space=str(fix_space), sut="sensor-aeb", sut_params=given,
                                    chunk=1024, rows=rows)
    whole, part = tmp_path / "whole", tmp_path / "part"
    sweep.execute(conf, whole)
    res = _interrupted_then_resumed(conf, part)
    assert res["resumed_from_scenario"] > 0  # it did resume from a checkpoint
    a, b = _summary(part), _summary(whole)
    assert a == b
    # each calibration's totals are those of a sweep of that calibration alone (independent)
    sp = jf.load_space(fix_space)
    seen = set()
    for c in b["calibrations"]:
        alone = truth.sweep_arrays(sp, "sensor-aeb", {"ttc_full": c["ttc_full"],
                                                      "latency": c["latency"]})
        assert c["n_collisions"] == int(alone["collision"].sum())
        r = np.where(np.isnan(alone["reward"]), -np.inf, alone["reward"])
        assert c["global_max_reward"] == pytest.approx(float(r.max()))
        seen.add((c["ttc_full"], c["latency"]))
    assert seen == {(t, lat) for t in (0.8, 1.2) for lat in (0.1, 0.3)}
    assert len({c["n_collisions"] for c in b["calibrations"]}) > 1  # the calibrations matter
    if rows == "all":
        x, y = _rows(part / "sweep.parquet"), _rows(whole / "sweep.parquet")
        assert list(x) == list(y)
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)
        for c in b["calibrations"]:  # the rows labelled c carry c's values
            mine = x["calibration"] == c["calibration"]
            assert np.all(x["ttc_full"][mine] == c["ttc_full"])
            assert np.all(x["latency"][mine] == c["latency"])
            assert int(x["collision"][mine].sum()) == c["n_collisions"]


def test_calibration_order_does_not_depend_on_the_order_given():
    s = sut_lib.resolve("sensor-aeb")
    a = sweep_config.calibrations(s, {"ttc_full": [0.8, 1.2], "latency": [0.1, 0.3]})
    b = sweep_config.calibrations(s, {"latency": [0.1, 0.3], "ttc_full": [0.8, 1.2]})
    assert a.instances == b.instances and a.swept == b.swept
    # C order over the declared order: the last declared (ttc_full) fastest
    order = [(sut_lib.params_dict(p)["latency"], sut_lib.params_dict(p)["ttc_full"])
             for p in a.instances]
    assert order == sorted(order)


def test_resume_refuses_a_checkpoint_of_other_calibrations(fix_space, tmp_path, monkeypatch):
    """The calibration list is part of the checkpoint's fingerprint: calibrations numbered
    otherwise on resume are refused, nothing mixed."""
    conf = sweep_config.SweepConfig(space=str(fix_space), sut="sensor-aeb",
                                    sut_params={"ttc_full": [0.8, 1.2], "latency": [0.1, 0.3]},
                                    chunk=1024, rows="none")
    out = tmp_path / "ck"
    calls = iter(range(1, 10**6))
    with pytest.raises(runs.Interrupted):
        sweep.execute(conf, out, stop=lambda: next(calls) >= 1)
    state = (out / "checkpoint" / "state.json").read_text()
    real = sweep_config.calibrations

    def reversed_calibrations(s, params):
        c = real(s, params)
        return sweep_config.Calibrations(c.sut, c.instances[::-1], c.swept)

    monkeypatch.setattr(sweep_config, "calibrations", reversed_calibrations)
    again, _ = sweep.resume_config(out)
    with pytest.raises(checkpoints.CheckpointError):
        sweep.execute(again, out, resume=True)
    assert (out / "checkpoint" / "state.json").read_text() == state


# --- 2. rounding keeps uniform draws inside [low, high]
def _grid(low, high, d):
    """Independent: the floats k / 10**d (correctly rounded, as np.round gives them) in
    [low, high], by enumeration."""
    ks = range(math.floor(low * 10**d) - 2, math.ceil(high * 10**d) + 3)
    return {k / 10**d for k in ks if low <= k / 10**d <= high}


def test_rounded_uniform_draws_stay_in_range_or_are_refused():
    rng = np.random.default_rng(7)
    refused = kept = 0
    for case in range(800):
        d = int(rng.integers(0, 5))
        low = round(float(rng.uniform(0, 15)), int(rng.integers(0, 6)))
        high = round(low + float(rng.uniform(0, 3)) * 10.0**-d, int(rng.integers(0, 7)))
        if not low < high:
            continue
        grid = _grid(low, high, d)
        try:
            p = space.uniform("ped_offset", low, high, 20, d)
        except ValueError as e:
            assert not grid, (low, high, d)
            msg = str(e)
            assert "\n" not in msg and "parameters.ped_offset" in msg
            refused += 1
            continue
        assert grid, (low, high, d)
        vals = p.discretise(case)
        assert np.all((vals >= low) & (vals <= high)), (low, high, d, vals)
        assert set(vals.tolist()) <= grid, (low, high, d, vals)
        kept += 1
    assert refused > 10 and kept > 10  # both branches exercised


def test_rounding_that_would_leave_the_range_is_refused_in_the_toml(tmp_path, capsys):
    f = tmp_path / "round.toml"
    f.write_text('[parameters.ped_offset]\ndistribution = "uniform"\nlow = 3.2\nhigh = 3.4\n'
                 'samples = 4\ndecimals = 0\n')
    assert not _grid(3.2, 3.4, 0)
    with pytest.raises(ValueError, match=r"parameters\.ped_offset: no multiple of 1"):
        jf.load_space(f)
    out = tmp_path / "out"
    assert main(["sweep", "--space", str(f), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ped_offset" in err and not out.exists()
    # the paper's space is unchanged: its grid ends are the range's ends
    p = space.uniform("ped_accel", 0.0, 0.1, 10)
    rng = np.random.default_rng([0, __import__("zlib").crc32(b"ped_accel")])
    np.testing.assert_array_equal(p.discretise(0), np.sort(np.round(rng.uniform(0, 0.1, 10), 3)))


# --- 3. NumPy SUT parameters through the Python API
def test_numpy_sut_params_write_a_resumable_config(fix_space, tmp_path):
    given = {"ttc_full": np.array([0.8, 1.2]), "latency": [np.float64(0.1), np.float64(0.3)],
             "fov": np.float64(50.0), "ttc_partial": np.float32(1.7)}
    plain = {"ttc_full": [0.8, 1.2], "latency": [0.1, 0.3], "fov": 50.0, "ttc_partial": 1.7}
    ref, out = tmp_path / "ref", tmp_path / "np"
    sweep.execute(sweep_config.SweepConfig(space=str(fix_space), sut="sensor-aeb",
                                           sut_params=plain, chunk=1024, rows="none"), ref)
    conf = sweep_config.SweepConfig(space=str(fix_space), sut="sensor-aeb", sut_params=given,
                                    chunk=1024, rows="none")
    _interrupted_then_resumed(conf, out)
    recorded = tomllib.loads((out / "config.toml").read_text())["sut_params"]
    assert recorded == tomllib.loads((ref / "config.toml").read_text())["sut_params"]
    assert (recorded["ttc_full"], recorded["fov"], recorded["ttc_partial"]) == \
        ([0.8, 1.2], 50.0, 1.7)
    assert _summary(out) == _summary(ref)


def test_toml_writer_takes_numpy_values_and_names_a_bad_key():
    doc = {"sut_params": {"a": np.float64(1.2), "b": np.int64(3), "c": np.array([0.5, 2.0]),
                          "d": np.float32(0.1), "e": np.bool_(True), "f": np.array(4.0)}}
    back = tomllib.loads(cfg.dumps_toml(doc))["sut_params"]
    assert back == {"a": 1.2, "b": 3, "c": [0.5, 2.0], "d": 0.1, "e": True, "f": 4.0}
    with pytest.raises(ValueError, match=r"^sut_params\.x: cannot write object"):
        cfg.dumps_toml({"sut_params": {"x": object()}})


# --- 4. a space's SUT parameters within the SUT's ranges
def test_space_sut_parameters_outside_the_sut_ranges_are_refused(tmp_path, capsys):
    f = tmp_path / "neg.toml"
    f.write_text("[parameters.ego_offset]\nvalues = [5.0, 10.0]\n"
                 "[parameters.sut.ttc_full]\nvalues = [-5.0, 1.0]\n")
    # independent: the same value as --sut-param / sut_params is refused
    with pytest.raises(ValueError):
        sut_lib.with_params(sut_lib.resolve("sensor-aeb"), {"ttc_full": -5.0})
    for cmd in (["sweep"], ["run", "--evaluations", "8", "--no-figures"]):
        out = tmp_path / cmd[0]
        assert main(cmd + ["--space", str(f), "--sut", "sensor-aeb", "--out", str(out),
                           "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1, err
        assert "sut.ttc_full" in err and "-5" in err and not out.exists()
    with pytest.raises(ValueError, match="sut.ttc_full"):
        sweep.execute(sweep_config.SweepConfig(space=str(f), sut="sensor-aeb"), tmp_path / "lib")
    assert not (tmp_path / "lib").exists()
    # values inside the ranges (a closed bound included) pass
    s = sut_lib.resolve("sensor-aeb")
    ok = space.space_from_dict({"parameters": {"sut": {"ttc_full": {"values": [0.0, 1.0]},
                                                       "fov": {"values": [10.0, 360.0]}}}})
    problem.check_space_sut(ok, s)
    bad = space.space_from_dict({"parameters": {"sut": {"fov": {"values": [10.0, 360.5]}}}})
    with pytest.raises(ValueError, match=r"sut\.fov.*360\.5"):
        problem.check_space_sut(bad, s)


# --- 5. distribution must be a string
@pytest.mark.parametrize("dist", ['["uniform"]', '{ kind = "uniform" }', "3"])
def test_distribution_not_a_string_is_one_line(tmp_path, capsys, dist):
    f = tmp_path / "d.toml"
    f.write_text(f"[parameters.ped_speed]\ndistribution = {dist}\nlow = 1.0\nhigh = 2.0\n"
                 "samples = 3\n")
    out = tmp_path / "out"
    assert main(["sweep", "--space", str(f), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert "parameters.ped_speed.distribution: must be a string" in err
    assert not out.exists()


# --- 6. explicit values tables checked like the others
@pytest.mark.parametrize("extra,key", [("low = 3.0", "low"), ("high = 3.0", "high"),
                                       ("mean = 1.0", "mean"), ("sd = 0.1", "sd"),
                                       ("samples = 2.0", "samples"),
                                       ("samples = true", "samples"),
                                       ("samples = 0", "samples"),
                                       ("samples = 3", "samples")])
def test_values_tables_refuse_what_does_not_apply(extra, key):
    doc = tomllib.loads(f"[parameters.ped_speed]\nvalues = [1.0, 2.0]\n{extra}\n")
    with pytest.raises(ValueError) as e:
        space.space_from_dict(doc)
    assert str(e.value).startswith(f"parameters.ped_speed.{key}") and "\n" not in str(e.value)


def test_values_tables_accept_a_matching_sample_count_and_a_string_description():
    doc = tomllib.loads('description = "mine"\n[parameters.ped_speed]\nvalues = [1.0, 2.0]\n'
                        "samples = 2\n")
    assert space.space_from_dict(doc).table == ((1.0, 2.0),)
    for bad in ("3", "[\"a\"]", "{ a = 1 }"):
        doc = tomllib.loads(f"description = {bad}\n[parameters.ped_speed]\nvalues = [1.0]\n")
        with pytest.raises(ValueError, match="^description must be a string"):
            space.space_from_dict(doc)


# --- 7. --sut-param values that coincide in float32
def test_sut_param_values_equal_in_float32_are_refused(tmp_path, capsys):
    a, b = 0.1, 0.10000000001
    assert a != b and np.float32(a) == np.float32(b)  # the premise, independently
    with pytest.raises(ValueError):  # a space's values are refused alike
        space.space_from_dict({"parameters": {"sut": {"ttc_full": {"values": [a, b]}}}})
    with pytest.raises(ValueError, match=r"sut_params\.ttc_full.*float32"):
        sweep_config.calibrations(sut_lib.resolve("sensor-aeb"), {"ttc_full": [a, b]})
    out = tmp_path / "out"
    assert main(["sweep", "--sut", "sensor-aeb", "--sut-param", f"ttc_full={a},{b}",
                 "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "ttc_full" in err and not out.exists()
    # distinct in float32: accepted
    c = 0.1000001
    assert np.float32(a) != np.float32(c)
    assert sweep_config.calibrations(sut_lib.resolve("sensor-aeb"), {"ttc_full": [a, c]}).count == 2


def test_too_many_calibrations_refused_before_building_them():
    params = {n: [1.0 + i / 10 for i in range(10)] for n in ("kp", "ki", "kd", "range", "fov")}
    with pytest.raises(ValueError, match="100000 calibrations"):
        sweep_config.calibrations(sut_lib.resolve("sensor-aeb"), params)


# --- 8. ped_offset's doc says what the simulator does
def test_ped_offset_doc_matches_the_start_position():
    doc = space.KNOWN_PARAMETERS["ped_offset"]["doc"]
    w = sim.WORLD
    # the walker starts ped_offset + 1 m from its base point, walker_base inside the kerb
    for off in (0.0, 3.0, 3.5, 4.5):
        _, y = sim.start_positions(0.0, off)
        assert y == pytest.approx(w.road_right + w.walker_base - (off + 1.0))
    assert sim.start_positions(0.0, 3.5)[1] == pytest.approx(w.road_right)  # at the kerb
    assert "ped_offset + 1" in doc and f"{w.walker_base:g} m" in doc and "3.5" in doc
    assert "minus 1 m" not in doc
