"""rerun-sdk playback of concrete scenarios from a run folder (host side only).

Written for rerun-sdk >= 0.23 (``rr.set_time(..., duration=...)``, ``rr.Scalars``); tested with
0.41, whose reader is ``rerun.chunk.RrdReader`` (``rerun.dataframe`` is gone there).

Entities of a recording:

* ``world/road`` (static): road edges, lane lines; ``world/crosswalk`` (static);
* ``world/ego``, ``world/pedestrian``: boxes on the ``sim_time`` timeline; the ego is red while
  its SUT brakes; ``world/hazard_corridor`` and ``world/walker_grown_box``: the Traffic
  Manager's polygons (``carla-tm`` only: the car's geodesic boundary, its width, reaching one
  car length plus the speed-dependent extension ahead; the walker's box grown by 1.5 s x its
  speed on every side); ``world/collision``: a marker at the collision;
* ``metrics/distance`` (box gap, m), ``metrics/rss_distance`` (RSS safe distance, m),
  ``metrics/epsilon`` (the requirement's clash distance, 1 m), ``metrics/high_risk`` (1 red /
  0 green), ``metrics/ego_speed``, ``metrics/ped_speed`` (m/s): scalar series on ``sim_time``;
* ``info``: the scenario's parameters and outcome as a markdown document;
* ``training/reward``: the run's reward per evaluation, on the ``evaluation`` timeline;
* ``overlay/<k>/distance``: with several scenarios, each one's distance (the critical ones red:
  collisions, or the violations of the run's requirement), as in the paper's Fig. 9.

A blueprint puts the top view and the scenario's text beside three plots: the distance with
the RSS safe distance and the epsilon line, the speeds and the high-risk flag, the training
curve (or the overlay).

:func:`record_campaign` records the whole search instead, on the ``evaluation`` timeline:

* ``campaign/reward``, ``campaign/min_distance`` (m): one point per evaluated scenario;
  ``campaign/collision``: 1 for a collision, 0 otherwise; ``campaign/best``: the running best;
* ``campaign/params/<name>``: the value each evaluation chose, in the parameter's unit;
* ``campaign/probabilities/<name>``: per update, a bar chart over the parameter's values of
  the share of each value among the last ``window`` evaluations (the strategy's sampling
  distribution as its draws show it: exact for every strategy, whatever its internals).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from jaxfalsify.base.config import plain
from jaxfalsify.core import sim
from jaxfalsify.engine.rundir import check_simulated, indices_of, load_run, resimulate
from jaxfalsify.io import store
from jaxfalsify.io.files import write_atomic
from jaxfalsify.outputs import analysis
from jaxfalsify.scenario.space import SUT_PREFIX, is_sut_parameter
from jaxfalsify.suts import carla_tm
from jaxfalsify.suts import registry as sut_lib

__all__ = ["record", "record_campaign", "resolve_scenario"]

RED, GREEN, BLUE, GREY = (220, 40, 40), (40, 160, 60), (40, 90, 220), (150, 150, 150)


def resolve_scenario(spec: str, ep: dict, space) -> int:
    """Row of ``best``, ``critical:K`` (K-th distinct collision by reward, 1-based) or
    ``eval:N`` (evaluation number N)."""
    if spec == "best":
        return analysis.best(ep)
    kind, _, num = spec.partition(":")
    # ASCII digits without leading zeros: the recording is named after the spec, and eval:01
    # or another script's digits would name the same scenario's file differently
    if not re.fullmatch(r"[1-9][0-9]*", num):
        raise ValueError(f"--scenario {spec!r}: expected best, critical:K or eval:N (K, N "
                         "positive whole numbers in ASCII digits, no leading zeros)")
    n = int(num)
    if kind == "eval":
        if not 1 <= n <= len(ep["evaluation"]):
            raise ValueError(f"--scenario {spec}: the run has evaluations "
                             f"1..{len(ep['evaluation'])}")
        return n - 1
    if kind == "critical":
        crit = analysis.distinct_critical(*analysis.from_evaluations(ep, space))
        if not 1 <= n <= len(crit):
            raise ValueError(f"--scenario {spec}: the run found {len(crit)} distinct "
                             "critical scenarios")
        return crit[n - 1]["row"]
    raise ValueError(f"--scenario {spec!r}: expected best, critical:K or eval:N")


def _writing(run_dir: Path, save: Path | None, what: str):
    """The run folder's lock (:func:`jaxfalsify.io.store.run_folder_lock`) while a recording is
    written into it by default (no ``save``), taken once every input was checked; nothing
    for a file saved elsewhere."""
    import contextlib

    return store.run_folder_lock(run_dir, what) if not save else contextlib.nullcontext()


def record(run_dir: Path, scenario: str = "best", save: Path | None = None,
           spawn: bool = False, overlay: int = 0):
    """Write (or spawn a viewer with) a recording of one scenario of a run; returns the path
    (``RUN_DIR/replay-SCENARIO.rrd`` unless ``save``: written under the run folder's lock)."""
    import rerun as rr

    sp, rc, summary, ep = load_run(run_dir)
    check_simulated(run_dir, rc, "replay")
    row = resolve_scenario(scenario, ep, sp)
    if overlay > len(ep["reward"]):
        raise ValueError(f"--scenarios {overlay}: the run has {len(ep['reward'])} evaluations")
    rec = rr.RecordingStream("jaxfalsify", recording_id=f"{Path(run_dir).name}-{scenario}")
    if spawn:
        _spawn(rec)
        _log(rec, run_dir, scenario, overlay, sp, rc, summary, ep, row)
        return None
    path = Path(save) if save else Path(run_dir) / f"replay-{scenario.replace(':', '-')}.rrd"
    check_save_path(path)

    with _writing(run_dir, save, "replay"):
        _save(rec, path, lambda: _log(rec, run_dir, scenario, overlay, sp, rc, summary, ep,
                                      row))
    return path


def _save(rec, path: Path, log) -> None:
    """Record into memory, then write the bytes to ``path`` atomically: complete under its
    final name, or not at all, and a failed write (a full disk) is an OSError naming the
    path. (rerun's own file sink reports a write error on its thread and leaves a truncated
    file.)"""
    stream = rec.binary_stream()
    try:
        log()
    finally:  # drained and disconnected also when logging failed: rerun's stream, dropped
        # undrained while the error unwinds, blocks the process forever on its last flush
        data = stream.read(flush=True)
        rec.disconnect()
    write_atomic(path, data or b"")


def _log(rec, run_dir, scenario, overlay, sp, rc, summary, ep, row):
    """Everything a recording holds (see :func:`record`)."""
    import rerun as rr
    import rerun.blueprint as rrb

    w = sim.WORLD
    # rerun keeps a stream's time per recording id: a second recording of the same run and
    # scenario in one process would inherit the first one's last evaluation number
    rec.reset_time()
    # static world
    x0, x1 = -15.0, w.end_x + 10.0
    edges = [[[x0, w.road_right], [x1, w.road_right]], [[x0, w.road_left], [x1, w.road_left]]]
    lanes = [[[x0, y], [x1, y]] for y in np.arange(w.road_right + w.lane_width, w.road_left,
                                                    w.lane_width)]
    rec.log("world/road", rr.LineStrips2D(edges + lanes, colors=[GREY] * (2 + len(lanes))),
            static=True)
    rec.log("world/crosswalk", rr.Boxes2D(centers=[[w.crosswalk_x, 0.5 * (w.road_left
                                                                            + w.road_right)]],
                                          sizes=[[3.0, w.road_left - w.road_right]],
                                          colors=[(230, 230, 230)], labels=["crosswalk"]),
            static=True)

    traj = resimulate(sp, rc, ep, [row])
    tr = {k: np.asarray(v)[0] for k, v in vars(traj).items()}
    valid = tr["valid"]
    sc = sp.scenario(indices_of(ep, sp, [row]))
    corridor = _tm_polygons(rc, tr, w, sc) if rc.sut == "carla-tm" else None
    # the start (t = 0), then the state after each simulated step
    ex0, py0 = sim.start_positions(float(sc["ego_offset"][0]), float(sc["ped_offset"][0]), w)

    def actors(t, ego_x, ego_y, ped_x, ped_y, braking):
        rec.set_time("sim_time", duration=float(t))
        rec.log("world/ego", rr.Boxes2D(centers=[[ego_x, ego_y]],
                                        sizes=[[w.ego_length, w.ego_width]],
                                        colors=[RED if braking else BLUE], labels=["ego"]))
        rec.log("world/pedestrian", rr.Boxes2D(centers=[[ped_x, ped_y]],
                                               sizes=[[w.ped_length, w.ped_width]],
                                               colors=[(240, 160, 0)]))

    actors(0.0, ex0, w.ego_y, w.crosswalk_x, py0, False)
    for k in np.nonzero(valid)[0]:
        actors(tr["t"][k], tr["ego_x"][k], tr["ego_y"][k], tr["ped_x"][k], tr["ped_y"][k],
               bool(tr["braking"][k]))
        if corridor is not None:  # the Traffic Manager's polygons at this step
            for name, (x0, x1, y0, y1), color in zip(
                    ("hazard_corridor", "walker_grown_box"), corridor,
                    ((120, 120, 255, 80), (240, 160, 0, 60))):
                rec.log(f"world/{name}", rr.Boxes2D(
                    centers=[[(x0[k] + x1[k]) / 2, (y0[k] + y1[k]) / 2]],
                    sizes=[[x1[k] - x0[k], y1[k] - y0[k]]], colors=[color]))
        if tr["collided"][k]:
            rec.log("world/collision", rr.Points2D([[tr["ped_x"][k], tr["ped_y"][k]]],
                                                   radii=[0.6], colors=[RED],
                                                   labels=["collision"]))
        rec.log("metrics/distance", rr.Scalars(float(tr["distance"][k])))
        rec.log("metrics/rss_distance", rr.Scalars(float(tr["rss_distance"][k])))
        rec.log("metrics/epsilon", rr.Scalars(float(w.epsilon)))
        rec.log("metrics/high_risk", rr.Scalars(float(tr["high_risk"][k])),
                rr.SeriesPoints(colors=[RED if tr["high_risk"][k] else GREEN]))
        rec.log("metrics/ego_speed", rr.Scalars(float(tr["ego_speed"][k])))
        rec.log("metrics/ped_speed", rr.Scalars(float(tr["ped_speed"][k])))

    text = [f"## {scenario} — evaluation {row + 1} of run `{Path(run_dir).name}`", "",
            "| parameter | value |", "|---|---|"]
    text += [f"| {n} | {analysis.format_value(sp, p, ep[n][row])} {u} |"
             for p, (n, u) in enumerate(zip(sp.names, sp.units))]
    text += ["", "| outcome | value |", "|---|---|"]
    text += [f"| {f} | {format(plain(ep[f][row]), fmt)} |" for f, fmt in analysis.OUTCOME_ROWS]
    text += ["", f"SUT `{rc.sut}`, strategy `{rc.strategy}`, seed {rc.seed}"]
    rec.log("info", rr.TextDocument("\n".join(text), media_type="text/markdown"), static=True)

    rec.reset_time()  # each entity on its own timeline only: no sim_time on the training curve
    for e, r in zip(ep["evaluation"], ep["reward"]):
        rec.set_time("evaluation", sequence=int(e))
        rec.log("training/reward", rr.Scalars(float(r)))

    if overlay:
        rng = np.random.default_rng(0)
        rows = rng.choice(len(ep["reward"]), overlay, replace=False)
        ov = resimulate(sp, rc, ep, rows)
        rec.reset_time()  # and no evaluation number on the overlaid distances
        crit = analysis.critical(ep)  # the run's requirement's violations (or collisions)
        for j, r in enumerate(rows):
            color = RED if crit[r] else GREEN
            rec.log(f"overlay/{j}/distance", rr.SeriesLines(colors=[color],
                                                           names=[f"eval {r + 1}"]), static=True)
            v = np.asarray(ov.valid[j])
            for k in np.nonzero(v)[0]:
                rec.set_time("sim_time", duration=float(ov.t[j, k]))
                rec.log(f"overlay/{j}/distance", rr.Scalars(float(ov.distance[j, k])))

    for name, color in (("distance", BLUE), ("rss_distance", (230, 130, 0)), ("epsilon", RED)):
        rec.log(f"metrics/{name}", rr.SeriesLines(colors=[color], names=[name]), static=True)
    rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
        rrb.Vertical(rrb.Spatial2DView(origin="world", name="top view"),
                     rrb.TextDocumentView(origin="info", name="scenario")),
        rrb.Vertical(
            rrb.TimeSeriesView(origin="metrics",
                               name="distance vs RSS safe distance and epsilon (m)",
                               contents=["metrics/distance", "metrics/rss_distance",
                                         "metrics/epsilon"]),
            rrb.TimeSeriesView(origin="metrics", name="speeds (m/s) and high risk",
                               contents=["metrics/ego_speed", "metrics/ped_speed",
                                         "metrics/high_risk"]),
            rrb.TimeSeriesView(origin="overlay" if overlay else "training",
                               name="overlay: distance (m)" if overlay else
                               "training: reward per evaluation")))))
    rec.flush()


def record_campaign(run_dir: Path, save: Path | None = None, spawn: bool = False,
                    window: int = 200):
    """Write (or spawn a viewer with) a recording of a run's whole search, every evaluation on
    the ``evaluation`` timeline (entities: see the module docstring); returns the path
    (``RUN_DIR/campaign.rrd`` unless ``save``: written under the run folder's lock).

    ``window``: evaluations behind each bar chart of the sampling distribution."""
    import rerun as rr

    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be a positive integer (got {window!r})")
    sp, rc, summary, ep = load_run(run_dir)
    check_simulated(run_dir, rc, "replay")
    rec = rr.RecordingStream("jaxfalsify", recording_id=f"{Path(run_dir).name}-campaign")
    if spawn:
        _spawn(rec)
        _log_campaign(rec, sp, ep, window)
        return None
    path = Path(save) if save else Path(run_dir) / "campaign.rrd"
    check_save_path(path)

    with _writing(run_dir, save, "replay"):
        _save(rec, path, lambda: _log_campaign(rec, sp, ep, window))
    return path


def sampling_shares(idx: np.ndarray, n: int) -> np.ndarray:
    """Share of each of ``n`` values among the indices ``idx`` ``(k,)``: ``(n,)`` summing to 1."""
    return np.bincount(np.asarray(idx, np.int64), minlength=n)[:n] / max(len(idx), 1)


def _log_campaign(rec, sp, ep, window: int) -> None:
    import rerun as rr
    import rerun.blueprint as rrb

    evals = np.asarray(ep["evaluation"], np.int64)
    reward = np.asarray(ep["reward"], np.float64)
    best = np.maximum.accumulate(np.where(np.isfinite(reward), reward, -np.inf))
    rec.reset_time()  # (see _log)
    for j, e in enumerate(evals):
        rec.set_time("evaluation", sequence=int(e))
        rec.log("campaign/reward", rr.Scalars(float(reward[j])))
        rec.log("campaign/best", rr.Scalars(float(best[j])))
        rec.log("campaign/min_distance", rr.Scalars(float(ep["min_distance"][j])))
        rec.log("campaign/collision", rr.Scalars(float(bool(ep["collision"][j]))),
                rr.SeriesPoints(colors=[RED if ep["collision"][j] else GREEN]))
        for n in sp.names:
            rec.log(f"campaign/params/{n}", rr.Scalars(float(ep[n][j])))
    # the sampling distribution, at the last evaluation of every update
    updates = np.asarray(ep["update"], np.int64)
    ends = np.nonzero(np.r_[updates[1:] != updates[:-1], True])[0]
    for j in ends:
        rec.set_time("evaluation", sequence=int(evals[j]))
        lo = max(0, j + 1 - window)
        for p, n in enumerate(sp.names):
            values = np.asarray(sp.table[p], np.float64)
            rec.log(f"campaign/probabilities/{n}", rr.BarChart(
                sampling_shares(ep[f"{n}_idx"][lo:j + 1], len(values)), abscissa=values))
    rec.send_blueprint(rrb.Blueprint(rrb.Horizontal(
        rrb.Vertical(rrb.TimeSeriesView(origin="campaign", name="reward, running best",
                                        contents=["campaign/reward", "campaign/best"]),
                     rrb.TimeSeriesView(origin="campaign", name="min distance (m), collision",
                                        contents=["campaign/min_distance",
                                                  "campaign/collision"]),
                     rrb.TimeSeriesView(origin="campaign/params", name="parameter values")),
        rrb.Grid(*[rrb.BarChartView(origin=f"campaign/probabilities/{n}",
                                    name=f"{n} ({u}): share of the last {window} draws")
                   for n, u in zip(sp.names, sp.units)]))))
    rec.flush()


def _spawn(rec) -> None:
    """Open a rerun viewer for ``rec``; ValueError (one line) when none can be started."""
    try:
        rec.spawn()
    except RuntimeError as e:
        raise ValueError(f"--spawn: {e} (install rerun-sdk's viewer on PATH, or --save a "
                         ".rrd file and open it with `rerun FILE.rrd`)") from None


def check_save_path(path: Path) -> Path:
    """A writable place for ``path`` (a .rrd file): its folder exists and can be written, it
    is not a folder itself. Returns the path."""
    import tempfile

    path = Path(path)
    if path.suffix != ".rrd":
        raise ValueError(f"--save {path}: the file name must end in .rrd")
    if path.is_dir():
        raise ValueError(f"--save {path}: is a folder")
    parent = path.parent
    if not parent.is_dir():
        raise ValueError(f"--save {path}: no folder {parent}")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise ValueError(f"--save {path}: cannot write in {parent} ({e.strerror})") from None
    return path


def _tm_polygons(rc, tr: dict, w, scenario: dict | None = None) -> tuple:
    """carla-tm's geodesic corridor and the walker's grown box at every recorded step, as
    ``(x0, x1, y0, y1)`` arrays (the SUT's own geometry, ``suts.carla_tm.tm_polygons``), with the
    SUT parameters the scenario ran with: the run's ``sut_params`` and the scenario's
    ``sut.NAME`` values (``scenario``: one scenario's parameters, scalars or arrays of one
    value), as ``rundir.resimulate`` simulates it."""

    s = sut_lib.resolve(rc.sut)
    over = {k[len(SUT_PREFIX):]: float(np.asarray(v).reshape(-1)[0])
            for k, v in (scenario or {}).items() if is_sut_parameter(k)}
    params = sut_lib.with_params(s, {**dict(rc.sut_params), **over})
    n = len(tr["t"])
    full = lambda v: np.full(n, v, np.float32)  # noqa: E731
    obs = sut_lib.Observation(
        t=tr["t"], dt=full(w.dt), ego_x=tr["ego_x"], ego_y=tr["ego_y"], ego_speed=tr["ego_speed"],
        ego_length=full(w.ego_length), ego_width=full(w.ego_width), ped_x=tr["ped_x"],
        ped_y=tr["ped_y"], ped_vx=full(0.0), ped_vy=tr["ped_speed"],
        ped_length=full(w.ped_length), ped_width=full(w.ped_width),
        road_right=full(w.road_right), road_left=full(w.road_left), weather=full(0))
    _, geo, walker = carla_tm.tm_polygons(obs, params)
    return tuple(tuple(np.asarray(a) for a in poly) for poly in (geo, walker))
