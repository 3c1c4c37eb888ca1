"""Host evaluators: a user's function that evaluates concrete scenarios outside JAX (their own
simulator, a co-simulation, hardware in the loop), run by a pool of worker processes or on a
Dask cluster, with a search of this project steering it (``jaxfalsify run --evaluator``).

**The evaluator** is ``module:attr`` (or ``path/to/file.py:attr``), a function of one batch::

    def evaluate(scenarios: dict[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]

``scenarios`` maps each space parameter's name to its ``(n,)`` float64 values, in the space's
units. It returns the requirement's robustness ``(n,)`` (negative: violated), or a dict with
``robustness`` and any of ``collision`` (bool: the failures searched for; default
``robustness < 0``) and the signals :data:`jaxfalsify.jobs.external.SIGNALS`. It runs in worker
processes (fresh interpreters that import it, never the user's script), so it must be
importable there: a module on the path, or a file.

**The pools** (:mod:`jaxfalsify.engine.pools`: local worker processes, or a Dask cluster with
``--scheduler tcp://host:8786``) hand out chunks of each batch, limit the time per scenario and
retry failed scenarios one by one; a scenario that still fails is recorded as failed
(``failed`` in ``evaluations.parquet``, listed in ``summary.json``), never dropped.

:func:`run` is the job: a :class:`jaxfalsify.jobs.external.Falsifier` asking, the pool
evaluating, checkpointed after every update and resumable; :func:`compare` runs strategies x
seeds through one pool.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from jaxfalsify import search
from jaxfalsify.base import config as cfg
from jaxfalsify.base.progress import Clock, Progress
from jaxfalsify.base.worker import (  # re-exported
    SIGNALS,
    EvaluatorError,
    call,
    dask_task,
    load,
)
from jaxfalsify.engine.lifecycle import Status
from jaxfalsify.engine.pools import (  # re-exported
    DaskPool,
    Pool,
    Results,
    check_settings,
    make_pool,
)
from jaxfalsify.engine.problem import RunConfig
from jaxfalsify.io import store
from jaxfalsify.io.files import write_atomic, write_json
from jaxfalsify.jobs import runs
from jaxfalsify.jobs.compare_stats import median
from jaxfalsify.jobs.external import Asked, Falsifier
from jaxfalsify.outputs.analysis import markdown_table
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "run", "pool_settings", "COMPARE_STRATEGIES", "compare", "compare_markdown", "Pool",
    "DaskPool", "Results", "make_pool", "check_settings", "load", "call", "SIGNALS",
    "EvaluatorError", "dask_task"
]


# ----------------------------------------------------------------------------- the job
def run(config: RunConfig, out: Path | str | None = None, *, workers: int | None = None,
        timeout: float | None = None, retries: int = 1, chunk: int | None = None,
        scheduler=None, resume: bool = False, force: bool = False,
        progress: Progress | None = None, stop: Callable[[], bool] | None = None,
        figures: bool = True):
    """``jaxfalsify run --evaluator``: a search steering the evaluator ``config.evaluator``
    run by a :class:`Pool` of ``workers`` (or a :class:`DaskPool` on ``scheduler``) until the
    budget is spent; returns the :class:`jaxfalsify.jobs.runs.RunOutcome`. Interrupted
    (``stop()`` true between updates, Ctrl-C, or an error), the run folder stays resumable
    (:class:`jaxfalsify.io.store.Interrupted` for a stop)."""
    if not config.evaluator or config.evaluator == "python":
        raise ValueError("run needs an evaluator module:attr (evaluator = 'python' is a "
                         "user's own ask/tell loop: jaxfalsify.Falsifier)")
    check_settings(workers, timeout, retries, chunk, scheduler)
    t = time.perf_counter()
    if scheduler is not None:
        config.build()  # every setting checked before connecting
    cluster = _load_or_connect(config.evaluator, workers, timeout, retries, chunk, scheduler)
    connecting = time.perf_counter() - t
    progress = progress or Progress()
    try:
        f = Falsifier.from_config(config, out, resume=resume, force=force, progress=progress)
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise
    f.status_extra["pool"] = {"workers": workers, "timeout": timeout, "retries": retries,
                              "scheduler": None if scheduler is None else str(scheduler)}
    try:
        t = time.perf_counter()
        pool = cluster if cluster is not None else make_pool(config.evaluator, workers,
                                                                 timeout, retries, chunk)
        f.clock.add("workers_start", connecting + time.perf_counter() - t)
        with pool:
            drive(f, pool, progress, stop)
    except KeyboardInterrupt:
        f.close()
        raise store.Interrupted("run", f.out, f.told, f.budget, "evaluations") from None
    except BaseException as e:
        f.close(error=e)  # resumable, and says what ended it
        raise
    return f.finish(figures=figures)


def _load_or_connect(spec: str, workers, timeout, retries, chunk, scheduler):
    """Before a folder or a worker exists: the evaluator loaded here (one line if it cannot
    be), or with ``scheduler`` the cluster's pool connected (a bad address leaves every folder
    as it was). The connected :class:`DaskPool`, or None for a local pool made later."""
    if scheduler is None:
        load(spec)
        return None
    return make_pool(spec, workers, timeout, retries, chunk, scheduler)


POOL_SETTINGS = ("workers", "timeout", "retries", "scheduler")


def pool_settings(resume_from: Path | str | None = None, **given) -> dict:
    """The pool's settings for :func:`run`: those ``given`` (None: not given); on a resume,
    the interrupted run's own (its ``status.json``) for the others; then the defaults
    (retries 1)."""
    out = {k: given.get(k) for k in POOL_SETTINGS}
    if resume_from is not None:
        try:
            earlier = json.loads((Path(resume_from) / "status.json").read_text()).get("pool")
        except (OSError, ValueError, AttributeError):
            earlier = None
        for k in POOL_SETTINGS:
            if out[k] is None and isinstance(earlier, dict):
                out[k] = earlier.get(k)
    if out["retries"] is None:
        out["retries"] = 1
    return out




def drive(f: Falsifier, pool, progress: Progress, stop=None) -> None:
    """Ask, evaluate on ``pool``, tell, until the budget is spent (KeyboardInterrupt when
    ``stop()`` is true between updates)."""
    while not f.done:
        if stop is not None and stop():
            raise KeyboardInterrupt
        asked = f.ask()
        t = time.perf_counter()
        res = pool.evaluate(asked.values)
        f.clock.add("evaluation", time.perf_counter() - t)
        tell_results(f, asked, res)
        for row, reason in sorted(res.errors.items())[:3]:
            progress.message(f"evaluation {int(asked.evaluation[row])} failed: {reason}")




COMPARE_STRATEGIES = ("reinforce/screened", "random", "cem")  # compare's default with an
# evaluator: the sample-efficient search against two cheap ones


def compare(evaluator: str, out: Path | str | None = None, *, strategies=COMPARE_STRATEGIES,
            seeds: int = 10, space: Any = "paper", space_seed: int = 0,
            evaluations: int | None = None, batch: int | None = None,
            strategy_params: dict | None = None, workers: int | None = None,
            timeout: float | None = None, retries: int = 1, scheduler=None,
            force: bool = False, progress: Progress | None = None, stop=None) -> dict:
    """``jaxfalsify compare --evaluator``: strategies x seeds against an external evaluator,
    one pool for all. There is no ground truth (the evaluator's space is not swept): per
    strategy the seeds that found a failure, evaluations, search seconds (ask + tell) and
    evaluation seconds to the first failure, distinct failures, failed evaluations. Each seed
    is a run folder ``OUT/runs/<strategy>-s<seed>/``; ``OUT/compare.json`` and ``compare.md``
    hold the table. Returns what ``compare.json`` holds."""
    check_settings(workers, timeout, retries, None, scheduler)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds must be an integer >= 1 (got {seeds!r})")
    strategy_params = dict(strategy_params or {})
    seen: dict[str, str] = {}
    for name in strategies:  # one row per strategy, as compare has it
        c = search.canonical(name)
        if c in seen:
            raise ValueError(f"strategies: {name!r} given twice"
                             + (f" ({seen[c]!r} names it too)" if seen[c] != name else ""))
        seen[c] = name
    for name in strategy_params:
        if name not in strategies:
            raise ValueError(f"strategy_params: {name!r} is not among the strategies "
                             f"({', '.join(strategies)})")
    configs = {name: RunConfig(space=space, space_seed=space_seed, strategy=name,
                               strategy_params=strategy_params.get(name, {}),
                               evaluations=evaluations, batch=batch, evaluator=evaluator)
               for name in strategies}
    for rc in configs.values():
        rc.build()  # every setting checked before anything is written
    clock = Clock(0.0)
    with clock("workers_start"):
        cluster = _load_or_connect(evaluator, workers, timeout, retries, None, scheduler)
    progress = progress or Progress()
    out = Path(out) if out is not None else Path("runs") / f"compare-{runs.timestamp()}"
    try:
        lk = store.open_folder(out, "compare", force=force)
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise
    rows = {}
    try:
        lk.claim("compare")
        if force:
            store.set_aside(out, "compare", extra=("runs",))  # its runs go with it
        out.mkdir(parents=True, exist_ok=True)
        first = configs[strategies[0]].resolved()
        doc = {"kind": "compare", "evaluator": sut_lib.recorded_spec(evaluator),
               "strategies": list(strategies), "seeds": seeds,
               "evaluations": first.evaluations if evaluations is None else evaluations,
               **({"batch": batch} if batch is not None else {}),
               "strategy_params": {k: dict(v) for k, v in strategy_params.items()},
               "pool": {k: v for k, v in (("workers", workers), ("timeout", timeout),
                                          ("retries", retries),
                                          ("scheduler", None if scheduler is None
                                           else str(scheduler))) if v is not None},
               "space": first.space}
        write_atomic(out / "config.toml", cfg.dumps_toml(doc))
        status = Status(out, "compare")
        status.running()
        with clock("workers_start"):
            pool = cluster if cluster is not None else make_pool(evaluator, workers,
                                                                 timeout, retries, None)
        cluster = None  # the pool's own block closes it from here
        with pool:
            for name, rc in configs.items():
                per_seed = []
                for seed in range(seeds):
                    rcs = dataclasses.replace(rc, seed=seed)
                    f = Falsifier.from_config(rcs, out / "runs" / f"{name.replace('/', '-')}"
                                              f"-s{seed}", force=force)
                    try:
                        progress.phase(f"{name}, seed {seed}")
                        drive(f, pool, progress, stop)
                    except BaseException:
                        f.close()
                        raise
                    o = f.finish(figures=False)
                    for phase in ("compile", "search", "evaluation", "checkpoint", "writing"):
                        clock.add(phase, o.timing.get(f"{phase}_seconds", 0.0))
                    per_seed.append(seed_row(seed, o, f))
                found = [r for r in per_seed if r["first_failure"] is not None]
                rows[name] = {
                    "batch": configs[name].build().strategy.batch,
                    "found": len(found), "seeds": seeds,
                    "first_failure_median": median(
                        [r["first_failure"] or r["evaluations"] + 1 for r in per_seed]),
                    "search_seconds_to_first_median": median(
                        [r["search_seconds_to_first"] for r in found]) if found else None,
                    "evaluation_seconds_to_first_median": median(
                        [r["evaluation_seconds_to_first"] for r in found]) if found else None,
                    "distinct_failures_median": median([r["distinct_failures"]
                                                         for r in per_seed]),
                    "failed_evaluations": sum(r["n_failed"] for r in per_seed),
                    "per_seed": per_seed}
        result = {"evaluator": doc["evaluator"], "space": configs[strategies[0]].build()
                  .space.name, "seeds": seeds, "strategies": rows}
        write_json(out / "compare.json", result, indent=2)
        write_atomic(out / "compare.md", compare_markdown(result))
        write_json(out / "timing.json", clock.summary(), indent=2)
        status.complete()
    except KeyboardInterrupt:
        Status(out, "compare").interrupted()
        raise store.Interrupted("compare", out, len(rows), len(configs), "strategies",
                                resumable=False) from None
    except BaseException as e:
        Status(out, "compare").failed(e)
        raise
    finally:
        if cluster is not None:
            cluster.close()
        lk.release()
    return result


def seed_row(seed: int, o, f: Falsifier) -> dict:
    """One seed of :func:`compare`: its first failure (evaluation, search and evaluation
    seconds to the end of its update), distinct failures and failed evaluations."""
    s = o.summary
    first = s["first_violation_evaluation"]
    u = None if first is None else (first - 1) // f.batch
    return {"seed": seed, "evaluations": s["evaluations"], "first_failure": first,
            "search_seconds_to_first": None if u is None
            else float(np.sum(f.search_seconds[:u + 1])),
            "evaluation_seconds_to_first": None if u is None
            else float(np.sum(f.evaluation_seconds[:u + 1])),
            "search_seconds": float(np.sum(f.search_seconds)),
            "evaluation_seconds": float(np.sum(f.evaluation_seconds)),
            "distinct_failures": s["n_distinct_critical"], "n_failed": s["n_failed"]}


def compare_markdown(result: dict) -> str:
    """``compare.md``: one row per strategy."""
    def num(x, fmt):
        return "-" if x is None else format(x, fmt)

    head = ["strategy", "batch", "found a failure", "evaluations to the first (median)",
            "search s to the first", "evaluation s to the first", "distinct failures (median)",
            "failed evaluations"]
    rows = [[name, str(r["batch"]), f"{r['found']}/{r['seeds']}",
             num(r["first_failure_median"], "g"),
             num(r["search_seconds_to_first_median"], ".3f"),
             num(r["evaluation_seconds_to_first_median"], ".3f"),
             num(r["distinct_failures_median"], "g"), str(r["failed_evaluations"])]
            for name, r in result["strategies"].items()]
    return "\n".join([f"# Strategies against the evaluator `{result['evaluator']}`", "",
                      f"Space {result['space']}, {result['seeds']} seeds; a seed without a "
                      "failure counts its budget + 1 in the median of evaluations; seconds "
                      "are medians over the seeds that found one.", "",
                      markdown_table(head, rows), ""])


def tell_results(f: Falsifier, asked: Asked, res: Results) -> None:
    """Tell a Falsifier a pool's results: failed scenarios as failed, and so is a scenario
    whose robustness or signal came back non-finite (its reason added to ``res.errors``)."""
    out = res.outputs
    failed = res.failed.copy()
    for k in ("robustness", *SIGNALS):
        if k not in out:
            continue
        bad = ~np.isfinite(out[k]) & ~failed
        if k == "min_ttc":
            bad &= ~np.isposinf(out[k])  # no approach: an infinite TTC is an answer
        for row in np.nonzero(bad)[0]:
            res.errors[int(row)] = f"returned {k} {out[k][row]}"
        failed |= bad
    res.failed[:] = failed
    rob = np.where(failed, 0.0, out.get("robustness", np.zeros(len(asked))))
    sig = {k: np.where(failed, 0.0, out[k]) for k in SIGNALS if k in out}
    traj = {k.split("/", 1)[1]: v for k, v in out.items() if k.startswith("trajectory/")}
    f.tell(asked, rob, out.get("collision"), signals=sig, failed=failed,
           trajectory=traj or None)
