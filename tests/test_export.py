"""OpenSCENARIO export, controller mode, without a run: the pedestrian's speed profile written
as parameter expressions and speed events reproduces the simulator's (checked against a
closed-form oracle of the original's profile, against ``sim.ped_speed_profile`` and by
integrating the file's events into positions). The run-level checks (the exported parameters
reproduce the run's outcomes, the distributions list the space) are in
``test_figures_report.py``, which has a run."""

import functools
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

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
    from jaxfalsify.export import value_of

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

    from jaxfalsify.export import schema_path

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
    from jaxfalsify import export, sim

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
    from jaxfalsify.export import value_of

    p = {"a": 0.25, "b": -2.0}
    assert value_of("1.5", p) == 1.5
    assert value_of("$b", p) == -2.0
    assert value_of("${floor(1 / $a + 0.5) * sqrt(($b) * ($b)) - pow(2, 3)}", p) == 0.0
    with pytest.raises(ValueError, match="unsupported"):
        value_of("${__import__(1)}", p)
