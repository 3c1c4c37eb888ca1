"""Exhaustive sweep and the command line: files, schema, determinism (bad input is in
test_bad_input.py)."""

import json
import os
import tomllib

import jax
import numpy as np
import pyarrow.parquet as pq
import pytest
from conftest import space_file_fixture

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.engine.sweep_chunks import iter_sweep
from jaxfalsify.engine.sweep_config import SweepConfig, calibrations
from jaxfalsify.engine.sweep_totals import Reducer, fold
from jaxfalsify.engine.truth import sweep_arrays
from jaxfalsify.suts import registry as sut_lib

SMALL = """
name = "small"
[parameters.ego_offset]
values = [7, 8, 9]
[parameters.ped_accel]
values = [0.007, 0.076]
[parameters.ped_speed]
distribution = "normal"
mean = 1.46
sd = 0.24
samples = 5
[parameters.ped_offset]
values = [3.5, 4.0]
[parameters.weather]
values = [0, 8]
"""


small_space = space_file_fixture(SMALL, "small")


def test_sweep_arrays_equal_direct_evaluation(small_space):
    sp = jf.load_space(small_space)
    rows = sweep_arrays(sp, chunk=7)  # several chunks, a padded last one
    assert len(rows["scenario"]) == sp.size == 120
    idx = np.stack(np.unravel_index(np.arange(sp.size), sp.shape), -1)
    direct = jf.evaluate(sp.scenario(idx))
    np.testing.assert_array_equal(rows["reward"], np.asarray(direct.reward))
    np.testing.assert_array_equal(rows["collision"], np.asarray(direct.collision))
    for f in ("min_distance", "final_distance", "robustness", "min_ttc"):  # to 4 ulp (README)
        a, b = rows[f], np.asarray(getattr(direct, f))
        fin = np.isfinite(b)
        np.testing.assert_array_equal(np.isfinite(a), fin, err_msg=f)
        np.testing.assert_array_max_ulp(a[fin], b[fin], maxulp=4)
    for p, name in enumerate(sp.names):
        np.testing.assert_array_equal(rows[f"{name}_idx"], idx[:, p])
    # chunk size does not change a single bit
    other = sweep_arrays(sp, chunk=64)
    for k in rows:
        np.testing.assert_array_equal(rows[k], other[k], err_msg=k)


def test_cli_sweep_writes_parquet_summary_config(small_space, tmp_path, capsys):
    out = tmp_path / "sw"
    assert main(["sweep", "--space", str(small_space), "--out", str(out), "--quiet",
                 "--chunk", "50"]) == 0
    table = pq.read_table(out / "sweep.parquet").to_pydict()
    sp = jf.load_space(small_space)
    assert len(table["scenario"]) == sp.size
    assert table["scenario"] == list(range(sp.size))
    expected = sweep_arrays(sp)
    np.testing.assert_array_equal(np.asarray(table["reward"], np.float32), expected["reward"])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["n_scenarios"] == sp.size
    assert summary["n_collisions"] == int(expected["collision"].sum())
    assert summary["collision_rate"] == pytest.approx(expected["collision"].mean())
    r = np.where(np.isnan(expected["reward"]), -np.inf, expected["reward"])
    assert summary["global_max_reward"] == pytest.approx(float(r.max()))
    best = summary["global_max_scenario"]
    assert best["scenario"] == int(np.argmax(r))
    assert summary["global_max_ties"] == int(np.sum(r == r.max()))
    assert "jax" in summary["versions"]
    assert json.loads((out / "timing.json").read_text())["total_seconds"] > 0
    config = tomllib.loads((out / "config.toml").read_text())
    assert config["sut"] == "carla-tm" and config["space"]["name"] == "small"
    assert config["kind"] == "sweep"
    assert [p for p in os.listdir(out) if p.startswith(".")] == [".lock"]  # no temporary leftovers
    # a second sweep into the same folder is refused, --force overwrites
    mtime = (out / "sweep.parquet").stat().st_mtime_ns
    assert main(["sweep", "--space", str(small_space), "--out", str(out), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err
    assert (out / "sweep.parquet").stat().st_mtime_ns == mtime
    assert main(["sweep", "--space", str(small_space), "--out", str(out), "--quiet",
                 "--force"]) == 0


def test_cli_simulate_prints_outcome(capsys):
    assert main(["simulate", "ego_offset=9", "ped_accel=0.007", "ped_speed=1.237",
                 "ped_offset=3.5", "weather=8"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["outcome"]["collision"] is True and out["outcome"]["reward"] > 0.25
    assert out["scenario"]["ego_offset"] == 9 and out["scenario"]["ped_change_step"] == 0.0


def test_cli_simulate_takes_values_after_options_and_sut_values(capsys):
    """NAME=VALUE after the options, and ``sut.NAME=VALUE``, give what ``jf.evaluate``
    gives with that SUT parameter (the scenario's own outcome, not the default calibration's)."""
    assert main(["simulate", "ego_offset=30", "--sut", "sensor-aeb", "ped_speed=1.5",
                 "sut.ttc_full=0.4"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scenario"]["ego_offset"] == 30 and out["scenario"]["ped_speed"] == 1.5
    assert np.isclose(out["sut_params"]["ttc_full"], 0.4)
    sut, params = jf.suts.registry.make("sensor-aeb", ttc_full=0.4)
    want = jf.evaluate({"ego_offset": 30.0, "ped_speed": 1.5}, sut=sut, sut_params=params)
    assert np.isclose(out["outcome"]["min_distance"], float(want.min_distance))
    default = jf.evaluate({"ego_offset": 30.0, "ped_speed": 1.5}, sut="sensor-aeb")
    assert out["outcome"]["min_distance"] != float(default.min_distance)
    # the library call behind the command gives the same document
    from jaxfalsify.core.sim import describe
    lib = describe({"ego_offset": 30, "ped_speed": 1.5}, sut="sensor-aeb",
                   sut_params={"ttc_full": 0.4})
    assert json.loads(json.dumps(lib)) == out and lib["defaults_used"] == sorted(
        set(lib["scenario"]) - {"ego_offset", "ped_speed"})


def test_calibration_sweep_equals_separate_sweeps(small_space, tmp_path, capsys):
    """``--sut-param NAME=V1,V2`` evaluates calibrations x scenarios in one compiled call;
    each calibration's rows equal a separate sweep with that value."""
    out = tmp_path / "cal"
    assert main(["sweep", "--space", str(small_space), "--sut-param", "full_brake=3.1,8",
                 "--sut-param", "walker_time=1.5", "--out", str(out), "--quiet"]) == 0
    table = pq.read_table(out / "sweep.parquet").to_pydict()
    summary = json.loads((out / "summary.json").read_text())
    sp = jf.load_space(str(small_space))
    assert summary["n_calibrations"] == 2 and len(table["scenario"]) == 2 * sp.size
    for c, brake in enumerate((3.1, 8.0)):
        mine = np.asarray(table["calibration"]) == c
        # the value as given (float64), not its float32 rounding 3.0999999
        assert np.all(np.asarray(table["full_brake"], np.float64)[mine] == brake)
        assert summary["calibrations"][c]["full_brake"] == brake
        every = summary["calibrations"][c]["sut_params"]  # every parameter, fixed ones too
        assert (every["full_brake"], every["walker_time"]) == (brake, 1.5)
        alone = sweep_arrays(sp, "carla-tm", {"full_brake": brake, "walker_time": 1.5})
        got = np.asarray(table["scenario"])[mine]
        np.testing.assert_array_equal(got, np.arange(sp.size))
        for f in ("reward", "collision", "min_distance", "steps"):
            np.testing.assert_array_equal(np.asarray(table[f])[mine], alone[f], err_msg=f)
        assert summary["calibrations"][c]["n_collisions"] == int(alone["collision"].sum())
    # config.toml holds every SUT parameter: the defaults, the given value and the list
    import tomllib

    from jaxfalsify.suts import registry as sut_lib
    recorded = tomllib.loads((out / "config.toml").read_text())["sut_params"]
    defaults = sut_lib.params_dict(sut_lib.resolve("carla-tm").default_params)
    assert recorded == {**defaults, "full_brake": [3.1, 8], "walker_time": 1.5}
    # the weaker brake must matter somewhere, or the test proves nothing
    assert summary["calibrations"][0]["n_collisions"] != summary["calibrations"][1]["n_collisions"]
    # the closing lines (sweep.summary_lines) name each calibration by its swept value
    printed = capsys.readouterr().out.splitlines()
    for c, brake in enumerate(("3.1", "8")):
        n = summary["calibrations"][c]["n_collisions"]
        assert printed[c].startswith(f"calibration full_brake={brake}: {sp.size:,} scenarios, "
                                     f"{n:,} collisions")
    assert printed[-1].startswith(f"wrote {out}/sweep.parquet")


def test_summary_only_sweep_reduces_on_device_like_rows(small_space, tmp_path, monkeypatch):
    """``--rows none`` reduces each chunk on the device; the totals (counts, global maximum,
    its ties, the best scenario's every field, per calibration) equal those folded from the
    rows, over several chunks (the maximum's ties spread over them) and a padded last one."""
    sp, calib = jf.load_space(small_space), calibrations(sut_lib.resolve("carla-tm"),
                                                         {"full_brake": [3.0, 8.0]})
    from_rows, reduced = [Reducer() for _ in range(2)], [Reducer() for _ in range(2)]
    for reds, on_device in ((from_rows, False), (reduced, True)):
        for b, e, cols in iter_sweep(sp, calib, planned=32, reduced=on_device):
            fold(reds, sp, calib, b, e, cols, on_device)
    as_text = lambda reds: json.dumps([r.state() for r in reds])  # noqa: E731 - NaN == NaN
    assert as_text(reduced) == as_text(from_rows)
    assert from_rows[0].best_ties > 1 and from_rows[0].collisions != from_rows[1].collisions
    # a range ending inside a chunk (a process's share): rows past it are other scenarios
    (_, _, res), = iter_sweep(sp, calib, stop=1, planned=32, reduced=True)
    (_, _, cols), = iter_sweep(sp, calib, stop=1, planned=32)
    np.testing.assert_array_equal(res["top"], cols["reward"])
    np.testing.assert_array_equal(res["ties"], [1, 1])
    assert from_rows[0].best_reward > cols["reward"][0]  # the mask matters here
    # the command: no rows written, the summary from the device-side totals
    out = tmp_path / "none"
    assert main(["sweep", "--space", str(small_space), "--sut-param", "full_brake=3,8",
                 "--rows", "none", "--out", str(out), "--quiet"]) == 0
    assert not (out / "sweep.parquet").exists()
    summary = json.loads((out / "summary.json").read_text())
    for c, red in enumerate(from_rows):
        got = summary["calibrations"][c]
        assert (got["n_collisions"], got["global_max_ties"]) == (red.collisions, red.best_ties)
        assert got["global_max_reward"] == red.best_reward
        assert got["global_max_scenario"]["scenario"] == red.best_row["scenario"]
    # the chunk resolved for this backend is recorded (2^17 on CPUs; 2^20 on accelerators)
    assert tomllib.loads((out / "config.toml").read_text())["chunk"] == (
        131072 if jax.default_backend() == "cpu" else 1048576)
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert SweepConfig().chunk is None  # chosen by execute, after a distributed start-up
    assert SweepConfig().resolved().chunk == jf.core.sim.default_chunk() == 1048576


def test_chunks_never_exceed_the_chunk_given():
    """``--chunk N`` bounds the scenarios per compiled call (memory): balanced chunks of at
    most N, aligned to 256 rows where N allows, covering the space in the fewest such chunks."""
    import itertools
    import math

    from jaxfalsify.engine.sweep_chunks import plan_chunks

    for size, chunk in itertools.product((1, 7, 255, 1000, 60_000, 100_000, 1_000_003),
                                         (1, 3, 100, 256, 1024, 20_000, 131_072)):
        c = plan_chunks(size, chunk)
        assert 1 <= c <= max(chunk, 1), (size, chunk, c)
        if chunk >= 256:
            assert c % 256 == 0, (size, chunk, c)
            assert math.ceil(size / c) == math.ceil(size / (chunk // 256 * 256)), (size, chunk)


def test_default_folder_keeps_the_whole_space_name():
    """``exp.v1`` and ``exp.v2`` sweep into folders of their own (the name was cut at its
    last dot, so the second found the first's results)."""
    from jaxfalsify.engine.sweep_config import default_out
    from jaxfalsify.scenario.space import space_from_dict

    doc = {"parameters": {"ped_speed": {"values": [1.0, 2.0]}}}
    names = [default_out(space_from_dict({**doc, "name": n}), "carla-tm", 0).name
             for n in ("exp.v1", "exp.v2")]
    assert names == ["exp.v1-carla-tm-s0", "exp.v2-carla-tm-s0"]
