"""OpenSCENARIO 1.x export of a run's concrete scenarios and its logical scenario
(``scenariogeneration``, host side).

One concern: writing OpenSCENARIO / OpenDRIVE files of a run's scenarios.

Writes, to one folder:

* per scenario, ``<name>.xosc`` (OpenSCENARIO 1.3; ``best.xosc`` or ``critical_NNN.xosc``);
* ``crossing.xodr`` (OpenDRIVE 1.7: the straight 4-lane road with a crosswalk object), shared;
* ``logical.xosc``: the run's logical scenario as a ``ParameterValueDistribution`` over the
  exported scenario file (the template): one deterministic ``DistributionSet`` per space
  parameter holding its discretised values, so a tool enumerating it re-runs the sweep;
* ``logical_stochastic.xosc``: the same parameters as the space declares them (normal, uniform,
  integer or explicit value sets) as a stochastic distribution (OpenSCENARIO allows one kind
  per file); ``weather`` and ``ped_change_step`` drawn normal or uniform as the integers their
  rounded draw can give, weighted by probability (:func:`integer_draws`).

Without ``force`` an export refuses a file it would write that is already in the folder; every
file header carries the run's date (:func:`run_date`), so an export is byte-reproducible.

Every scenario file declares the space's parameters (``ParameterDeclarations``: names as in the
space, type double, the concrete value with the space's decimals) and the known scenario
parameters the file uses that the space does not declare (with their defaults).

Two ways to export the ego (``ego``):

* ``controller`` (default): the ego gets only its start (``TeleportAction`` to a lane position
  ``ego_offset`` behind its base, at rest: ``AbsoluteTargetSpeed`` 0), its route along its
  lane (``AssignRouteAction``) and, at t = 0, a request to reach the run's SUT cruise speed
  (``ego_target_speed`` at ``ego_launch_accel``); whatever controls it in the tool (esmini's
  default controller, a user's stack under CARLA ScenarioRunner) drives it. The pedestrian is
  fully specified by parameter expressions (``${...}``): its path across the road (a
  trajectory without timing) and the simulator's speed profile (:func:`jaxfalsify.core.sim.
  ped_speed_profile`) as speed events started by the ego's start (t = 0, as in the
  simulation). Stop: collision, the ego's 30 m + ``ego_offset`` travelled, or the 30 s horizon.
* ``replay``: both actors follow their *simulated* trajectories (a timed polyline of every
  0.1 s step, ``FollowTrajectoryAction`` with absolute timing); stop at the episode's end.

The CARLA weather preset becomes an ``EnvironmentAction`` (cloudiness -> oktas, precipitation ->
rain of up to 10 mm/h, sun altitude -> sun elevation, water deposits -> road wetness; friction
unchanged as in CARLA); in controller mode a space with several weather values also switches
the environment on ``$weather`` (one ``ParameterCondition``-triggered event per value either
distribution may set, :func:`distribution_values`).

The pedestrian's profile in events. The simulator's speed during step k (of ``dt``) is
``max(s_k, 0)`` with ``s = ped_speed - 5 * ped_accel`` for steps 0..5, then ``s`` grows by
``ped_accel`` per step for ``n = floor(0.25 / ped_accel + 5.0001) + 1`` steps (to the target
``s + n * ped_accel``), i.e. at ``ped_accel / dt`` m/s^2. A linear ramp at that rate starting
at ``5.5 * dt`` (half a step early: the midpoint of each step's speed) passes every step's
speed at the step's middle, so the walked distance equals the simulator's at the end of the
ramp and differs by ``ped_accel * dt / 8`` (<= 1.3 mm in the paper's space) during it. In a
space declaring ``ped_speed_change`` or ``ped_change_step`` (the extended space; the simulator
opens the window whatever the change, a change of 0 holds the speed), the six-step window from
step ``T = ped_change_step`` walks at the last
step's speed + ``ped_speed_change`` and pauses the growth: a step to that speed at ``T * dt``,
a step back to the ramp's value at ``(T + 6) * dt``, then the ramp again. A negative profile
speed (a slow walker with a large increment) walks at 0; a ramp from a negative value starts,
from 0, when the raw line crosses zero (then exact up to that one step).

Road frame: our x + ``X_OFFSET`` along the road (OpenDRIVE's road starts at x = 0), y as ours
(left positive, the centre line at y = 0); the ego drives in lane -1.
"""

from __future__ import annotations

import ast
import datetime
import math
import operator
import re
import tempfile
from pathlib import Path

import numpy as np

from jaxfalsify.core.sim import STILL, WINDOW, WORLD, start_positions
from jaxfalsify.engine.rundir import check_simulated, indices_of, load_run, resimulate
from jaxfalsify.io.files import naming_errors, replace_files
from jaxfalsify.io.store import folder_kind, with_article
from jaxfalsify.outputs import analysis
from jaxfalsify.scenario import weather as weather_lib
from jaxfalsify.scenario.space import KNOWN_PARAMETERS, decimal_grid
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "X_OFFSET", "schema_path", "write_road", "value_of", "used_parameters", "parameter_values",
    "ego_request", "write_controller_scenario", "write_distribution", "EXPORT_FILES", "export"
]

X_OFFSET = 60.0  # m: our x = -60 is the road's start (ego_offset <= 50 m starts on it)
ROAD_LENGTH = 130.0  # m
EGO_LANE = -1  # OpenDRIVE lane of the ego (the innermost right lane)
EGO_MODES = ("controller", "replay")
SCENARIO_CHOICES = ("best", "critical")
PED_PATH_BEYOND = 5.0  # m: the pedestrian's path ends this far past the far kerb
OKTAS = ("zeroOktas", "oneOktas", "twoOktas", "threeOktas", "fourOktas", "fiveOktas",
         "sixOktas", "sevenOktas", "eightOktas")

_EPS = "0.000000000001"  # keeps ped_accel = 0 finite in divisions (its products are then 0)


def schema_path(kind: str = "xosc") -> Path:
    """The XSD that ships with scenariogeneration (OpenSCENARIO 1.3.1 / OpenDRIVE 1.7)."""
    import scenariogeneration

    base = Path(scenariogeneration.__file__).resolve().parent.parent / "schemas"
    return base / ("OpenSCENARIO_1_3_1.xsd" if kind == "xosc" else "opendrive_17_core.xsd")


def write_road(path: Path, world, date: datetime.datetime | None = None) -> Path:
    """``crossing.xodr``: OpenDRIVE 1.7 (the header says so: the file is checked against the
    1.7 XSD), its header dated ``date`` (default: now)."""
    from scenariogeneration import xodr
    from scenariogeneration.helpers import printToFile

    road = xodr.create_road(xodr.Line(ROAD_LENGTH), id=0, left_lanes=int(world.lanes_left),
                            right_lanes=int(world.lanes_right), lane_width=world.lane_width)
    # centred across the road (t: lateral offset from the reference line, left positive)
    road.add_object(xodr.Object(s=world.crosswalk_x + X_OFFSET,
                                t=(world.road_left + world.road_right) / 2,
                                Type=xodr.ObjectType.crosswalk, name="crosswalk",
                                width=world.road_left - world.road_right, length=3.0,
                                height=0.0, hdg=0.0))
    odr = xodr.OpenDrive("jaxfalsify_crossing", revMajor="1", revMinor="7")
    odr.add_road(road)
    odr.adjust_roads_and_lanes()
    root = odr.get_element()
    root.find("header").set("date", _date_text(date))  # scenariogeneration writes now()
    for obj in root.iter("object"):  # the crosswalk, the road's only object
        # its id: scenariogeneration numbers objects across a process (a second export would
        # get another id, and a printed warning for a given one); its subtype (optional)
        # written as the text "None"
        obj.set("id", "1")
        if obj.get("subtype") == "None":
            del obj.attrib["subtype"]
    printToFile(root, str(path))
    return path


def _date_text(date: datetime.datetime | None) -> str:
    return (date or datetime.datetime.now()).isoformat()


def environment(weather_index: int):
    """OpenSCENARIO environment of a CARLA weather preset."""
    from scenariogeneration import xosc

    name, cloud, rain, deposits, sun = weather_lib.PRESETS[int(weather_index)]
    oktas = getattr(xosc.FractionalCloudCover, OKTAS[min(8, round(cloud / 12.5))])
    precip = (xosc.Precipitation(xosc.PrecipitationType.rain, rain / 10.0) if rain > 0
              else xosc.Precipitation(xosc.PrecipitationType.dry, 0.0))
    w = xosc.Weather(cloudstate=oktas, precipitation=precip,
                     sun=xosc.Sun(100000.0 if sun > 45 else 20000.0, 0.0, math.radians(sun)))
    wet = xosc.Wetness.dry if deposits == 0 else (xosc.Wetness.wetWithPuddles if deposits >= 100
                                                  else xosc.Wetness.moist)
    hour = 12 if sun > 45 else 19
    return xosc.Environment(name, xosc.TimeOfDay(False, 2026, 6, 21, hour, 0, 0), w,
                            xosc.RoadCondition(1.0, wetness=wet))


# ---------------------------------------------------------------- parameter expressions
def _num(v: float) -> str:
    return f"{float(v):.12g}"


def _abs(x: str) -> str:  # OpenSCENARIO expressions have no abs/min/max: |x| = sqrt(x * x)
    return f"sqrt(({x}) * ({x}))"


def _pos(x: str) -> str:  # max(x, 0)
    return f"(({x}) + {_abs(x)}) / 2"


def _neg(x: str) -> str:  # max(-x, 0)
    return f"({_abs(x)} - ({x})) / 2"


def _clip(x: str, lo: str, hi: str) -> str:  # min(max(x, lo), hi) for lo <= hi
    m = f"(({x}) + ({lo}) + {_abs(f'({x}) - ({lo})')}) / 2"
    return f"(({m}) + ({hi}) - {_abs(f'({m}) - ({hi})')}) / 2"


def _expr(body: str) -> str:
    return "${" + body + "}"


def ped_expressions(world, window: bool) -> dict[str, str]:
    """The pedestrian's start and speed profile as OpenSCENARIO expressions of the parameters
    (``${...}``); ``window``: with the extended space's speed-change window."""
    dt = float(world.dt)
    s = f"$ped_speed - {STILL - 1} * $ped_accel"
    a_safe = f"($ped_accel + {_EPS})"
    n = f"(floor(0.25 / {a_safe} + 5.0001) + 1)"
    out = {
        "ped_y0": _expr(f"{_num(world.road_right + world.walker_base - 1.0)} - $ped_offset"),
        "start_speed": _expr(_pos(s)),
        "ramp_at": _expr(f"{_num((STILL - 0.5) * dt)} + {_neg(s)} / {a_safe} * {_num(dt)}"),
        "rate": _expr(f"$ped_accel / {_num(dt)}"),
        "target": _expr(f"{s} + {n} * $ped_accel"),
    }
    if window:
        t = "$ped_change_step"
        held = f"{s} + {_clip(f'{t} - {STILL}', '0', n)} * $ped_accel + $ped_speed_change"
        back = f"{s} + {_clip(f'{t} - {STILL - 0.5}', '0.5', n)} * $ped_accel"
        out.update({
            "window_at": _expr(f"{t} * {_num(dt)}"),
            "window_speed": _expr(_pos(held)),
            "restore_at": _expr(f"({t} + {WINDOW}) * {_num(dt)}"),
            "restore_speed": _expr(_pos(back)),
            "ramp_again_delay": _expr(f"{_neg(back)} / {a_safe} * {_num(dt)}"),
        })
    return out


_OPS = {ast.Add: operator.add, ast.Sub: operator.sub, ast.Mult: operator.mul,
        ast.Div: operator.truediv, ast.Mod: math.fmod, ast.USub: operator.neg,
        ast.UAdd: operator.pos}
_FUNCS = {"floor": math.floor, "ceil": math.ceil, "sqrt": math.sqrt, "pow": math.pow,
          "round": lambda x: math.floor(x + 0.5) if x >= 0 else -math.floor(-x + 0.5)}


def value_of(text: str, params: dict[str, float]) -> float:
    """The number an OpenSCENARIO attribute stands for: a literal, a ``$name`` reference or a
    ``${...}`` expression (arithmetic, floor, ceil, round, sqrt, pow) over ``params``."""
    text = text.strip()
    if text.startswith("${") and text.endswith("}"):
        body = re.sub(r"\$([A-Za-z_]\w*)", lambda m: f"({float(params[m.group(1)])!r})",
                      text[2:-1])

        def ev(node):
            if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)):
                return float(node.value)
            if isinstance(node, ast.BinOp) and type(node.op) in _OPS:
                return _OPS[type(node.op)](ev(node.left), ev(node.right))
            if isinstance(node, ast.UnaryOp) and type(node.op) in _OPS:
                return _OPS[type(node.op)](ev(node.operand))
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                    and node.func.id in _FUNCS and not node.keywords:
                return float(_FUNCS[node.func.id](*(ev(x) for x in node.args)))
            raise ValueError(f"unsupported expression element in {text!r}")

        return float(ev(ast.parse(body, mode="eval").body))
    if text.startswith("$"):
        return float(params[text[1:]])
    return float(text)


# ---------------------------------------------------------------- declarations
WINDOW_PARAMETERS = ("ped_speed_change", "ped_change_step")


def has_window(names) -> bool:
    """Whether scenarios over the parameters ``names`` have the speed-change window: either of
    its parameters declared (the simulator opens it at ``ped_change_step`` whatever the
    change: a space declaring only the step still pauses the growth there)."""
    return any(n in names for n in WINDOW_PARAMETERS)


def used_parameters(space) -> tuple[str, ...]:
    """Known scenario parameters a controller-mode file references."""
    base = ("ego_offset", "ped_speed", "ped_accel", "ped_offset", "weather")
    return base + (WINDOW_PARAMETERS if has_window(space.names) else ())


def parameter_values(space, indices) -> dict[str, str]:
    """``{name: value text}``: the space's parameters at ``indices`` (with the space's
    decimals), then the other known parameters a scenario file uses (their defaults)."""
    out = {n: analysis.format_value(space, p, space.table[p][int(indices[p])])
           for p, n in enumerate(space.names)}
    for n in used_parameters(space):
        out.setdefault(n, f"{KNOWN_PARAMETERS[n]['default']:g}")
    return out


def _declarations(values: dict[str, str], extra: dict[str, float] | None = None):
    from scenariogeneration import xosc

    decl = xosc.ParameterDeclarations()
    for n, v in values.items():
        decl.add_parameter(xosc.Parameter(n, xosc.ParameterType.double, v))
    for n, v in (extra or {}).items():
        decl.add_parameter(xosc.Parameter(n, xosc.ParameterType.double, _num(v)))
    return decl


def ego_request(sut, sut_params, world, traj=None) -> dict[str, float]:
    """The ego's launch request in controller mode: ``ego_target_speed`` [m/s] (the SUT's
    cruise target: the autopilot's ``speed_limit * (1 - below_limit / 100)``) and
    ``ego_launch_accel`` [m/s^2] (its saturated launch, ``max_throttle * throttle_accel``,
    within the vehicle's limit). A SUT without those parameters: the top speed and the largest
    acceleration of its simulated trajectory ``traj`` (fields of one scenario)."""

    s = sut_lib.resolve(sut)
    p = sut_lib.params_dict(sut_lib.with_params(s, dict(sut_params or {})))
    if {"speed_limit", "below_limit"} <= set(p):
        target = p["speed_limit"] / 3.6 * (1.0 - p["below_limit"] / 100.0)
        accel = p.get("max_throttle", 1.0) * p.get("throttle_accel", float(world.max_accel))
    elif traj is not None:
        v = np.asarray(traj["valid"], bool)
        target = float(np.max(np.asarray(traj["ego_speed"])[v], initial=0.0))
        accel = float(np.max(np.asarray(traj["ego_accel"])[v], initial=0.0))
    else:
        raise ValueError(f"SUT '{s.name}' has no speed_limit/below_limit: pass its trajectory")
    accel = min(accel, float(world.max_accel))
    return {"ego_target_speed": round(float(target), 6),
            "ego_launch_accel": round(float(max(accel, 1e-3)), 6)}


# ---------------------------------------------------------------- scenario files
def _entities(world):
    from scenariogeneration import xosc

    entities = xosc.Entities()
    car_box = xosc.BoundingBox(world.ego_width, world.ego_length, 1.6, 0.0, 0.0, 0.8)
    axle_f = xosc.Axle(0.5, 0.65, 1.6, 1.4, 0.33)
    axle_r = xosc.Axle(0.0, 0.65, 1.6, -1.4, 0.33)
    car = xosc.Vehicle("ego", xosc.VehicleCategory.car, car_box, axle_f, axle_r, 50.0,
                       float(world.max_accel), float(world.max_brake))
    car.add_property("type", "ego_vehicle")  # ScenarioRunner's mark of an ego vehicle
    entities.add_scenario_object("Ego", car)
    ped_box = xosc.BoundingBox(world.ped_length, world.ped_width, 1.8, 0.0, 0.0, 0.9)
    entities.add_scenario_object("Pedestrian", xosc.Pedestrian(
        "adult", 80.0, xosc.PedestrianCategory.pedestrian, ped_box, model="adult"))
    return entities


def _describe(name: str, params: dict) -> str:
    return f"jaxfalsify {name}: " + ", ".join(f"{k}={float(v):g}" for k, v in params.items())


def write_scenario(path: Path, road_file: str, traj: dict, params: dict, world,
                   name: str, declarations: dict[str, str] | None = None,
                   date: datetime.datetime | None = None) -> Path:
    """Replay mode: one ``.xosc`` in which both actors follow a simulated trajectory (fields
    ``(T,)`` of one scenario); ``declarations`` ``{name: value text}`` are declared (not
    referenced: the trajectories carry the values)."""
    from scenariogeneration import xosc

    v = traj["valid"]
    x0, y0 = start_positions(params["ego_offset"], params["ped_offset"], world)
    # the start (t = 0) first, then the state after each simulated step
    t = [0.0] + [round(float(x), 3) for x in traj["t"][v]]
    ego_pos = [xosc.WorldPosition(float(x) + X_OFFSET, float(y), 0.0, 0.0)
               for x, y in zip([x0, *traj["ego_x"][v]], [world.ego_y, *traj["ego_y"][v]])]
    ped_pos = [xosc.WorldPosition(float(x) + X_OFFSET, float(y), 0.0, math.pi / 2)
               for x, y in zip([world.crosswalk_x, *traj["ped_x"][v]], [y0, *traj["ped_y"][v]])]

    init = xosc.Init()
    init.add_init_action("Ego", xosc.TeleportAction(ego_pos[0]))
    init.add_init_action("Pedestrian", xosc.TeleportAction(ped_pos[0]))
    init.add_global_action(xosc.EnvironmentAction(environment(params["weather"])))

    end = t[-1] + 0.1
    stop = xosc.ValueTrigger("end", 0.0, xosc.ConditionEdge.rising,
                             xosc.SimulationTimeCondition(end, xosc.Rule.greaterThan), "stop")
    sb = xosc.StoryBoard(init, stop)
    start = xosc.ValueTrigger("start", 0.0, xosc.ConditionEdge.none,
                              xosc.SimulationTimeCondition(0.0, xosc.Rule.greaterThan))
    for actor, pos in (("Ego", ego_pos), ("Pedestrian", ped_pos)):
        tr = xosc.Trajectory(f"{actor.lower()}_trajectory", False)
        tr.add_shape(xosc.Polyline(t, pos))
        follow = xosc.FollowTrajectoryAction(tr, xosc.FollowingMode.position,
                                             xosc.ReferenceContext.absolute, 1.0, 0.0)
        ev = xosc.Event(f"{actor.lower()}_moves", xosc.Priority.override)
        ev.add_action(f"{actor.lower()}_follows", follow)
        ev.add_trigger(start)
        man = xosc.Maneuver(f"{actor.lower()}_maneuver")
        man.add_event(ev)
        sb.add_maneuver(man, actor)
    sce = xosc.Scenario(_describe(name, params), "jaxfalsify",
                        _declarations(declarations or {}), _entities(world), sb,
                        xosc.RoadNetwork(roadfile=road_file), xosc.Catalog(),
                        creation_date=date)
    sce.write_xml(str(path))
    return path


def _step():
    from scenariogeneration import xosc

    return xosc.TransitionDynamics(xosc.DynamicsShapes.step, xosc.DynamicsDimension.time, 0.0)


def _at(name: str, time: str, rule=None):
    """A condition: simulation time reached ``time`` (a number or expression)."""
    from scenariogeneration import xosc

    return xosc.ValueTrigger(name, 0.0, xosc.ConditionEdge.none, xosc.SimulationTimeCondition(
        time, rule or xosc.Rule.greaterOrEqual))


def _param_is(name: str, parameter: str, value: str, rule):
    from scenariogeneration import xosc

    return xosc.ValueTrigger(name, 0.0, xosc.ConditionEdge.none,
                             xosc.ParameterCondition(parameter, value, rule))


def _any_of(*groups):
    """A start trigger: OR over ``groups``, each an AND of conditions."""
    from scenariogeneration import xosc

    trig = xosc.Trigger("start")
    for conds in groups:
        g = xosc.ConditionGroup("start")
        for c in conds:
            g.add_condition(c)
        trig.add_conditiongroup(g)
    return trig


def _speed_event(name: str, target: str, dynamics, trigger):
    from scenariogeneration import xosc

    ev = xosc.Event(name, xosc.Priority.override)
    ev.add_action(name, xosc.AbsoluteSpeedAction(target, dynamics))
    ev.add_trigger(trigger)
    return ev


def write_controller_scenario(path: Path, road_file: str, space, values: dict[str, str],
                              request: dict[str, float], world, name: str,
                              date: datetime.datetime | None = None) -> Path:
    """Controller mode: one ``.xosc`` for the concrete scenario ``values`` (``{name: value
    text}``, :func:`parameter_values`) in which the ego gets its start, route and launch
    request (``request``, :func:`ego_request`) and the pedestrian's path and speed profile
    are expressions of the declared parameters; see the module's docstring."""
    from scenariogeneration import xosc

    dt = float(world.dt)
    window = has_window(values)
    ex = ped_expressions(world, window)
    ego_s = _expr(f"{_num(X_OFFSET)} - $ego_offset")
    ped_x = world.crosswalk_x + X_OFFSET

    init = xosc.Init()
    init.add_init_action("Ego", xosc.TeleportAction(
        xosc.LanePosition(ego_s, 0.0, EGO_LANE, "0")))
    init.add_init_action("Ego", xosc.AbsoluteSpeedAction(0.0, _step()))
    route = xosc.Route("ego_lane")
    route.add_waypoint(xosc.LanePosition(ego_s, 0.0, EGO_LANE, "0"), xosc.RouteStrategy.shortest)
    route.add_waypoint(xosc.LanePosition(ROAD_LENGTH - 1.0, 0.0, EGO_LANE, "0"),
                       xosc.RouteStrategy.shortest)
    init.add_init_action("Ego", xosc.AssignRouteAction(route))
    ped_start = xosc.WorldPosition(ped_x, ex["ped_y0"], 0.0, math.pi / 2)
    init.add_init_action("Pedestrian", xosc.TeleportAction(ped_start))
    init.add_init_action("Pedestrian", xosc.AbsoluteSpeedAction(0.0, _step()))
    init.add_global_action(xosc.EnvironmentAction(environment(float(values["weather"]))))

    # the episode's end: collision, 30 m + ego_offset travelled, or the horizon
    stop = xosc.Trigger("stop")
    for cond in (
            xosc.EntityTrigger("collision", 0.0, xosc.ConditionEdge.rising,
                               xosc.CollisionCondition("Pedestrian"), "Ego",
                               triggeringpoint="stop"),
            xosc.EntityTrigger("travelled", 0.0, xosc.ConditionEdge.rising,
                               xosc.TraveledDistanceCondition(
                                   _expr(f"{_num(world.end_x)} + $ego_offset")), "Ego",
                               triggeringpoint="stop"),
            xosc.ValueTrigger("horizon", 0.0, xosc.ConditionEdge.rising,
                              xosc.SimulationTimeCondition(world.horizon * dt,
                                                           xosc.Rule.greaterThan), "stop")):
        g = xosc.ConditionGroup("stop")
        g.add_condition(cond)
        stop.add_conditiongroup(g)
    sb = xosc.StoryBoard(init, stop)

    ego_start = lambda: _at("ego_start", 0.0)  # noqa: E731  (a fresh element per use)
    act = xosc.Act("crossing", _any_of([ego_start()]))

    # the ego: a launch request to the SUT's cruise speed (a user's controller may ignore it)
    ego_man = xosc.Maneuver("ego_launch")
    ego_man.add_event(_speed_event(
        "ego_cruise_request", "$ego_target_speed",
        xosc.TransitionDynamics(xosc.DynamicsShapes.linear, xosc.DynamicsDimension.rate,
                                "$ego_launch_accel"), _any_of([ego_start()])))
    mg = xosc.ManeuverGroup("ego")
    mg.add_actor("Ego")
    mg.add_maneuver(ego_man)
    act.add_maneuver_group(mg)

    # the pedestrian: its path (no timing: it walks at the speed the events set) ...
    ped_path = xosc.Trajectory("ped_path", False)
    ped_path.add_shape(xosc.Polyline([], [
        xosc.WorldPosition(ped_x, ex["ped_y0"], 0.0, math.pi / 2),
        xosc.WorldPosition(ped_x, float(world.road_left) + PED_PATH_BEYOND, 0.0,
                           math.pi / 2)]))
    walk = xosc.Event("ped_walks", xosc.Priority.parallel)
    walk.add_action("ped_follows_path", xosc.FollowTrajectoryAction(
        ped_path, xosc.FollowingMode.position))
    walk.add_trigger(_any_of([ego_start()]))
    path_man = xosc.Maneuver("ped_path")
    path_man.add_event(walk)

    # ... and its speed profile, started by the ego's start
    linear = xosc.TransitionDynamics(xosc.DynamicsShapes.linear, xosc.DynamicsDimension.rate,
                                     ex["rate"])
    speed_man = xosc.Maneuver("ped_speed_profile")
    E, R = xosc.StoryboardElementType, xosc.Rule
    if window:
        # at T = 0 the window itself is the start speed: the two must not start together
        start = _any_of([ego_start(), _param_is("window_later", "ped_change_step", "0",
                                                R.greaterThan)])
        window_waiting = lambda: xosc.ValueTrigger(  # noqa: E731
            "window_not_started", 0.0, xosc.ConditionEdge.none,
            xosc.StoryboardElementStateCondition(E.event, "ped_speed_change",
                                                 xosc.StoryboardElementState.standbyState))
        ramp = _any_of([_at("growth_starts", ex["ramp_at"]), window_waiting()])
    else:
        start = _any_of([ego_start()])
        ramp = _any_of([_at("growth_starts", ex["ramp_at"])])
    speed_man.add_event(_speed_event("ped_start_speed", ex["start_speed"], _step(), start))
    speed_man.add_event(_speed_event("ped_accelerates", ex["target"], linear, ramp))
    if window:
        # the window opens whatever the change (pdf.py): a change of 0 holds the speed
        speed_man.add_event(_speed_event(
            "ped_speed_change", ex["window_speed"], _step(),
            _any_of([_at("window_starts", ex["window_at"])])))
        speed_man.add_event(_speed_event(
            "ped_speed_restore", ex["restore_speed"], _step(),
            _any_of([_at("window_ends", ex["restore_at"])])))
        again = xosc.ValueTrigger(
            "restored", ex["ramp_again_delay"], xosc.ConditionEdge.none,
            xosc.StoryboardElementStateCondition(E.event, "ped_speed_restore",
                                                 xosc.StoryboardElementState.endTransition))
        speed_man.add_event(_speed_event("ped_accelerates_again", ex["target"], linear,
                                         _any_of([again])))
    mg = xosc.ManeuverGroup("pedestrian")
    mg.add_actor("Pedestrian")
    mg.add_maneuver(path_man)
    mg.add_maneuver(speed_man)
    act.add_maneuver_group(mg)

    # the weather on $weather, for a template whose distribution varies it: every preset the
    # deterministic or the stochastic distribution may set (the stochastic one draws from the
    # declared range, not only the space's drawn values)
    w_all = distribution_values(space, "weather")
    if len(w_all) > 1:
        w_man = xosc.Maneuver("weather")
        for v in w_all:
            ev = xosc.Event(f"weather_{int(v)}", xosc.Priority.parallel)
            ev.add_action(f"weather_{int(v)}", xosc.EnvironmentAction(environment(int(v))))
            ev.add_trigger(_any_of([ego_start(), _param_is(f"weather_is_{int(v)}", "weather",
                                                           f"{int(v)}", R.equalTo)]))
            w_man.add_event(ev)
        mg = xosc.ManeuverGroup("environment")
        mg.add_maneuver(w_man)
        act.add_maneuver_group(mg)

    story = xosc.Story("crossing")
    story.add_act(act)
    sb.add_story(story)
    sce = xosc.Scenario(_describe(name, {k: float(v) for k, v in values.items()}), "jaxfalsify",
                        _declarations(values, request), _entities(world), sb,
                        xosc.RoadNetwork(roadfile=road_file), xosc.Catalog(),
                        creation_date=date)
    sce.write_xml(str(path))
    return path


# ---------------------------------------------------------------- the logical scenario
def _normal_cdf(x: float, mean: float, sd: float) -> float:
    return 0.5 * math.erfc(-(x - mean) / (sd * math.sqrt(2.0)))


def integer_draws(par) -> list[tuple[int, float]] | None:
    """A parameter the simulator reads as an integer (``KNOWN_PARAMETERS``' ``integer``:
    ``weather``, ``ped_change_step``) declared ``uniform`` or ``normal``: ``[(value,
    probability)]`` of every integer the space's draw can give (a draw rounded to an integer;
    uniform: clipped to the range's integers, so ``v`` has the probability of ``[v - 0.5,
    v + 0.5)`` within the range; normal: that of ``N(mean, sd^2)``, truncated to the
    parameter's domain); values of probability 0 (below 1e-15) left out. None for every other
    parameter (it is drawn continuously)."""

    spec = KNOWN_PARAMETERS.get(par.name)
    if spec is None or not spec["integer"] or par.distribution not in ("uniform", "normal"):
        return None
    if par.distribution == "uniform":
        lo, hi = (float(a) for a in par.args)
        g_lo, g_hi = (int(round(g)) for g in decimal_grid(lo, hi, 0))
        mass = {v: (min(hi, v + 0.5) if v < g_hi else hi) - (max(lo, v - 0.5) if v > g_lo else lo)
                for v in range(g_lo, g_hi + 1)}
    else:
        mean, sd = (float(a) for a in par.args)
        d_lo, d_hi = spec["domain"]
        mass = {v: _normal_cdf(v + 0.5, mean, sd) - _normal_cdf(v - 0.5, mean, sd)
                for v in range(math.ceil(d_lo), math.floor(d_hi) + 1)}
    total = sum(mass.values())
    out = [(v, m / total) for v, m in mass.items() if m / total > 1e-15]
    norm = sum(w for _, w in out)
    return [(v, float(f"{w / norm:.12g}")) for v, w in out]


def distribution_values(space, name: str) -> list[int]:
    """The integer values of the parameter ``name`` (``weather``) that the deterministic or
    the stochastic distribution (:func:`write_distribution`) may set: the space's values and
    every integer its declaration allows (``integers``: the range; ``values``: the list;
    ``uniform``, ``normal``: :func:`integer_draws`); [] when the space does not declare it."""
    if name not in space.names:
        return []
    p = space.names.index(name)
    par = space.parameters[p]
    out = {int(v) for v in space.table[p]}
    if par.distribution == "integers":
        out |= set(range(int(par.args[0]), int(par.args[1]) + 1))
    elif par.distribution == "values":
        out |= {int(v) for v in par.args}
    else:
        out |= {v for v, _ in integer_draws(par) or ()}
    return sorted(out)


def write_distribution(path: Path, space, scenario_file: str, kind: str = "deterministic",
                       test_runs: int | None = None,
                       date: datetime.datetime | None = None) -> Path:
    """The logical scenario as an OpenSCENARIO ``ParameterValueDistribution`` over the
    template ``scenario_file`` (a path relative to ``path``'s folder).

    ``deterministic``: per space parameter a ``DistributionSet`` of its discretised values (with
    the space's decimals): the Cartesian product is the space, a tool enumerating it re-runs
    the sweep. ``stochastic``: each parameter as the space declares it (``normal`` ->
    ``NormalDistribution`` with variance sd^2 truncated to the parameter's domain, ``uniform``
    -> ``UniformDistribution``, ``integers`` and ``values`` -> equally weighted
    ``ProbabilityDistributionSet``; integer ranges over 10,000 values -> ``UniformDistribution``;
    a parameter the simulator reads as an integer, ``weather`` or ``ped_change_step``,
    declared ``uniform`` or ``normal`` -> a ``ProbabilityDistributionSet`` over the integers
    its draw can give, weighted by their probability, :func:`integer_draws`),
    ``test_runs`` draws (default: the space's size, at most 2**32 - 1), seeded with the space's
    seed. Not expressible there: the rounding to the declared decimals and the draw of one
    fixed value set per run.
    """
    from scenariogeneration import xosc

    if kind == "deterministic":
        dist = xosc.Deterministic()
        for p, n in enumerate(space.names):
            ds = xosc.DistributionSet()
            for v in space.table[p]:
                ds.add_value(analysis.format_value(space, p, v))
            dist.add_single_distribution(n, ds)
    elif kind == "stochastic":
        runs = min(int(test_runs or space.size), 2**32 - 1)
        dist = xosc.Stochastic(runs, float(space.seed))
        for par in space.parameters:
            a = par.args
            lo, hi = KNOWN_PARAMETERS.get(par.name, {"domain": (-math.inf, math.inf)})["domain"]
            if (draws := integer_draws(par)) is not None:  # weather, ped_change_step
                d = xosc.ProbabilityDistributionSet()
                for v, w in draws:
                    d.add_set(f"{v:d}", w)
            elif par.distribution == "normal":
                rng = xosc.Range(lo, hi) if math.isfinite(lo) and math.isfinite(hi) else None
                d = xosc.NormalDistribution(a[0], float(f"{a[1] ** 2:.12g}"), rng)
            elif par.distribution == "uniform":
                d = xosc.UniformDistribution(xosc.Range(a[0], a[1]))
            elif par.distribution == "integers" and a[1] - a[0] + 1 > 10_000:
                d = xosc.UniformDistribution(xosc.Range(a[0], a[1]))
            else:
                vals = (range(int(a[0]), int(a[1]) + 1) if par.distribution == "integers"
                        else a)
                d = xosc.ProbabilityDistributionSet()
                for v in vals:
                    d.add_set(f"{float(v):g}" if float(v).is_integer() else repr(float(v)),
                              1.0)
            dist.add_distribution(par.name, d)
    else:
        raise ValueError(f"kind {kind!r}: expected deterministic or stochastic")
    pvd = xosc.ParameterValueDistribution(
        f"jaxfalsify logical scenario '{space.name}' (seed {space.seed}, {space.size} "
        f"concrete scenarios), {kind}", "jaxfalsify", scenario_file, dist)
    pvd.header.creation_date = date  # None: now
    pvd.write_xml(str(path))
    return path


# ---------------------------------------------------------------- the export command
# what an export writes (and, with force, replaces), as globs for the CLI's check of --out
# (``critical_[0-9][0-9][0-9]*.xosc`` also covers 4-digit numbers) and as the exact names
EXPORT_FILES = ("crossing.xodr", "best.xosc", "critical_[0-9][0-9][0-9]*.xosc", "template.xosc",
                "logical.xosc", "logical_stochastic.xosc")
_EXPORT_NAME = re.compile(r"(crossing\.xodr|best\.xosc|critical_\d{3,}\.xosc|template\.xosc"
                          r"|logical\.xosc|logical_stochastic\.xosc)\Z")


def is_export_file(name: str) -> bool:
    """Whether ``name`` is a file name an export writes (``critical_001.xosc``, not a user's
    ``critical_mine.xosc``)."""
    return _EXPORT_NAME.match(name) is not None


def run_date(run_dir: Path) -> datetime.datetime:
    """The date an export's file headers carry: the run's completion (its ``summary.json``'s
    modification time, UTC, whole seconds), so exporting one run twice gives the same bytes."""
    mtime = (Path(run_dir) / "summary.json").stat().st_mtime
    return datetime.datetime.fromtimestamp(int(mtime), tz=datetime.timezone.utc)


def _check_out(out: Path, force: bool) -> None:
    """``out`` can take an export: a folder (or a path to one that can be created) that is
    not a result folder and, without ``force``, holds no file an export writes."""

    anc = next((a for a in (out, *out.parents) if a.exists() or a.is_symlink()), None)
    if anc is not None and not anc.is_dir():
        raise ValueError(f"{out}: {anc} exists and is not a folder" if anc != out
                         else f"{out} exists and is not a folder")
    if anc != out:
        return
    if (kind := folder_kind(out)) is not None:
        raise ValueError(f"{out} holds {with_article(kind)}; choose another folder")
    there = sorted(f.name for f in out.iterdir() if is_export_file(f.name))
    if there and not force:
        raise ValueError(f"{out} already holds {there[0]}"
                         f"{f' (and {len(there) - 1} more)' if len(there) > 1 else ''}; "
                         "pass force=True (--force) to replace an earlier export's files")
    odd = [n for n in there if (out / n).is_dir() and not (out / n).is_symlink()]
    if odd:
        raise ValueError(f"{out / odd[0]} is a folder: an export writes a file of that name")


def export(run_dir: Path, out: Path, which: str = "best", ego: str = "controller",
           force: bool = False) -> list[Path]:
    """Export the run's best scenario (``best``) or all its distinct critical ones
    (``critical``) to ``out``, the ego under the user's controller (``controller``) or
    replaying its simulated trajectory (``replay``), with ``crossing.xodr`` and the logical
    scenario (``logical.xosc``, ``logical_stochastic.xosc``); returns the files written:
    the road, the scenarios, (replay: ``template.xosc``, the controller-mode file the
    distributions vary), the two distributions.

    A file an export writes (:func:`is_export_file`, the names of ``EXPORT_FILES``) already
    in ``out`` is refused (ValueError naming it) unless ``force``, which replaces an earlier
    export's files (no stale ``critical_NNN.xosc`` stays beside a new ``best.xosc``); other
    files are left alone. Everything is written into a temporary folder inside ``out``, then
    moved in: a failed export leaves ``out`` as it was (a folder it created is removed). The
    file headers carry the run's date (:func:`run_date`): two exports of a run are identical."""
    if which not in SCENARIO_CHOICES:
        raise ValueError(f"--scenario {which!r}: expected best or critical")
    if ego not in EGO_MODES:
        raise ValueError(f"--ego {ego!r}: expected controller or replay")
    final = Path(out)
    _check_out(final, force)
    sp, rc, summary, ep = load_run(run_dir)
    check_simulated(run_dir, rc, "export")
    if which == "best":
        rows = [analysis.best(ep)]
    else:
        rows = [c["row"] for c in analysis.distinct_critical(*analysis.from_evaluations(ep, sp))]
        if not rows:
            raise ValueError(f"{run_dir}: the run found no critical scenario to export")
    date = run_date(run_dir)
    created = []  # the folders this export creates, deepest first (removed on failure)
    for a in (final, *final.parents):
        if a.exists():
            break
        created.append(a)
    final.mkdir(parents=True, exist_ok=True)
    try:
        with naming_errors(final), \
                tempfile.TemporaryDirectory(dir=final, prefix=".export-") as tmp:
            files = _write_export(Path(tmp), sp, rc, ep, rows, which, ego, date)
            replace_files(files, final, is_export_file)
    except BaseException:
        for a in created:
            try:
                a.rmdir()
            except OSError:
                break
        raise
    return [final / f.name for f in files]


def _write_export(out: Path, sp, rc, ep, rows, which: str, ego: str,
                  date: datetime.datetime | None = None) -> list[Path]:

    world = WORLD
    road = write_road(out / "crossing.xodr", world, date)
    idx = indices_of(ep, sp, rows)
    full = sp.scenario(idx)
    sut_params = dict(rc.sut_params)
    try:  # a SUT without a cruise target takes its request from its trajectory
        ego_request(rc.sut, sut_params, world)
        cruise = True
    except ValueError:
        cruise = False
    traj = (resimulate(sp, rc, ep, rows, world)
            if ego == "replay" or not cruise else None)
    fields = ("t", "ego_x", "ego_y", "ego_speed", "ego_accel", "ped_x", "ped_y", "valid")
    files = [road]
    template = None
    for k, row in enumerate(rows):
        tr = None if traj is None else {f: np.asarray(getattr(traj, f))[k] for f in fields}
        values = parameter_values(sp, idx[k])
        label = "best" if which == "best" else f"critical_{k + 1:03d}"
        title = f"{label} (evaluation {row + 1})"
        over = {n[4:]: float(values[n]) for n in sp.names if n.startswith("sut.")}
        req = ego_request(rc.sut, {**sut_params, **over}, world, tr)
        if ego == "replay":
            params = {n: float(np.asarray(full[n])[k]) for n in full}
            files.append(write_scenario(out / f"{label}.xosc", road.name, tr, params, world,
                                        title, values, date))
            if template is None:
                template = write_controller_scenario(out / "template.xosc", road.name, sp,
                                                     values, req, world, f"template ({title})",
                                                     date)
        else:
            files.append(write_controller_scenario(out / f"{label}.xosc", road.name, sp, values,
                                                   req, world, title, date))
    if template is not None:
        files.append(template)
    scenario_file = (template or files[1]).name
    files.append(write_distribution(out / "logical.xosc", sp, scenario_file, date=date))
    files.append(write_distribution(out / "logical_stochastic.xosc", sp, scenario_file,
                                    "stochastic", len(np.asarray(ep["reward"])), date))
    return files
