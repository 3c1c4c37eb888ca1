"""Host evaluators: a user's function that evaluates concrete scenarios outside JAX (their own
simulator, a co-simulation, hardware in the loop), run by a pool of worker processes or on a
Dask cluster, with a search of this project steering it (``jaxfalsify run --evaluator``).

**The evaluator** is ``module:attr`` (or ``path/to/file.py:attr``), a function of one batch::

    def evaluate(scenarios: dict[str, np.ndarray]) -> np.ndarray | dict[str, np.ndarray]

``scenarios`` maps each space parameter's name to its ``(n,)`` float64 values, in the space's
units. It returns the requirement's robustness ``(n,)`` (negative: violated), or a dict with
``robustness`` and any of ``collision`` (bool: the failures searched for; default
``robustness < 0``) and the signals :data:`jaxfalsify.external.SIGNALS`. It runs in worker
processes (fresh interpreters that import it, never the user's script), so it must be
importable there: a module on the path, or a file.

**The pool** (:class:`Pool`) hands each idle worker a chunk of the batch, waits at most
``timeout`` seconds per scenario of the chunk, and on an exception, a timeout (the worker is
killed) or a worker that died retries the chunk's scenarios one by one, ``retries`` times;
a scenario that still fails is recorded as failed (``failed`` in ``evaluations.parquet``,
listed in ``summary.json``), never dropped. :class:`DaskPool` does the same on a Dask cluster
(``--scheduler tcp://host:8786``), whose workers may be on other machines.

:func:`run` is the job: a :class:`jaxfalsify.external.Falsifier` asking, the pool
evaluating, checkpointed after every update and resumable.
"""

from __future__ import annotations

import dataclasses
import json
import os
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any, Callable

import numpy as np

from jaxfalsify import runs, store
from jaxfalsify.external import Asked, Falsifier
from jaxfalsify.problem import RunConfig
from jaxfalsify.progress import Clock, Progress
from jaxfalsify.worker import (  # noqa: F401 - re-exported
    SIGNALS,
    EvaluatorError,
    call,
    dask_task,
    load,
)

WORKER = str(Path(__file__).with_name("worker.py"))  # a worker process runs this file

@dataclasses.dataclass
class Results:
    """One batch's results: ``outputs`` ``{name: (B,)}`` (NaN / False where failed),
    ``failed (B,)`` bool and ``errors`` ``{row: reason}`` of the failed ones."""

    outputs: dict[str, np.ndarray]
    failed: np.ndarray
    errors: dict[int, str]


def _assemble(B: int, done: dict[int, dict], errors: dict[int, str]) -> Results:
    keys = sorted({k for d in done.values() for k in d})
    outputs = {k: np.full(B, False) if k == "collision" else np.full(B, np.nan)
               for k in keys}
    for row, d in done.items():
        for k, v in d.items():
            outputs[k][row] = v
    failed = np.zeros(B, bool)
    failed[list(errors)] = True
    return Results(outputs, failed, errors)


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


class Pool:
    """Local worker processes evaluating batches (see the module's docstring).

    Args:
      spec: the evaluator's import path.
      workers: processes (default: the CPU cores this process may use).
      timeout: seconds allowed per scenario (None: no limit).
      retries: further tries of a scenario that failed alone: a failed chunk's scenarios are
        each tried alone, ``1 + retries`` times at most.
      chunk: scenarios per task (None: the batch split into about 4 tasks per worker).

    Workers run in their own process group (a Ctrl-C in the terminal reaches only this
    process, which stops them) and end by themselves when this process dies.
    """

    def __init__(self, spec: str, workers: int | None = None, timeout: float | None = None,
                 retries: int = 1, chunk: int | None = None):
        check_settings(workers, timeout, retries, chunk)
        self.spec, self.timeout, self.retries, self.chunk = spec, timeout, retries, chunk
        self.n = workers or _cores()
        self.procs: list[Any] = [None] * self.n
        self.conns: list[Any] = [None] * self.n
        self.restarts = 0
        try:
            for w in range(self.n):
                self._start(w)
            for w in range(self.n):
                self._ready(w)
        except BaseException:
            self.close()
            raise

    def _start(self, w: int) -> None:
        parent, child = socket.socketpair()
        p = subprocess.Popen([sys.executable, "-P", WORKER, str(child.fileno()),
                              str(os.getpid())], pass_fds=[child.fileno()],
                             stdin=subprocess.DEVNULL, process_group=0)
        child.close()
        conn = Connection(parent.detach())
        conn.send((self.spec, list(sys.path), os.getcwd()))
        self.procs[w], self.conns[w] = p, conn

    def _ready(self, w: int) -> None:
        try:
            tag, msg = self.conns[w].recv()
        except EOFError:
            code = self.procs[w].wait()
            raise EvaluatorError(f"evaluator '{self.spec}': its worker process ended while "
                                 f"loading it (exit code {code})") from None
        if tag == "load":
            raise EvaluatorError(msg)

    def _restart(self, w: int) -> None:
        self._stop(w)
        self.restarts += 1
        self._start(w)
        self._ready(w)

    def _stop(self, w: int) -> None:
        p, c = self.procs[w], self.conns[w]
        if p is not None:
            if p.poll() is None:
                p.kill()
            p.wait()
        if c is not None:
            c.close()
        self.procs[w] = self.conns[w] = None

    def evaluate(self, values: dict[str, np.ndarray]) -> Results:
        """Evaluate one batch ``{name: (B,)}``. Left early (an exception, Ctrl-C), the
        workers still busy are restarted, so no late reply reaches a later batch."""
        B = len(next(iter(values.values())))
        size = self.chunk or max(1, -(-B // (4 * self.n)))
        queue = [(list(range(s, min(s + size, B))), 0) for s in range(0, B, size)]
        done: dict[int, dict] = {}
        errors: dict[int, str] = {}
        busy: dict[int, tuple] = {}  # worker -> (rows, tries, deadline, tag)
        tag = 0

        def fail(rows, tries, reason):
            if len(rows) > 1:  # a chunk: its scenarios one by one, a first try each
                queue.extend(([r], 0) for r in rows)
            elif tries < self.retries:
                queue.append((rows, tries + 1))
            else:
                errors[rows[0]] = reason

        try:
            while queue or busy:
                for w in range(self.n):
                    if w not in busy and queue:
                        rows, tries = queue.pop(0)
                        tag += 1
                        try:
                            self.conns[w].send((tag, {k: v[rows] for k, v in values.items()}))
                        except OSError:  # the worker died while idle: a fresh one, no try
                            self._restart(w)  # counted
                            queue.insert(0, (rows, tries))
                            continue
                        limit = np.inf if self.timeout is None else self.timeout * len(rows)
                        busy[w] = (rows, tries, time.monotonic() + limit, tag)
                if not busy:  # a worker was replaced before its chunk went out: again
                    continue
                wait_s = min(d for _, _, d, _ in busy.values()) - time.monotonic()
                ready = wait([self.conns[w] for w in busy],
                             timeout=None if wait_s == np.inf else max(wait_s, 0.0))
                for w in list(busy):
                    rows, tries, deadline, sent = busy[w]
                    if self.conns[w] in ready:
                        try:
                            got, (status, payload) = self.conns[w].recv()
                        except (EOFError, OSError):  # the worker died
                            del busy[w]
                            code = self.procs[w].wait()
                            self._restart(w)
                            fail(rows, tries, f"the worker process died (exit code {code})")
                            continue
                        if got != sent:  # not this chunk's reply (cannot happen: a worker
                            continue     # left busy is restarted); wait for its own
                        del busy[w]
                        if status == "ok":
                            for j, r in enumerate(rows):
                                done[r] = {k: v[j] for k, v in payload.items()}
                        else:
                            fail(rows, tries, payload)
                    elif time.monotonic() >= deadline:
                        del busy[w]
                        self._restart(w)
                        fail(rows, tries, f"timed out after {self.timeout:g} s per scenario")
        finally:
            for w in list(busy):  # left early: its reply must not reach the next batch
                self._stop(w)
                try:
                    self._start(w)
                    self._ready(w)
                except Exception:  # noqa: BLE001 - the next evaluate finds it dead and says
                    pass
        return _assemble(B, done, errors)

    def close(self) -> None:
        """Stop every worker: an idle one is asked to end, and any still running after a
        shared second is killed."""
        for c in self.conns:
            if c is not None:
                try:
                    c.send(None)
                except (OSError, ValueError):
                    pass
        deadline = time.monotonic() + 1.0
        for w, p in enumerate(self.procs):
            if p is not None:
                try:
                    p.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
            self._stop(w)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class DaskPool:
    """The pool on a Dask cluster (``pip install "jaxfalsify[cluster]"``): each chunk a task
    submitted to ``scheduler`` (an address, or a ``distributed.Client``); chunks and retries
    as :class:`Pool`'s, a time limit per task (``timeout`` x its scenarios, from the moment
    the batch is submitted, so a queue longer than the cluster's threads counts against it).
    A task past its limit is cancelled and its scenarios recorded as failed, but Dask cannot
    stop a task that is running: a hung evaluation keeps its worker thread. Dask reschedules
    the tasks of a worker that died. The workers need jaxfalsify (its ``worker`` module runs
    the evaluator) and the evaluator's module."""

    def __init__(self, spec: str, scheduler, timeout: float | None = None, retries: int = 1,
                 chunk: int | None = None):
        check_settings(None, timeout, retries, chunk)
        try:
            import distributed
        except ImportError:
            raise EvaluatorError("the Dask backend needs the cluster extra: pip install "
                                 "'jaxfalsify[cluster]'") from None
        self.spec, self.timeout, self.retries, self.chunk = spec, timeout, retries, chunk
        self._own = not isinstance(scheduler, distributed.Client)
        try:
            self.client = distributed.Client(scheduler, timeout=30) if self._own else scheduler
        except (OSError, TimeoutError) as e:
            raise EvaluatorError(f"scheduler {scheduler}: cannot connect ({e})") from None
        self.n = max(1, sum(w.get("nthreads", 1) for w in
                            self.client.scheduler_info()["workers"].values()))
        self.restarts = 0

    def evaluate(self, values: dict[str, np.ndarray]) -> Results:
        from distributed import wait as dask_wait

        B = len(next(iter(values.values())))
        size = self.chunk or max(1, -(-B // (4 * self.n)))
        pending = [(list(range(s, min(s + size, B))), 0) for s in range(0, B, size)]
        done: dict[int, dict] = {}
        errors: dict[int, str] = {}
        while pending:
            t0 = time.monotonic()
            futures = {self.client.submit(dask_task, self.spec,
                                          {k: v[rows] for k, v in values.items()},
                                          pure=False): (rows, tries)
                       for rows, tries in pending}
            pending = []
            for f, (rows, tries) in futures.items():
                left = None if self.timeout is None else max(
                    0.0, t0 + self.timeout * len(rows) * -(-len(futures) // self.n)
                    - time.monotonic())
                try:
                    dask_wait([f], timeout=left)
                except TimeoutError:
                    pass
                if f.status == "finished":
                    status, payload = f.result()
                    if status == "load":
                        raise EvaluatorError(payload)
                else:
                    timed_out = not f.done()
                    f.cancel()
                    status = "error"
                    payload = (f"timed out after {self.timeout:g} s per scenario" if timed_out
                               else f"the task failed ({f.status})")
                if status == "ok":
                    for j, r in enumerate(rows):
                        done[r] = {k: v[j] for k, v in payload.items()}
                elif len(rows) > 1:
                    pending.extend(([r], 0) for r in rows)
                elif tries < self.retries:
                    pending.append((rows, tries + 1))
                else:
                    errors[rows[0]] = payload
        return _assemble(B, done, errors)

    def close(self) -> None:
        if self._own:
            self.client.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


# ----------------------------------------------------------------------------- the job
def run(config: RunConfig, out: Path | str | None = None, *, workers: int | None = None,
        timeout: float | None = None, retries: int = 1, chunk: int | None = None,
        scheduler=None, resume: bool = False, force: bool = False,
        progress: Progress | None = None, stop: Callable[[], bool] | None = None,
        figures: bool = True):
    """``jaxfalsify run --evaluator``: a search steering the evaluator ``config.evaluator``
    run by a :class:`Pool` of ``workers`` (or a :class:`DaskPool` on ``scheduler``) until the
    budget is spent; returns the :class:`jaxfalsify.runs.RunOutcome`. Interrupted
    (``stop()`` true between updates, Ctrl-C, or an error), the run folder stays resumable
    (:class:`jaxfalsify.store.Interrupted` for a stop)."""
    if not config.evaluator or config.evaluator == "python":
        raise ValueError("run needs an evaluator module:attr (evaluator = 'python' is a "
                         "user's own ask/tell loop: jaxfalsify.Falsifier)")
    check_settings(workers, timeout, retries, chunk)
    if scheduler is None:
        load(config.evaluator)  # here, in one line, before a folder or a worker exists
    progress = progress or Progress()
    f = Falsifier.from_config(config, out, resume=resume, force=force, progress=progress)
    f.status_extra["pool"] = {"workers": workers, "timeout": timeout, "retries": retries,
                              "scheduler": None if scheduler is None else str(scheduler)}
    try:
        t = time.perf_counter()
        pool = make_pool(config.evaluator, workers, timeout, retries, chunk, scheduler)
        f.clock.add("workers_start", time.perf_counter() - t)
        with pool:
            drive(f, pool, progress, stop)
    except KeyboardInterrupt:
        f.close()
        raise store.Interrupted("run", f.out, f.told, f.budget, "evaluations") from None
    except BaseException:
        f.close()
        raise
    return f.finish(figures=figures)


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


def make_pool(spec: str, workers=None, timeout=None, retries: int = 1, chunk=None,
              scheduler=None):
    """A :class:`Pool` of local workers, or a :class:`DaskPool` on ``scheduler``."""
    if scheduler is None:
        return Pool(spec, workers, timeout, retries, chunk)
    return DaskPool(spec, scheduler, timeout, retries, chunk)


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


def check_settings(workers, timeout, retries, chunk) -> None:
    """One-line ValueError for a bad pool setting."""
    for name, v, lo in (("workers", workers, 1), ("retries", retries, 0), ("chunk", chunk, 1)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < lo):
            raise ValueError(f"{name} must be an integer >= {lo} (got {v!r})")
    if timeout is not None and not (isinstance(timeout, (int, float)) and timeout > 0
                                    and np.isfinite(timeout)):
        raise ValueError(f"timeout must be a positive number of seconds (got {timeout!r})")


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
    from jaxfalsify import config as cfg
    from jaxfalsify.compare import _median

    check_settings(workers, timeout, retries, None)
    if isinstance(seeds, bool) or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"seeds must be an integer >= 1 (got {seeds!r})")
    strategy_params = dict(strategy_params or {})
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
    if scheduler is None:
        load(evaluator)
    progress = progress or Progress()
    out = Path(out) if out is not None else Path("runs") / f"compare-{runs.timestamp()}"
    lk = store.open_folder(out, "compare", force=force)
    rows = {}
    try:
        lk.claim("compare")
        if force:
            store.clear(out, "compare")
        out.mkdir(parents=True, exist_ok=True)
        doc = {"kind": "compare", "evaluator": sut_recorded(evaluator),
               "strategies": list(strategies), "seeds": seeds,
               "evaluations": evaluations or 0, "batch": batch or 0,
               "space": configs[strategies[0]].resolved().space}
        store.write_atomic(out / "config.toml", cfg.dumps_toml(doc))
        store.write_status(out, "compare", "running")
        clock = Clock(0.0)
        with make_pool(evaluator, workers, timeout, retries, None, scheduler) as pool:
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
                    per_seed.append(seed_row(seed, o, f))
                found = [r for r in per_seed if r["first_failure"] is not None]
                rows[name] = {
                    "batch": configs[name].build().strategy.batch,
                    "found": len(found), "seeds": seeds,
                    "first_failure_median": _median(
                        [r["first_failure"] or r["evaluations"] + 1 for r in per_seed]),
                    "search_seconds_to_first_median": _median(
                        [r["search_seconds_to_first"] for r in found]) if found else None,
                    "evaluation_seconds_to_first_median": _median(
                        [r["evaluation_seconds_to_first"] for r in found]) if found else None,
                    "distinct_failures_median": _median([r["distinct_failures"]
                                                         for r in per_seed]),
                    "failed_evaluations": sum(r["n_failed"] for r in per_seed),
                    "per_seed": per_seed}
        result = {"evaluator": doc["evaluator"], "space": configs[strategies[0]].build()
                  .space.name, "seeds": seeds, "strategies": rows}
        store.write_json(out / "compare.json", result, indent=2)
        store.write_atomic(out / "compare.md", compare_markdown(result))
        store.write_json(out / "timing.json", clock.summary(), indent=2)
        store.write_status(out, "compare", "complete")
    except KeyboardInterrupt:
        store.write_status(out, "compare", "interrupted")
        raise store.Interrupted("compare", out, len(rows), len(configs), "strategies",
                                resumable=False) from None
    finally:
        lk.release()
    return result


def sut_recorded(spec: str) -> str:
    from jaxfalsify import sut as sut_lib

    return sut_lib.recorded_spec(spec)


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
    from jaxfalsify.analysis import markdown_table

    def num(x, fmt):
        return "-" if x is None else format(x, fmt)

    head = ["strategy", "batch", "found a failure", "evaluations to the first (median)",
            "search s to the first", "evaluation s to the first", "distinct failures (median)",
            "failed evaluations"]
    rows = [[name, str(r["batch"]), f"{r['found']}/{r['seeds']}",
             num(r["first_failure_median"], ".0f"),
             num(r["search_seconds_to_first_median"], ".3f"),
             num(r["evaluation_seconds_to_first_median"], ".3f"),
             num(r["distinct_failures_median"], ".0f"), str(r["failed_evaluations"])]
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
    f.tell(asked, rob, out.get("collision"), signals=sig, failed=failed)
