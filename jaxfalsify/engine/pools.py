"""Worker pools that evaluate batches of concrete scenarios with a user's host evaluator:
:class:`Pool` (local worker processes) and :class:`DaskPool` (a Dask cluster). Each hands out
chunks of a batch, limits the time per scenario, retries failed scenarios one by one and
returns every scenario's outputs or the reason it failed (:class:`Results`). The job that
steers them is :mod:`jaxfalsify.jobs.evaluators`; the worker process is
:mod:`jaxfalsify.base.worker`."""

from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
import time
from multiprocessing.connection import Connection, wait
from pathlib import Path
from typing import Any

import numpy as np

from jaxfalsify.base.worker import EvaluatorError, dask_task

__all__ = ["Results", "Pool", "DaskPool", "make_pool", "check_settings"]

WORKER = str(Path(__file__).parents[1] / "base" / "worker.py")  # a worker process runs it

@dataclasses.dataclass
class Results:
    """One batch's results: ``outputs`` ``{name: (B,)}`` (NaN / False where failed),
    ``failed (B,)`` bool and ``errors`` ``{row: reason}`` of the failed ones."""

    outputs: dict[str, np.ndarray]
    failed: np.ndarray
    errors: dict[int, str]


def _assemble(B: int, done: dict[int, dict], errors: dict[int, str]) -> Results:
    keys = sorted({k for d in done.values() for k in d})
    longest = max((np.size(v) for d in done.values() for k, v in d.items()
                   if k.startswith("trajectory/")), default=0)
    steps = {k: longest for k in keys if k.startswith("trajectory/")}  # one T for every
    # history (chunks may differ in T and in the histories they return: NaN-padded)
    outputs = {k: np.full((B, steps[k]), np.nan) if k in steps else
               np.full(B, False) if k == "collision" else np.full(B, np.nan) for k in keys}
    for row, d in done.items():
        for k, v in d.items():
            if k in steps:
                outputs[k][row, :np.size(v)] = v
            else:
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
        self.n = workers or min(_cores(), MAX_WORKERS)
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
        except (OSError, TimeoutError, ValueError) as e:
            raise EvaluatorError(f"scheduler {scheduler!r}: cannot connect ({e})") from None
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


MAX_WORKERS = 256  # evaluator processes on one machine (each its own interpreter and pipes)
MAX_RETRIES = 100  # further tries of a failing scenario


def make_pool(spec: str, workers=None, timeout=None, retries: int = 1, chunk=None,
              scheduler=None):
    """A :class:`Pool` of local workers, or a :class:`DaskPool` on ``scheduler``."""
    if scheduler is None:
        return Pool(spec, workers, timeout, retries, chunk)
    return DaskPool(spec, scheduler, timeout, retries, chunk)


def check_settings(workers, timeout, retries, chunk, scheduler=None) -> None:
    """One-line ValueError for a bad pool setting."""
    if isinstance(scheduler, str) and not scheduler.strip():
        raise ValueError(f"scheduler must be an address such as tcp://host:8786 (got "
                         f"{scheduler!r})")
    for name, v, lo, hi in (("workers", workers, 1, MAX_WORKERS),
                            ("retries", retries, 0, MAX_RETRIES), ("chunk", chunk, 1, 1 << 24)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < lo):
            raise ValueError(f"{name} must be an integer >= {lo} (got {v!r})")
        if v is not None and v > hi:  # a process (and its pipes) per worker: memory, files
            raise ValueError(f"{name} must be at most {hi} (got {v})")
    if timeout is not None and not (isinstance(timeout, (int, float)) and timeout > 0
                                    and np.isfinite(timeout)):
        raise ValueError(f"timeout must be a positive number of seconds (got {timeout!r})")
