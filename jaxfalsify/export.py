"""OpenSCENARIO 1.x export of a run's concrete scenarios (``scenariogeneration``, host side).

Writes, per scenario, ``<name>.xosc`` (OpenSCENARIO 1.3) and one shared ``crossing.xodr``
(OpenDRIVE: the straight 4-lane road with a crosswalk object), so a found scenario replays in
esmini or CARLA ScenarioRunner:

* entities: the ego car (4.6 x 2.1 m box) and an adult pedestrian (0.5 x 0.6 m);
* init: both teleported to their start positions; the weather of the CARLA preset as an
  ``EnvironmentAction`` (cloudiness -> oktas, precipitation -> rain of up to 10 mm/h,
  sun altitude -> sun elevation, water deposits -> road wetness; friction unchanged as in CARLA);
* story: each actor follows its *simulated* trajectory (a timed polyline of every 0.1 s step,
  ``FollowTrajectoryAction`` with absolute timing), which carries the ego's start, its
  autopilot's speed profile and braking, and the pedestrian's speed profile;
* stop: the episode's end time (collision, distance travelled, or the 30 s horizon).

Road frame: our x + ``X_OFFSET`` along the road (OpenDRIVE's road starts at x = 0), y as ours
(left positive, the centre line at y = 0).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from jaxfalsify import weather as weather_lib
from jaxfalsify import analysis
from jaxfalsify.figures import indices_of, load_run

X_OFFSET = 30.0  # m: our x = -30 is the road's start
ROAD_LENGTH = 80.0  # m
OKTAS = ("zeroOktas", "oneOktas", "twoOktas", "threeOktas", "fourOktas", "fiveOktas",
         "sixOktas", "sevenOktas", "eightOktas")


def schema_path(kind: str = "xosc") -> Path:
    """The XSD that ships with scenariogeneration (OpenSCENARIO 1.3.1 / OpenDRIVE 1.7)."""
    import scenariogeneration

    base = Path(scenariogeneration.__file__).resolve().parent.parent / "schemas"
    return base / ("OpenSCENARIO_1_3_1.xsd" if kind == "xosc" else "opendrive_17_core.xsd")


def write_road(path: Path, world) -> Path:
    from scenariogeneration import xodr

    road = xodr.create_road(xodr.Line(ROAD_LENGTH), id=0, left_lanes=int(world.lanes_left),
                            right_lanes=int(world.lanes_right), lane_width=world.lane_width)
    road.add_object(xodr.Object(s=world.crosswalk_x + X_OFFSET, t=0.0,
                                Type=xodr.ObjectType.crosswalk, id="1", name="crosswalk",
                                width=world.road_left - world.road_right, length=3.0,
                                height=0.0, hdg=0.0))
    odr = xodr.OpenDrive("jaxfalsify_crossing")
    odr.add_road(road)
    odr.adjust_roads_and_lanes()
    odr.write_xml(str(path))
    return path


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


def write_scenario(path: Path, road_file: str, traj: dict, params: dict, world,
                   name: str) -> Path:
    """One ``.xosc`` for a simulated trajectory (fields ``(T,)`` of one scenario)."""
    from scenariogeneration import xosc

    v = traj["valid"]
    t = [round(float(x), 3) for x in traj["t"][v]]
    ego_pos = [xosc.WorldPosition(float(x) + X_OFFSET, float(y), 0.0, 0.0)
               for x, y in zip(traj["ego_x"][v], traj["ego_y"][v])]
    ped_pos = [xosc.WorldPosition(float(x) + X_OFFSET, float(y), 0.0, math.pi / 2)
               for x, y in zip(traj["ped_x"][v], traj["ped_y"][v])]

    entities = xosc.Entities()
    car_box = xosc.BoundingBox(world.ego_width, world.ego_length, 1.6, 0.0, 0.0, 0.8)
    axle_f = xosc.Axle(0.5, 0.65, 1.6, 1.4, 0.33)
    axle_r = xosc.Axle(0.0, 0.65, 1.6, -1.4, 0.33)
    entities.add_scenario_object("Ego", xosc.Vehicle("ego", xosc.VehicleCategory.car, car_box,
                                                     axle_f, axle_r, 50.0, 4.0, 9.0))
    ped_box = xosc.BoundingBox(world.ped_length, world.ped_width, 1.8, 0.0, 0.0, 0.9)
    entities.add_scenario_object("Pedestrian", xosc.Pedestrian(
        "adult", 80.0, xosc.PedestrianCategory.pedestrian, ped_box, model="adult"))

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
    desc = ", ".join(f"{k}={v:g}" for k, v in params.items())
    sce = xosc.Scenario(f"jaxfalsify {name}: {desc}", "jaxfalsify", xosc.ParameterDeclarations(),
                        entities, sb, xosc.RoadNetwork(roadfile=road_file), xosc.Catalog())
    sce.write_xml(str(path))
    return path


def export(run_dir: Path, out: Path, which: str = "best") -> list[Path]:
    """Export the run's best scenario (``best``) or all its distinct critical ones
    (``critical``) to ``out``; returns the files written."""
    import jaxfalsify as jf

    if which not in ("best", "critical"):
        raise ValueError(f"--scenario {which!r}: expected best or critical")
    sp, rc, summary, ep = load_run(run_dir)
    if which == "best":
        rows = [analysis.best(ep)]
    else:
        rows = [c["row"] for c in analysis.distinct_critical(*analysis.from_episodes(ep, sp))]
        if not rows:
            raise ValueError(f"{run_dir}: the run found no critical scenario to export")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    road = write_road(out / "crossing.xodr", jf.WORLD)
    full = sp.scenario(indices_of(ep, sp, rows))
    traj = jf.simulate(full, sut=rc.sut, sut_params=dict(rc.sut_params))
    files = [road]
    for k, row in enumerate(rows):
        tr = {f: np.asarray(getattr(traj, f))[k] for f in ("t", "ego_x", "ego_y", "ped_x",
                                                           "ped_y", "valid")}
        params = {n: float(np.asarray(full[n])[k]) for n in full}
        label = "best" if which == "best" else f"critical_{k + 1:03d}"
        files.append(write_scenario(out / f"{label}.xosc", road.name, tr, params, jf.WORLD,
                                    f"{label} (evaluation {row + 1})"))
    return files
