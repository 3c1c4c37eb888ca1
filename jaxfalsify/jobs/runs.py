"""Falsification runs: the main job as a library call, ``execute(config, out, ...)``.

One concern: the main job (its configuration, folder, lifecycle and
closing lines).

A run folder holds:

* ``config.toml`` — everything resolved (the space's full description, the SUT's and the
  strategy's full parameter sets), so ``jaxfalsify run --config RUN/config.toml`` repeats it;
* ``status.json`` — ``running``, ``interrupted`` or ``complete``, and how to resume;
* ``checkpoint/`` — while the run is unfinished (see
  :class:`jaxfalsify.io.checkpoints.CampaignCheckpoint`);
* ``evaluations.parquet`` — every evaluated concrete scenario;
* ``summary.json`` — the run's outcome, bit-identical between runs of the same config and seed;
* ``critical.csv`` — the distinct collision scenarios found, ranked by reward, with their
  failure cluster (:func:`jaxfalsify.outputs.analysis.failure_clusters`);
* ``timing.json`` — wall time from start to exit, split into start-up, compile, search,
  writing and figures;
* ``figures/``, ``report.md`` (and ``best.rrd`` if asked).

``config.toml`` and ``status.json`` are written when the run starts, the results when it ends,
``status.json`` last. The CLI's ``jaxfalsify run`` only maps flags to a :class:`RunConfig` and
exceptions to exit codes; a Python user gets exactly the same folder from :func:`execute`.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from jaxfalsify.base import config as cfg
from jaxfalsify.base.progress import Clock, Progress, timing_line
from jaxfalsify.core.sim import WORLD
from jaxfalsify.engine import campaign, rundir
from jaxfalsify.engine.lifecycle import Status, sut_raised
from jaxfalsify.engine.problem import (  # the run's configuration
    SETTINGS,
    Built,
    RunConfig,
    configure,
)
from jaxfalsify.io import cache, checkpoints, store
from jaxfalsify.io.files import jsonable, write_atomic, write_json, write_parquet
from jaxfalsify.io.store import Interrupted
from jaxfalsify.outputs import analysis, figure_process
from jaxfalsify.outputs import figures as figures_lib
from jaxfalsify.outputs import replay as replay_lib
from jaxfalsify.outputs import report as report_lib
from jaxfalsify.scenario.space import Space

__all__ = [
    "RunConfig", "configure", "SETTINGS", "Interrupted",
    "evaluations_table", "CLUSTERS_LISTED", "summary_dict", "critical_csv", "restore",
    "STATE_COPIES", "check_strategy_memory", "RunOutcome", "execute", "redraw",
    "resume_config", "closing_report", "run_lines", "timestamp", "default_run_dir"
]


# ----------------------------------------------------------------------------- outputs
def evaluations_table(res: campaign.Result) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {"evaluation": res.evaluation, "update": res.update}
    for p, name in enumerate(res.space.names):
        cols[f"{name}_idx"] = res.indices[:, p]
    for p, name in enumerate(res.space.names):
        cols[name] = res.space.exact_values[p][res.indices[:, p]]
    cols.update(res.fields)
    return cols


CLUSTERS_LISTED = 20  # failure clusters summary.json describes (the largest)


def cluster_entries(space: Space, fc: analysis.FailureClusters, fields: dict,
                    most: int = CLUSTERS_LISTED) -> list[dict]:
    """The ``most`` largest failure clusters as ``summary.json`` lists them: per cluster its
    number, ``size`` (distinct critical scenarios), ``first_evaluation`` (1-based, the first
    evaluation of any member) and ``representative``, its best-reward member: ``params``
    (values), ``indices``, ``critical_rank`` (its row in ``critical.csv``), ``evaluation``
    (its first) and ``reward``."""
    out = []
    for c in range(min(fc.k, most)):
        j = int(fc.representative[c])
        row = int(fc.rows[j])
        out.append({"cluster": c + 1, "size": int(fc.sizes[c]),
                    "first_evaluation": int(fc.first_evaluation[c]),
                    "representative": {"params": space.values_at(fc.indices[j]),
                                       "indices": [int(i) for i in fc.indices[j]],
                                       "critical_rank": j + 1, "evaluation": row + 1,
                                       "reward": cfg.plain(np.asarray(fields["reward"])[row])}})
    return out


def summary_dict(res: campaign.Result, rc: RunConfig,
                 clusters: analysis.FailureClusters | None = None) -> dict:
    """``summary.json`` (``rc`` resolved): bit-identical for the same config and seed.
    ``clusters``: the run's failure clusters, when already computed."""
    b = analysis.best(res.fields)
    fc = clusters if clusters is not None else analysis.failure_clusters(res.indices, res.fields)
    best = {"params": res.space.values_at(res.indices[b]),
            "indices": [int(i) for i in res.indices[b]], "evaluation": b + 1,
            **{k: cfg.plain(res.fields[k][b]) for k in
               ("reward", "collision", "min_distance", "final_distance",
                "high_risk_share_second_half")}}
    return {"strategy": rc.strategy, "space": res.space.name, "space_seed": rc.space_seed,
            "sut": rc.sut, "sut_params": dict(rc.sut_params), "seed": rc.seed,
            "evaluations": res.n, "batch": rc.batch, "requirement": rc.requirement,
            "requirement_params": dict(rc.requirement_params),
            "first_collision_evaluation": analysis.first_collision(res.fields),
            "n_collisions": int(np.sum(analysis.collided(res.fields))),
            "first_violation_evaluation": analysis.first_critical(res.fields),
            "n_violations": int(np.sum(analysis.critical(res.fields))),
            "n_distinct_critical": fc.n, "n_failure_clusters": fc.k,
            "n_nonfinite": int(np.sum(res.fields["nonfinite"])),
            "best": best, "best_reached_evaluation": analysis.best_reached(res.fields),
            "learner_converged_evaluation": analysis.learner_converged(res.fields),
            "failure_clusters": cluster_entries(res.space, fc, res.fields),
            "failure_clusters_omitted": max(fc.k - CLUSTERS_LISTED, 0),
            "versions": cfg.versions()}


def critical_csv(res: campaign.Result,
                 clusters: analysis.FailureClusters | None = None) -> str:
    """``critical.csv``: one row per distinct critical scenario, ranked by reward, with its
    failure cluster (the number ``summary.json`` lists it under). ``clusters``: the run's
    failure clusters, when already computed."""
    buf = io.StringIO()
    w = csv.writer(buf)
    names = list(res.space.names)
    w.writerow(["rank", "cluster", *names, "reward", "min_distance",
                "high_risk_share_second_half", "first_evaluation", "times_evaluated"])
    fc = clusters if clusters is not None else analysis.failure_clusters(res.indices, res.fields)
    keys, rows, counts = analysis.distinct_critical_rows(res.indices, res.fields)
    values = [np.asarray(res.space.table[p], np.float64)[keys[:, p]].tolist()
              for p in range(len(names))]
    shown = [np.asarray(res.fields[f])[rows].tolist()
             for f in ("reward", "min_distance", "high_risk_share_second_half")]
    for i, (row, count) in enumerate(zip(rows.tolist(), counts.tolist())):
        w.writerow([i + 1, int(fc.labels[i]), *(f"{v[i]:g}" for v in values),
                    f"{shown[0][i]:.6f}", f"{shown[1][i]:.4f}", f"{shown[2][i]:.4f}",
                    row + 1, count])
    return buf.getvalue()


def fingerprint(rc: RunConfig, b: Built) -> dict:
    """What a checkpoint must have been written under: the resolved config, the plan, the
    code (jaxfalsify's, a user SUT's and strategy's files: :func:`jaxfalsify.io.cache.source_hash`)
    and the environment that changes results (:func:`jaxfalsify.engine.campaign.environment`: JAX's
    tracing settings, the backend and the local device count)."""
    code = cache.source_hash(b.sut.act, b.sut.init, type(b.strategy))
    return json.loads(json.dumps({"config": rc.to_toml(), "plan": list(b.plan), "code": code,
                                  "environment": campaign.environment()}))


def restore(ckpt: checkpoints.CampaignCheckpoint, b: Built, seed: int):
    """``(carry, records)`` saved in ``ckpt`` for this run (``(None, [])`` if none yet);
    raises :class:`~jaxfalsify.io.checkpoints.CheckpointError` if unusable."""
    template = campaign.carry_avals(b.space, b.sut, b.sut_params, b.strategy,
                                    b.strategy_params, b.plan, requirement=b.requirement,
                                    requirement_params=b.requirement_params)
    carry, records = ckpt.load(template)
    wants = [campaign.record_shapes(b.space, b.plan, c) for c in range(len(records))]
    if len(records) > b.plan.n_chunks or any(
            set(r) != set(want) or any(r[k].shape != want[k] for k in want)
            for r, want in zip(records, wants)):
        raise checkpoints.CheckpointError(f"checkpoint {ckpt.folder}: its records do not fit "
                                          "this run's plan")
    return carry, records


SCENARIO_BYTES = 2048  # device memory per scenario of a batch in flight (rollout state, XLA
                       # temporaries), measured generously


STATE_COPIES = 3  # a strategy's state, its updated copy and the gradients of its weights


def check_strategy_memory(b: Built, name: str, options: Mapping[str, Any]) -> None:
    """Refuse (one line) a strategy whose state (its size found by tracing ``start`` alone,
    without allocating it), counted three times (the state, its update, gradients), exceeds
    half the available memory: e.g. ``hidden=1024, learners=1024`` of ``reinforce/screened``,
    51 GiB of weights and Adam moments."""
    import jax

    # the key made inside the trace: a concrete one would start the backend, which must wait
    # for jax.distributed.initialize in a multi-process comparison
    state = jax.eval_shape(lambda: b.strategy.start(jax.random.key(0), b.strategy_params))
    need = sum(int(np.prod(x.shape)) * x.dtype.itemsize for x in jax.tree.leaves(state))
    given = ", ".join(f"{k}={v}" for k, v in sorted(options.items()))
    cfg.check_memory(STATE_COPIES * need, f"the state of {name}"
                     + (f" ({given})" if given else ""),
                     "choose smaller strategy options")


def check_memory(b: Built, config: RunConfig) -> None:
    """Refuse (one line) a strategy's state or a batch whose memory estimate exceeds half the
    available memory (``config``: the options as given, named in the message)."""
    check_strategy_memory(b, config.strategy, config.strategy_params)
    P = len(b.space.shape)
    per_eval = (P + len(campaign.RECORD_FIELDS)) * 8
    records = b.plan.updates_per_chunk * b.plan.batch * per_eval
    state = b.space.size * 4 if b.strategy.__class__.__name__ == "Grid" else 0
    cfg.check_memory(b.plan.batch * SCENARIO_BYTES + records + state,
                     f"a batch of {b.plan.batch} scenarios", "lower --batch")
    # every evaluation's record is kept on the host, then tabulated (twice the records)
    cfg.check_memory(b.plan.evaluations * per_eval * 2, f"{b.plan.evaluations} evaluations",
                     "lower --evaluations")



@dataclasses.dataclass
class RunOutcome:
    out: Path
    config: RunConfig  # resolved
    result: campaign.Result
    summary: dict
    timing: dict


def _stats_progress(progress: Progress, total: int, desc: str, start_from: int = 0):
    """The campaign's per-chunk callback: start the bar after the first (compiling) chunk and
    show the best reward and collisions so far."""
    state = {"best": -np.inf, "collisions": 0, "seen": 0, "started": False, "evals": 0}

    def update(done, records):
        for rec in records[state["seen"]:]:
            shape = rec["reward"].shape[1:]  # (S, U, B): one seed's evaluations in order
            first = state["evals"]
            state["evals"] += int(np.prod(shape))
            # the overflow of the last batch (past the budget) is discarded: not counted
            keep = (first + np.arange(int(np.prod(shape))) < total).reshape(shape)
            r = np.where(np.isnan(rec["reward"]) | ~keep, -np.inf, rec["reward"])
            state["best"] = max(state["best"], float(r.max()))
            state["collisions"] += int(np.sum(rec["collision"] & ~rec["nonfinite"] & keep))
        state["seen"] = len(records)
        if not state["started"]:
            progress.start(total, done, "eval", desc)
            state["started"] = True
        progress.update(done, best=f"{state['best']:.4f}", collisions=state["collisions"])

    return update


class _Preparing:
    """The figures' preparation (matplotlib, the compiled trajectory program, with
    ``critical`` the ground truth and the critical-region map) in a background thread: XLA
    compiles and runs without the GIL, so this overlaps the campaign's own compilation and
    search. A failure here is ignored (the figures redo the work)."""

    def __init__(self, b: Built, critical: bool = True):
        import threading

        self.result = None
        self.thread = threading.Thread(target=self._work, args=(b, critical), daemon=True,
                                       name="jaxfalsify-prepare-figures")
        self.thread.start()

    def _work(self, b: Built, critical: bool) -> None:
        try:
            self.result = figures_lib.prepare(b.space, b.sut, b.sut_params, WORLD,
                                              critical=critical)
        except Exception:  # noqa: BLE001 - make_figures repeats it and reports errors
            pass

    def join(self):
        """What :func:`jaxfalsify.outputs.figures.prepare` returned (None if it failed)."""
        self.thread.join()
        return self.result


def execute(config: RunConfig, out: Path | str | None, *, resume: bool = False,
            force: bool = False,
            progress: Progress | None = None, stop: Callable[[], bool] | None = None,
            figures: bool = True, rerun: bool = False, startup_seconds: float = 0.0
            ) -> RunOutcome:
    """Run a falsification campaign into the folder ``out``; the library form of
    ``jaxfalsify run``.

    Args:
      config: what to run (validated here: ValueError with one line on bad values).
      out: the run folder; None: a new folder ``runs/<time>-<strategy>`` (``-2``, ``-3``, ...
        appended when a run started in the same second has that name; ``RunOutcome.out``).
      resume: continue the unfinished run in ``out`` (its ``config.toml`` must equal
        ``config`` resolved; use :func:`resume_config` to read it).
      force: replace earlier results in ``out`` (complete ones set aside in ``.earlier/`` until
        this run completes: :func:`jaxfalsify.io.store.set_aside`).
      progress: a :class:`~jaxfalsify.base.progress.Progress` (default: silent).
      stop: checked between chunks; when it returns True the run commits its checkpoint,
        marks itself interrupted and raises :class:`Interrupted`. A KeyboardInterrupt does
        the same (at whatever point it lands, the checkpoint on disk stays consistent).
      figures: draw ``figures/`` and write ``report.md``.
      rerun: also write ``best.rrd``.
      startup_seconds: time spent before this call (process start-up), for ``timing.json``.
    Returns:
      :class:`RunOutcome` (results in memory, the summary and the timing written).
    Raises:
      ValueError (a :class:`~jaxfalsify.io.store.FolderError` or
      :class:`~jaxfalsify.io.checkpoints.CheckpointError` among them) before anything is written;
      :class:`Interrupted`.
    """
    cfg.check_type(config, RunConfig, "config")
    cache.check_settings()  # before anything is written
    cache.check_backend()

    clock = Clock(startup_seconds)
    progress = progress or Progress()
    if out is None and resume:
        raise ValueError("resume needs the run folder (out)")
    b = config.build()
    rc = config.resolved(b)
    check_memory(b, config)
    if out is None:
        out, lk = store.open_new_folder(default_run_dir(rc.strategy), "run")
        existed = False
    else:
        out = Path(out)
        existed = out.exists()
        lk = store.open_folder(out, "run", force=force, resume=resume)
    try:
        return _execute(b, rc, out, lk, resume, force, progress, stop, figures, rerun, clock)
    except BaseException as e:
        if not resume and (sut_raised(e) or store.nothing_written(out)):  # the SUT raised,
            store.discard(out, "run", lk, existed)  # or nothing written: nothing to keep
        raise
    finally:
        lk.release()


def _execute(b: Built, rc: RunConfig, out: Path, lk: store.FolderLock, resume: bool,
             force: bool, progress: Progress, stop, figures: bool, rerun: bool,
             clock: Clock) -> RunOutcome:
    lk.claim("run")  # the holder's pid is readable from the moment the lock is held
    ckpt = checkpoints.CampaignCheckpoint(out / "checkpoint", fingerprint(rc, b))
    resumed = None
    if resume:
        checkpoints.check_checkpoint_folder(ckpt.folder)
        on_disk = RunConfig.from_toml(out / "config.toml").resolved()
        if on_disk.to_toml() != rc.to_toml():
            raise checkpoints.CheckpointError(f"--resume {out}: config.toml does not match the "
                                              "run configuration given")
        resumed = restore(ckpt, b, rc.seed)
    start_from = b.plan.done_after(len(resumed[1])) if resumed else 0
    if resumed is None:
        if force:
            store.set_aside(out, "run")
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "config.toml", rc.to_toml())
    status = Status(out, "run")
    status.running(evaluations=b.plan.evaluations, resumed_from_evaluation=start_from)
    if start_from:
        progress.message(f"resuming {out} at evaluation {start_from} of {b.plan.evaluations}")
    # a second process draws the figures that need no trajectory, from its start (imports,
    # the critical-region map) on the core the compile and the writing leave idle
    helper = (figure_process.FigureProcess(b.space, rc, WORLD)
              if figures and figure_process.wanted() else None)
    try:
        return _search_and_finish(b, rc, out, ckpt, resumed, start_from, status, progress,
                                  stop, figures, rerun, clock, helper)
    finally:
        if helper is not None:
            helper.close()


def _search_and_finish(b: Built, rc: RunConfig, out: Path, ckpt, resumed, start_from: int,
                       status: Status, progress: Progress, stop, figures: bool, rerun: bool,
                       clock: Clock, helper) -> RunOutcome:
    try:
        t0 = time.perf_counter()
        progress.phase(f"compiling {rc.strategy} x {rc.sut} on {b.space.name}")
        campaign.program(campaign.Campaign(b.space.layout, b.sut, b.strategy,
                                           b.plan.updates_per_chunk, b.requirement),
                         campaign.args_for(b.space, b.sut_params, b.strategy_params, WORLD,
                                           b.plan.evaluations, b.requirement_params),
                         1)  # export (or load) the program
        clock.add("compile", time.perf_counter() - t0)
        # then, while XLA compiles it (without the GIL), prepare the figures in the background
        prep = _Preparing(b, critical=helper is None) if figures else None
        res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                           rc.seed, progress=_stats_progress(progress, b.plan.evaluations,
                                                             f"{rc.strategy} on {b.space.name}",
                                                             start_from),
                           requirement=b.requirement,
                           requirement_params=b.requirement_params,
                           checkpoint=ckpt, resumed=resumed, stop=stop)
        if stop is not None and stop():  # the signal came during the last chunk: commit
            raise campaign.Stopped(b.plan.n_chunks)
    except (campaign.Stopped, KeyboardInterrupt):
        progress.close()
        done = ckpt.evaluations_done()
        status.interrupted(evaluations_done=done, evaluations=b.plan.evaluations)
        raise Interrupted("run", out, done, b.plan.evaluations, "evaluations") from None
    except BaseException as e:
        progress.close()
        status.failed(e, evaluations_done=ckpt.evaluations_done(),  # the search failed
                      evaluations=b.plan.evaluations)
        raise
    progress.close()
    clock.add("compile", res.compile_seconds)
    clock.add("search", res.search_seconds)
    try:
        return _finish(b, rc, out, res, ckpt, start_from, prep, figures, rerun, progress, clock,
                       status, helper)
    except BaseException as e:
        status.failed(e, evaluations_done=res.n, evaluations=res.n)  # the search is done, its
        raise  # outputs are not


def _finish(b: Built, rc: RunConfig, out: Path, res: campaign.Result, ckpt, start_from: int,
            prep, figures: bool, rerun: bool, progress: Progress, clock: Clock,
            status: Status, helper=None) -> RunOutcome:
    """Write the results, figures, timing, and finally ``status.json`` = complete."""
    with clock("writing"):
        table = evaluations_table(res)
        if helper is not None:
            helper.draw(table)  # it draws while this process writes
        clusters = analysis.failure_clusters(res.indices, res.fields)
        summary = summary_dict(res, rc, clusters)
        write_parquet(out / "evaluations.parquet", table)
        write_atomic(out / "critical.csv", critical_csv(res, clusters))
        summary_text = json.dumps(jsonable(summary), indent=2) + "\n"
        write_atomic(out / "summary.json", summary_text)
    # the folder as rundir.load_run reads it back, without reading it back
    folder = rundir.RunFolder(b.space, rc, json.loads(summary_text), table)
    if figures:
        progress.phase("drawing figures")

        with clock("figures"):
            figures_lib.make_figures(out, world=WORLD, prepared=prep.join(),
                                     drawn_elsewhere=helper and helper.collect, folder=folder)
    if rerun:
        with clock("rerun"):
            replay_lib.record(out, "best", save=out / "best.rrd", overlay=14)
    if figures:  # report.md shows the wall time up to itself; timing.json includes it
        with clock("figures"):
            report_lib.write_report(out, timing={**clock.summary(),
                                                 "resumed_from_evaluation": start_from},
                                    folder=folder)
    timing = {**clock.summary(), "resumed_from_evaluation": start_from}
    write_json(out / "timing.json", timing, indent=2)
    status.complete(evaluations_done=res.n, evaluations=res.n)
    ckpt.remove()
    return RunOutcome(out, rc, res, summary, timing)


def redraw(run_dir: Path | str) -> tuple[list[Path], Path]:
    """``jaxfalsify figures RUN``: draw a finished run's ``figures/`` and ``report.md`` again,
    under the run folder's lock; a damaged, edited or blocked folder (a file where the
    ``figures`` folder goes, a folder named ``report.md``) is refused in one line before
    anything, the lock included, is written. Returns ``(figure paths, report path)``."""

    run_dir = Path(run_dir)
    rundir.load_run(run_dir)
    for name, folder in (("figures", True), ("report.md", False)):
        where = run_dir / name
        if where.exists() and where.is_dir() != folder:
            raise ValueError(f"{where} is {'not ' if folder else ''}a folder; move it away to "
                             "redraw the figures")
    with store.run_folder_lock(run_dir, "figures"):
        return figures_lib.make_figures(run_dir), report_lib.write_report(run_dir)


def resume_config(out: Path | str) -> RunConfig:
    """The configuration of the run in ``out`` (for ``execute(..., resume=True)``)."""
    out = Path(out)
    store.check_out(out, "run", resume=True)
    return RunConfig.from_toml(out / "config.toml")


def _all_failed(s: dict) -> bool:
    """Whether every evaluation of the run ``summary.json`` ``s`` describes failed (an
    evaluator's run: no scenario has a result)."""
    return s.get("n_failed", 0) >= s["evaluations"]


def closing_report(o: RunOutcome) -> str:
    """The best scenario beside a typical non-critical one (paper Table II layout) and the
    run's numbers."""
    res, s = o.result, o.summary
    table = []
    if not _all_failed(s):  # no scenario to show when every one failed
        head, rows = analysis.table_ii(res.space, res.indices, res.fields)
        table = [analysis.text_table(head, rows), ""]
    return "\n".join([*table, *run_lines(s),
                      f"wall time {timing_line(o.timing)} (from process start to exit)"])


def run_lines(s: dict) -> list[str]:
    """What a run found, in words (the closing report and report.md)."""
    req = s.get("requirement", "collision")
    if req == "evaluator":  # an external evaluator's failures: its flags or robustness < 0
        fv = s["first_violation_evaluation"]
        found = (f"{s['n_violations']} failures, {s['n_distinct_critical']} distinct critical "
                 f"scenarios{cluster_words(s)}, the first at evaluation {fv}; "
                 f"{s.get('n_failed', 0)} evaluations failed" if fv is not None else
                 f"no failure found; {s.get('n_failed', 0)} evaluations failed")
    elif req == "collision":
        fc = s["first_collision_evaluation"]
        found = (f"{s['n_collisions']} collisions, {s['n_distinct_critical']} distinct critical "
                 f"scenarios{cluster_words(s)}, the first at evaluation {fc}" if fc is not None
                 else "no collision found (the best scenario below is not critical)")
    else:
        fv = s["first_violation_evaluation"]
        found = (f"{s['n_violations']} violations of {req}, {s['n_distinct_critical']} distinct "
                 f"critical scenarios{cluster_words(s)}, the first at evaluation {fv}; "
                 f"{s['n_collisions']} collisions" if fv is not None else
                 f"no violation of {req} found (the best scenario below is not critical); "
                 f"{s['n_collisions']} collisions")
    conv = s.get("learner_converged_evaluation")
    best = (f"Best reward {s['best']['reward']:.4f}, first evaluated at "
            f"{s['best']['evaluation']}; the running best was within 1 % of it from evaluation "
            f"{s['best_reached_evaluation']}." if s["best_reached_evaluation"] is not None else
            f"No result: all {s['evaluations']} evaluations failed (each failure's reason "
            "is printed as it happens)." if _all_failed(s) else
            f"No finite reward: all {s['n_nonfinite']} evaluations non-finite (the SUT "
            "returned NaN or inf; see 'Numerical guards' in README).")
    return [f"{s['evaluations']} evaluations: {found}.", best,
            "Learner converged at evaluation " + (
                f"{conv} (from there its moving mean reward over 100 evaluations stays within "
                "5 % of the reward range of its final value)." if conv is not None else
                "- (too few evaluations to tell).")]


def cluster_words(s: dict) -> str:
    """`` in 7 failure clusters (largest 120)`` from a summary (empty for a summary without
    clusters)."""
    k = s.get("n_failure_clusters")
    if not k:
        return ""
    if k == 1:
        return " in 1 failure cluster"
    return f" in {k} failure clusters (largest {s['failure_clusters'][0]['size']})"


def timestamp() -> str:
    """The local time in default folder names, ``YYYYmmdd-HHMMSS``."""
    return time.strftime("%Y%m%d-%H%M%S")


def default_run_dir(strategy: str) -> Path:
    return Path("runs") / f"{timestamp()}-{strategy.replace('/', '-')}"
