"""OpenSCENARIO export, controller mode, without a run: the pedestrian's speed profile written
as parameter expressions and speed events reproduces the simulator's (checked against a
closed-form oracle of the original's profile, against ``sim.ped_speed_profile`` and by
integrating the file's events into positions). The run-level checks (the exported parameters
reproduce the run's outcomes, the distributions list the space) are in
``test_run_folder_outputs.py``, which has a run."""

import functools
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from conftest import grid_run

DT = 0.1


# ------------------------------------------------------------------ oracle and interpreter
def oracle_profile(speed, accel, change=0.0, step=0, n_steps=300):
    """Per-step walking speed of the original code (pdf.py), written as its loop: ``s =
    speed - 5 * accel``; steps 0..5 at ``s``; then ``s += accel`` each step while it has not
    yet exceeded ``speed + 0.25`` (by more than 1e-4 of an increment); steps
    ``step..step+5`` walk at ``s + change`` without growing, whatever the change (0 holds
    the speed); never below 0.
    Returns (speeds, start, final s)."""
    start = speed - 5 * accel
    s = start
    out = []
    for k in range(n_steps):
        window = step <= k < step + 6
        if k >= 6 and not window and not s > speed + 0.25 + 1e-4 * accel:
            s += accel
        out.append(max(s + change if window else s, 0.0))
    if accel == 0:
        final = start
    else:
        final = start
        while not final > speed + 0.25 + 1e-4 * accel:
            final += accel
    return np.asarray(out), start, final


def declarations(root):
    return {p.attrib["name"]: float(p.attrib["value"])
            for p in root.find("ParameterDeclarations").findall("ParameterDeclaration")}


def _conditions(trigger):
    return [g.findall("Condition") for g in trigger.findall("ConditionGroup")]


def speed_events(root, params, maneuver="ped_speed_profile"):
    """``[(name, start time or None, kind, target, rate)]`` of a maneuver's speed events, start
    times resolved from their triggers (simulation time, parameter conditions, another
    event's end or standby state), as an OpenSCENARIO engine would."""
    from jaxfalsify.outputs.export import value_of

    man = next(m for m in root.iter("Maneuver") if m.attrib["name"] == maneuver)
    events = {}
    for ev in man.findall("Event"):
        dyn = ev.find(".//SpeedActionDynamics")
        events[ev.attrib["name"]] = dict(
            kind=dyn.attrib["dynamicsShape"], rate=value_of(dyn.attrib["value"], params),
            target=value_of(ev.find(".//AbsoluteTargetSpeed").attrib["value"], params),
            groups=_conditions(ev.find("StartTrigger")), start=None)
    rules = {"equalTo": lambda a, b: a == b, "notEqualTo": lambda a, b: a != b,
             "greaterThan": lambda a, b: a > b, "greaterOrEqual": lambda a, b: a >= b}

    def group_time(conds):
        """Earliest time all conditions of a group hold (None: never / not yet known)."""
        t, before = 0.0, math.inf
        for c in conds:
            delay = value_of(c.attrib["delay"], params)
            if (pc := c.find(".//ParameterCondition")) is not None:
                if not rules[pc.attrib["rule"]](params[pc.attrib["parameterRef"]],
                                                float(pc.attrib["value"])):
                    return None
            elif (sc := c.find(".//SimulationTimeCondition")) is not None:
                assert sc.attrib["rule"] == "greaterOrEqual"
                t = max(t, value_of(sc.attrib["value"], params) + delay)
            else:
                se = c.find(".//StoryboardElementStateCondition")
                other = events[se.attrib["storyboardElementRef"]]
                if se.attrib["state"] == "endTransition":  # step actions end at once
                    if other["start"] is None:
                        return None
                    t = max(t, other["start"] + delay)
                else:
                    assert se.attrib["state"] == "standbyState"
                    before = other["start"] if other["start"] is not None else math.inf
        return t if t < before else None

    for _ in range(len(events) + 1):  # resolve chains of dependencies
        for e in events.values():
            times = [x for g in e["groups"] if (x := group_time(g)) is not None]
            e["start"] = min(times) if times else None
    return [(n, e["start"], e["kind"], e["target"], e["rate"]) for n, e in events.items()]


def integrate(events, t_end, h=1e-3):
    """Speed and walked distance on a fine grid: each started event replaces the running
    speed action (a step sets the target; a linear one moves to it at its rate)."""
    started = sorted((e for e in events if e[1] is not None), key=lambda e: e[1])
    t = (np.arange(round(t_end / h)) + 0.5) * h  # midpoints: steps at grid points integrate exactly
    v = np.zeros_like(t)
    cur = 0.0
    for i, (name, t0, kind, target, rate) in enumerate(started):
        t1 = started[i + 1][1] if i + 1 < len(started) else math.inf
        seg = (t >= t0 - 1e-12) & (t < t1 - 1e-12)
        if kind == "step":
            v[seg] = cur = target
        else:
            ramp = cur + np.sign(target - cur) * rate * (t[seg] - t0)
            v[seg] = np.minimum(ramp, target) if target >= cur else np.maximum(ramp, target)
            cur = (min(cur + rate * (t1 - t0), target) if target >= cur
                   else max(cur - rate * (t1 - t0), target)) if t1 < math.inf else target
    pos = np.concatenate([[0.0], np.cumsum(v * h)])  # pos[i]: walked by t = i * h
    return t, v, pos


# ------------------------------------------------------------------ the library-level test
@functools.lru_cache(maxsize=None)
def schema(kind="xosc"):
    """The XSD, loaded once per test session (a few seconds each)."""
    import xmlschema

    from jaxfalsify.outputs.export import schema_path

    return xmlschema.XMLSchema(str(schema_path(kind)))


@pytest.fixture(scope="module")
def xsd():
    return schema()


CASES = [  # ped_speed, ped_accel, ped_speed_change, ped_change_step
    (1.237, 0.007, 0.0, 0.0),    # Table II challenging: a long ramp
    (1.808, 0.076, 0.0, 0.0),    # Table II non-challenging: a short one
    (1.46, 0.0, 0.0, 0.0),       # no increment: constant speed
    (1.2, 0.05, 0.0, 0.0),       # 0.25 / accel + 5 an integer: the tie the 1e-4 settles
    (0.3, 0.1, 0.0, 0.0),        # negative start speed: walks at 0 first
    (1.2, 0.01, -0.5, 20.0),     # window while the speed grows
    (1.2, 0.1, 0.75, 20.0),      # window after the growth
    (1.2, 0.02, 0.5, 3.0),       # window in the still phase (growth starts after it)
    (1.2, 0.02, 0.5, 0.0),       # window from step 0 (instead of the start speed)
    (1.46, 0.0, -0.75, 30.0),    # window without any increment
    (1.2, 0.03, 0.0, 20.0),      # a change of 0: the window holds the speed, growth paused
    (0.3, 0.1, -0.5, 8.0),       # window with clamped speeds
]


@pytest.mark.parametrize("speed, accel, change, step", CASES,
                         ids=[f"v{c[0]}-a{c[1]}-c{c[2]}-T{c[3]:g}" for c in CASES])
def test_exported_pedestrian_profile_equals_the_simulator(tmp_path, xsd, speed, accel, change,
                                                         step):
    import jaxfalsify as jf
    from jaxfalsify.core import sim
    from jaxfalsify.outputs import export

    sp = jf.load_space("paper-extended")
    values = {"ego_offset": "7", "ped_accel": f"{accel:g}", "ped_speed": f"{speed:g}",
              "ped_offset": "3.5", "weather": "8", "ped_speed_change": f"{change:g}",
              "ped_change_step": f"{step:g}"}
    req = export.ego_request("carla-tm", {}, jf.WORLD)
    f = export.write_controller_scenario(tmp_path / "s.xosc", "crossing.xodr", sp, values, req,
                                         jf.WORLD, "case")
    xsd.validate(str(f))
    root = ET.parse(f).getroot()
    params = declarations(root)
    assert {k: params[k] for k in values} == {k: float(v) for k, v in values.items()}

    # the independent oracle, and the simulator's own profile
    n = 300
    ref, start, final = oracle_profile(speed, accel, change, int(step), n)
    simv = np.asarray(sim.ped_speed_profile(np.arange(n, dtype=np.float32), np.float32(speed),
                                            np.float32(accel), np.float32(change),
                                            np.float32(step)))
    np.testing.assert_allclose(simv, ref, atol=2e-5)

    # start speed, acceleration and target speed in the file: the closed form
    ev = {e[0]: e for e in speed_events(root, params)}
    assert ev["ped_accelerates"][2] == "linear"
    assert ev["ped_accelerates"][4] == pytest.approx(accel / DT, abs=1e-12)
    assert ev["ped_accelerates"][3] == pytest.approx(final, abs=1e-9)
    if step > 0:
        assert ev["ped_start_speed"][1] == 0.0  # at the ego's start
        assert ev["ped_start_speed"][3] == pytest.approx(max(start, 0.0), abs=1e-12)
    assert ev["ped_speed_change"][1] == pytest.approx(step * DT)  # whatever the change
    assert ev["ped_speed_change"][3] == pytest.approx(ref[int(step)], abs=1e-9)
    assert ev["ped_speed_restore"][1] == pytest.approx((step + 6) * DT)

    # the walked distance at every step's end: the simulator's up to accel * dt / 8 (the
    # ramp runs through each step's mean speed), plus one step's clamping at zero speed
    t, v, pos = integrate(list(ev.values()), n * DT)
    ends = np.round(np.arange(1, n + 1) * DT / 1e-3).astype(int)
    walked = np.cumsum(ref) * DT
    tol = accel * DT / 8 + (accel * DT / 2 if start < 0 or min(ref) == 0 else 0) + 1e-6
    np.testing.assert_allclose(pos[ends], walked, atol=tol, rtol=0)
    assert abs(pos[ends][-1] - walked[-1]) < tol


def test_value_of_evaluates_references_and_expressions():
    from jaxfalsify.outputs.export import value_of

    p = {"a": 0.25, "b": -2.0}
    assert value_of("1.5", p) == 1.5
    assert value_of("$b", p) == -2.0
    assert value_of("${floor(1 / $a + 0.5) * sqrt(($b) * ($b)) - pow(2, 3)}", p) == 0.0
    with pytest.raises(ValueError, match="unsupported"):
        value_of("${__import__(1)}", p)


# ------------------------------------------------------------------ review fixes
def _space(tmp_path, text, name="s"):
    import jaxfalsify as jf

    f = tmp_path / f"{name}.toml"
    f.write_text(text)
    return jf.load_space(f)


def test_a_space_with_only_ped_change_step_pauses_the_growth_there(tmp_path, xsd):
    """The simulator opens the window at ``ped_change_step`` whatever the change (a change of
    0 holds the speed, the growth paused six steps): a space declaring only the step exports a
    pedestrian that walks the simulator's distance, not an unpaused ramp."""
    import jaxfalsify as jf
    from jaxfalsify.core import sim
    from jaxfalsify.outputs import export

    sp = _space(tmp_path, 'name = "stepcha"\n[parameters.ego_offset]\nvalues = [9.0]\n'
                '[parameters.ped_speed]\nvalues = [1.237]\n[parameters.ped_accel]\n'
                'values = [0.007]\n[parameters.ped_offset]\nvalues = [3.5]\n'
                '[parameters.ped_change_step]\nvalues = [10, 20]\n')
    req = export.ego_request("carla-tm", {}, jf.WORLD)
    n = 300
    for i, step in enumerate(sp.table[sp.names.index("ped_change_step")]):
        idx = [0] * len(sp.names)
        idx[sp.names.index("ped_change_step")] = i
        values = export.parameter_values(sp, idx)
        f = export.write_controller_scenario(tmp_path / f"s{i}.xosc", "crossing.xodr", sp,
                                             values, req, jf.WORLD, "case")
        xsd.validate(str(f))
        root = ET.parse(f).getroot()
        params = declarations(root)
        simv = np.asarray(sim.ped_speed_profile(
            np.arange(n, dtype=np.float32), np.float32(params["ped_speed"]),
            np.float32(params["ped_accel"]), np.float32(params.get("ped_speed_change", 0.0)),
            np.float32(step)))
        ref, _, _ = oracle_profile(1.237, 0.007, 0.0, int(step), n)
        np.testing.assert_allclose(simv, ref, atol=2e-5)  # the simulator pauses the growth
        t, v, pos = integrate(speed_events(root, params), n * DT)
        ends = np.round(np.arange(1, n + 1) * DT / 1e-3).astype(int)
        np.testing.assert_allclose(pos[ends], np.cumsum(ref) * DT, atol=0.007 * DT / 8 + 1e-6,
                                   rtol=0)


def _recording_column(path, entity, column):
    from rerun.chunk import RrdReader

    out = []
    for c in RrdReader(path).stream().to_chunks():
        if c.entity_path == entity:
            rb = c.to_record_batch()
            if column in rb.schema.names:
                out.extend(rb.column(column).to_pylist())
    return out


@pytest.fixture(scope="module")
def sut_run(tmp_path_factory):
    """A 4-evaluation grid run (carla-tm) over a space with a SUT parameter dimension."""
    return grid_run(tmp_path_factory.mktemp("sutw"), "sutw",
                    'name = "sutw"\n[parameters.ego_offset]\nvalues = [5.0, 9.0]\n'
                    '[parameters.ped_speed]\nvalues = [1.237, 1.5]\n'
                    '[parameters.ped_offset]\nvalues = [3.5]\n'
                    '[parameters."sut.walker_time"]\nvalues = [3.0]\n',
                    4, "--batch", "4", "--no-figures")


def test_replay_grows_the_walker_box_with_the_spaces_sut_parameter(sut_run, tmp_path):
    """The recorded walker box is grown by the scenario's ``sut.walker_time`` (3 s), as the
    run simulated it, not the SUT's default (1.5 s): half size = half the walker's size +
    walker_time * its speed."""
    import jaxfalsify as jf
    from jaxfalsify.outputs.replay import record
    from jaxfalsify.suts.registry import CarlaTMParams

    f = record(sut_run, "best", save=tmp_path / "best.rrd")
    half = np.asarray([np.asarray(h)[0] for h in _recording_column(
        f, "/world/walker_grown_box", "Boxes2D:half_sizes")])
    speed = np.concatenate([np.ravel(s) for s in _recording_column(
        f, "/metrics/ped_speed", "Scalars:scalars")])
    assert len(half) == len(speed) > 10 and speed.max() > 1.0
    w = jf.WORLD
    np.testing.assert_allclose(half[:, 0], w.ped_length / 2 + 3.0 * speed, atol=1e-4)
    np.testing.assert_allclose(half[:, 1], w.ped_width / 2 + 3.0 * speed, atol=1e-4)
    assert CarlaTMParams().walker_time != 3.0  # the default would have failed


@pytest.mark.parametrize("decl", ['distribution = "uniform"\nlow = 0\nhigh = 14\nsamples = 3\n'
                                  'decimals = 0\n',
                                  'distribution = "uniform"\nlow = 2.2\nhigh = 9.7\nsamples = 4\n'
                                  'decimals = 0\n',
                                  'distribution = "normal"\nmean = 7\nsd = 2.5\nsamples = 3\n'
                                  'decimals = 0\n'], ids=["uniform", "uniform-inner", "normal"])
def test_every_weather_the_stochastic_file_may_draw_has_its_event(tmp_path, xsd, decl):
    """A weather drawn uniform/normal: logical_stochastic.xosc draws integers only (weighted
    as the space's own rounded draw gives them, estimated here by drawing 400,000 times with
    the space's rule), and every value it may draw starts exactly one weather event, the one
    setting that preset."""
    import dataclasses

    import jaxfalsify as jf
    from jaxfalsify.outputs import export
    from jaxfalsify.scenario import weather

    sp = _space(tmp_path, 'name = "w"\n[parameters.ego_offset]\nvalues = [9.0]\n'
                '[parameters.weather]\n' + decl)
    p = sp.names.index("weather")
    req = export.ego_request("carla-tm", {}, jf.WORLD)
    f = export.write_controller_scenario(tmp_path / "t.xosc", "crossing.xodr", sp,
                                         export.parameter_values(sp, [0] * len(sp.names)), req,
                                         jf.WORLD, "t")
    d = export.write_distribution(tmp_path / "st.xosc", sp, "t.xosc", "stochastic", 10)
    det = export.write_distribution(tmp_path / "det.xosc", sp, "t.xosc")
    for x in (f, d, det):
        xsd.validate(str(x))
    dist = next(e for e in ET.parse(d).getroot().iter("StochasticDistribution")
                if e.attrib["parameterName"] == "weather")
    assert dist.find("UniformDistribution") is None and dist.find("NormalDistribution") is None
    drawn = {float(e.attrib["value"]): float(e.attrib["weight"]) for e in dist.iter("Element")}
    assert all(v.is_integer() for v in drawn) and sum(drawn.values()) == pytest.approx(1.0)
    # the oracle: the space's own draw, many times
    big = dataclasses.replace(sp.parameters[p], samples=400_000).discretise(1)
    lo, hi = jf.scenario.space.KNOWN_PARAMETERS["weather"]["domain"]
    big = big[(big >= lo) & (big <= hi)]  # the file's normal is truncated to the domain
    vals, counts = np.unique(big, return_counts=True)
    freq = dict(zip(vals.tolist(), (counts / counts.sum()).tolist()))
    for v in set(freq) | set(drawn):
        assert drawn.get(v, 0.0) == pytest.approx(freq.get(v, 0.0), abs=0.004), v
    assert set(drawn) >= set(freq)
    may = set(drawn) | {float(e.attrib["value"])
                        for e in ET.parse(det).getroot().iter("DistributionSetElement")}
    assert may >= {float(v) for v in sp.table[p]}

    # the events a drawn value starts (the condition resolved as an engine would)
    rules = {"equalTo": lambda a, b: a == b, "greaterOrEqual": lambda a, b: a >= b,
             "greaterThan": lambda a, b: a > b, "lessThan": lambda a, b: a < b,
             "lessOrEqual": lambda a, b: a <= b, "notEqualTo": lambda a, b: a != b}
    root = ET.parse(f).getroot()
    man = next(m for m in root.iter("Maneuver") if m.attrib["name"] == "weather")

    def starts(ev, value):
        for g in ev.find("StartTrigger").findall("ConditionGroup"):
            conds = [c.find(".//ParameterCondition") for c in g.findall("Condition")]
            if all(rules[c.attrib["rule"]](value, float(c.attrib["value"]))
                   for c in conds if c is not None and c.attrib["parameterRef"] == "weather"):
                return True
        return False

    for v in may:
        hits = [ev for ev in man.findall("Event") if starts(ev, v)]
        assert len(hits) == 1, v
        assert hits[0].find(".//Environment").attrib["name"] == weather.PRESETS[int(v)][0]


def _snapshot(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_library_export_refuses_existing_files_without_force(sut_run, tmp_path):
    """``export(..., force=False)`` refuses a file an export writes (one line naming it), an
    existing file as the folder; ``force=True`` replaces an earlier export's files only
    (``critical_NNN.xosc``, not a user's ``critical_mine.xosc``)."""
    import fnmatch

    from jaxfalsify.outputs.export import EXPORT_FILES, export

    out = tmp_path / "osc"
    out.mkdir()
    (out / "critical_mine.xosc").write_text("mine")
    (out / "notes.txt").write_text("notes")
    first = export(sut_run, out)  # a user's files do not count
    assert sorted(p.name for p in first) == ["best.xosc", "crossing.xodr", "logical.xosc",
                                             "logical_stochastic.xosc"]
    (out / "critical_001.xosc").write_text("stale, from an earlier critical export")
    before = _snapshot(out)
    with pytest.raises(ValueError) as e:
        export(sut_run, out)
    msg = str(e.value)
    assert "\n" not in msg and "best.xosc" in msg and "force" in msg
    assert _snapshot(out) == before
    export(sut_run, out, force=True)
    after = _snapshot(out)
    assert "critical_001.xosc" not in after  # an earlier export's scenario, replaced
    assert after["critical_mine.xosc"] == b"mine" and after["notes.txt"] == b"notes"
    assert set(after) == {"best.xosc", "crossing.xodr", "logical.xosc", "logical_stochastic.xosc",
                          "critical_mine.xosc", "notes.txt"}
    # the CLI's check of --out uses the same names
    assert not any(fnmatch.fnmatch("critical_mine.xosc", g) for g in EXPORT_FILES)
    assert any(fnmatch.fnmatch("critical_012.xosc", g) for g in EXPORT_FILES)

    f = tmp_path / "afile"
    f.write_text("x")
    for bad in (f, f / "sub"):
        with pytest.raises(ValueError) as e:
            export(sut_run, bad)
        assert "\n" not in str(e.value) and "not a folder" in str(e.value)
    assert f.read_text() == "x"


def test_a_failed_export_leaves_the_folder_as_it_was(sut_run, tmp_path, monkeypatch):
    """A writer failing (OSError): a folder the export created is gone, an earlier export's
    files stay as they were; a failure while moving the files in puts the earlier ones back."""
    import os
    from pathlib import Path

    from jaxfalsify.outputs import export as ex

    def broken(*a, **k):
        raise OSError(28, "No space left on device")

    new = tmp_path / "a" / "b"
    with monkeypatch.context() as m:
        m.setattr(ex, "write_distribution", broken)
        with pytest.raises(OSError, match="No space left") as e:
            ex.export(sut_run, new)
    assert e.value.filename == str(new)  # the error names the export's folder
    assert not (tmp_path / "a").exists()

    out = tmp_path / "osc"
    ex.export(sut_run, out)
    (out / "notes.txt").write_text("mine")
    before = _snapshot(out)
    with monkeypatch.context() as m:
        m.setattr(ex, "write_distribution", broken)
        with pytest.raises(OSError, match="No space left"):
            ex.export(sut_run, out, force=True)
    assert _snapshot(out) == before
    real = os.replace
    calls = []

    def fails_late(src, dst):  # the third new file moved in fails (the earlier ones moved)
        if Path(dst).parent == out and Path(src).parent.name.startswith(".export-"):
            calls.append(dst)
            if len(calls) == 3:
                raise OSError(5, "Input/output error")
        return real(src, dst)

    with monkeypatch.context() as m:
        m.setattr(os, "replace", fails_late)  # (the os module: files publishes)
        with pytest.raises(OSError, match="Input/output"):
            ex.export(sut_run, out, which="best", ego="replay", force=True)
    assert len(calls) == 3
    assert _snapshot(out) == before
    assert sorted(p.name for p in out.iterdir()) == sorted(before)  # no temporary folder left


def test_an_export_is_byte_reproducible_and_its_road_says_opendrive_1_7(sut_run, tmp_path):
    """Two exports of one run (in one process) are byte-identical (the headers carry the
    run's date, not the time of writing); the road's header says OpenDRIVE 1.7, the XSD it
    is checked against, and the crosswalk has no subtype "None"."""
    import time

    from jaxfalsify.outputs.export import export

    export(sut_run, tmp_path / "one", ego="replay")
    time.sleep(1.1)
    export(sut_run, tmp_path / "two", ego="replay")
    one, two = _snapshot(tmp_path / "one"), _snapshot(tmp_path / "two")
    assert one == two and len(one) == 5
    road = ET.parse(tmp_path / "one" / "crossing.xodr").getroot()
    header = road.find("header")
    assert (header.attrib["revMajor"], header.attrib["revMinor"]) == ("1", "7")
    schema("xodr").validate(str(tmp_path / "one" / "crossing.xodr"))
    [obj] = road.iter("object")
    assert obj.attrib["type"] == "crosswalk" and "subtype" not in obj.attrib
    for name in one:
        if name.endswith(".xosc"):
            schema().validate(str(tmp_path / "one" / name))
