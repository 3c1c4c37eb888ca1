"""Falsifying a system that lives outside JAX: ask / tell.

One concern: ask / tell for systems outside JAX (:class:`Falsifier` and
its run folder).

The search stays jitted; only the evaluation happens on the host, in the user's loop::

    f = jaxfalsify.Falsifier("paper", strategy="reinforce/screened", seed=0, out="runs/mine")
    while not f.done:
        asked = f.ask()                      # a batch of concrete scenarios (Asked)
        rob = my_simulator(asked.values)     # the requirement's robustness, one per scenario
        f.tell(asked, rob)                   # collision / signals / failed: optional
    outcome = f.finish()                     # the run folder's results, figures, report

:class:`Falsifier` writes the same run folder as ``jaxfalsify run`` (``config.toml`` with
``evaluator = "python"``, ``status.json``, ``evaluations.parquet``, ``summary.json``,
``critical.csv``, ``figures/``, ``report.md``), commits a checkpoint after every told update,
and resumes after a crash of the user's loop (``Falsifier(..., out=folder, resume=True)``): the
next batch asked is the one that was being evaluated, the same scenarios.

The strategy sees exactly what a built-in campaign shows it (:func:`jaxfalsify.engine.campaign
.make_campaign`): the same keys, the reward (the ``reward`` signal; by default the negated
robustness), the robustness, the violations (robustness < 0) and, when given, the minimum
time-to-collision. So an evaluator that returns the built-in simulator's outcomes gives the
built-in run's scenarios, update after update.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.base.progress import Clock, Progress
from jaxfalsify.base.worker import SIGNALS, first_non_flag, shown, trajectory_arrays
from jaxfalsify.core import sim
from jaxfalsify.engine import campaign
from jaxfalsify.engine.lifecycle import Status, error_text
from jaxfalsify.engine.problem import RunConfig
from jaxfalsify.io import cache, checkpoints, store
from jaxfalsify.io.files import save_npz, write_atomic, write_json, write_parquet
from jaxfalsify.jobs import runs
from jaxfalsify.outputs import figures as figures_lib
from jaxfalsify.outputs import report as report_lib

__all__ = ["Asked", "Falsifier", "summary_dict"]

TRAJECTORIES = "trajectories.npz"  # an evaluator's run: the trajectories it told


@dataclasses.dataclass(frozen=True)
class Asked:
    """One batch of concrete scenarios to evaluate.

    Attributes:
      update: the update it belongs to (0-based).
      evaluation: ``(B,)`` int64 evaluation numbers (1-based; past the budget: not counted).
      indices: ``(B, P)`` int32 each scenario's value indices in the space.
      values: ``{name: (B,) float64}`` the concrete values, in the space's units.
      units: ``{name: unit}``.
    """

    update: int
    evaluation: np.ndarray
    indices: np.ndarray
    values: dict[str, np.ndarray]
    units: dict[str, str]

    def __len__(self) -> int:
        return len(self.evaluation)

    def rows(self) -> list[dict[str, float]]:
        """One dict per scenario: ``evaluation`` and each parameter's value."""
        return [{"evaluation": int(e), **{n: float(v[i]) for n, v in self.values.items()}}
                for i, e in enumerate(self.evaluation)]


class Falsifier:
    """A search driven from the host: :meth:`ask` a batch, evaluate it anywhere, :meth:`tell`
    the results; :meth:`finish` writes the run's results.

    Args:
      space: a built-in space name, a TOML path or a space description table.
      strategy: a strategy name (default ``reinforce/screened``, the sample-efficient one:
        an external system's evaluation usually costs far more than the search).
      strategy_params, batch, evaluations, seed, space_seed: as :class:`jaxfalsify.RunConfig`'s
        (a checkpoint is committed after every update).
      out: the run folder (None: ``runs/<time>-<strategy>``).
      resume: continue the unfinished run in ``out`` (the same settings).
      force: replace earlier results in ``out`` (complete ones set aside in ``.earlier/`` until
        this run completes: :func:`jaxfalsify.io.store.set_aside`).
      evaluator: what config.toml records as the evaluator (``python``: this loop).
      progress: a :class:`~jaxfalsify.base.progress.Progress`.
    Raises:
      ValueError (one line) on bad settings or a folder that cannot be used, before anything
      is written.
    """

    def __init__(self, space: Any = "paper", *, strategy: str = "reinforce/screened",
                 strategy_params: Mapping[str, Any] | None = None, batch: int | None = None,
                 evaluations: int | None = None, seed: int = 0, space_seed: int = 0,
                 out: Path | str | None = None,
                 resume: bool = False, force: bool = False, evaluator: str = "python",
                 progress: Progress | None = None):
        config = RunConfig(space=space, space_seed=space_seed, strategy=strategy,
                           strategy_params=dict(strategy_params or {}), batch=batch,
                           evaluations=evaluations, seed=seed, evaluator=evaluator)
        self._open(config, out, resume, force, progress)

    @classmethod
    def from_config(cls, config: RunConfig, out: Path | str | None = None, *,
                    resume: bool = False, force: bool = False,
                    progress: Progress | None = None) -> "Falsifier":
        """A Falsifier for a :class:`RunConfig` whose ``evaluator`` is set."""
        if not isinstance(config, RunConfig) or not config.evaluator:
            raise ValueError("Falsifier.from_config needs a RunConfig with an evaluator")
        self = cls.__new__(cls)
        self._open(config, out, resume, force, progress)
        return self

    # ------------------------------------------------------------------ set-up
    def _open(self, config, out, resume, force, progress):
        cache.check_settings()
        self.clock = Clock(0.0)
        self.progress = progress or Progress()
        if out is None and resume:
            raise ValueError("resume needs the run folder (out)")
        b = config.build()
        self.built, self.config = b, config.resolved(b)
        self.space, self.strategy = b.space, b.strategy
        self.batch, self.budget = b.strategy.batch, b.plan.evaluations
        self.n_updates = b.plan.n_updates
        if out is None:
            out, self._lock = store.open_new_folder(runs.default_run_dir(self.config.strategy),
                                                    "run")
        else:
            out = Path(out)
            try:
                self._lock = store.open_folder(out, "run", force=force, resume=resume)
            except store.FolderError as e:
                if config.evaluator != "python":
                    raise
                raise store.FolderError(_python_words(str(e), out)) from None
        self.out = out
        self._finished = False
        self.status_extra: dict = {}  # more for status.json (the pool's settings)
        try:
            self._lock.claim("run")
            self._start(resume, force)
        except BaseException:
            self._lock.release()
            raise

    def _start(self, resume: bool, force: bool) -> None:
        b, rc, strat = self.built, self.config, self.strategy
        params = jax.tree.map(lambda x: np.asarray(x, np.float32), b.strategy_params)

        def init(key_data):
            k_init, _, k_run = jax.random.split(jax.random.wrap_key_data(key_data), 3)
            return {"state": strat.start(k_init, params), "key": k_run}

        def ask(carry):
            key, k_ask, k_tell = jax.random.split(carry["key"], 3)
            idx, state = strat.ask(k_ask, carry["state"], params)
            return idx, {"state": state, "key": key}, k_tell

        def tell(carry, k_tell, idx, r, rob, violated, ttc):
            state = strat.tell_outcome(k_tell, carry["state"], idx, r, rob, violated, params,
                                       ttc=ttc)
            return {"state": state, "key": carry["key"]}

        self._ask, self._tell = jax.jit(ask), jax.jit(tell)
        key_data = np.asarray(jax.random.key_data(jax.random.wrap_key_data(
            sim.seed_key_data(rc.seed))))
        template = jax.eval_shape(init, key_data)
        self._treedef = jax.tree.structure(template)
        self._is_key = [campaign.is_key(x) for x in jax.tree.leaves(template)]
        self.ckpt = checkpoints.CampaignCheckpoint(self.out / "checkpoint", self._fingerprint())
        self.records: list[dict[str, np.ndarray]] = []
        carry = None
        if resume:
            checkpoints.check_checkpoint_folder(self.ckpt.folder)
            on_disk = RunConfig.from_toml(self.out / "config.toml").resolved()
            if on_disk.to_toml() != rc.to_toml():
                raise checkpoints.CheckpointError(f"--resume {self.out}: config.toml does not "
                                                  "match the run configuration given")
            leaves_t = jax.eval_shape(
                lambda kd: [jax.random.key_data(x) if k else x
                            for x, k in zip(jax.tree.leaves(init(kd)), self._is_key)],
                key_data)
            leaves, self.records = self.ckpt.load(leaves_t)
            if leaves is not None:
                carry = self._unflatten(leaves)
        else:
            if force:
                store.set_aside(self.out, "run")
            self.out.mkdir(parents=True, exist_ok=True)
            write_atomic(self.out / "config.toml", rc.to_toml())
        self.start_from = min(len(self.records) * self.batch, self.budget)
        # per update: the search's seconds (ask + tell) and the host's between ask and tell
        # (NaN for the updates a resumed run restored)
        self.search_seconds = [float("nan")] * len(self.records)
        self.evaluation_seconds = [float("nan")] * len(self.records)
        with self.clock("compile"):  # ask and tell compiled here, so search time is theirs
            self._carry = carry if carry is not None else jax.jit(init)(key_data)
            idx, after, k_tell = self._ask(self._carry)
            B = self.batch
            jax.block_until_ready(self._tell(after, k_tell, idx, np.zeros(B, np.float32),
                                             np.zeros(B, np.float32), np.zeros(B, bool),
                                             np.full(B, np.inf, np.float32)))
        self._pending = None
        self._status("running", evaluations=self.budget,
                     resumed_from_evaluation=self.start_from)
        if self.start_from:
            self.progress.message(f"resuming {self.out} at evaluation {self.start_from} of "
                                  f"{self.budget}")
        self.progress.start(self.budget, self.start_from, "eval",
                            f"{rc.strategy} on {self.space.name}")

    def _status(self, state: str, **extra) -> None:
        """``status.json``, with the evaluator, the pool's settings and how to resume (a
        user's own loop: ``Falsifier(..., resume=True)``)."""
        if self.config.evaluator == "python" and state != "complete":
            extra["resume"] = (f"Falsifier(..., out={str(self.out)!r}, resume=True) with the "
                               "settings of its config.toml")
        Status(self.out, "run", evaluator=self.config.evaluator, **self.status_extra).write(
            state, **extra)

    def _fingerprint(self) -> dict:
        return json.loads(json.dumps({
            "config": self.config.to_toml(), "plan": list(self.built.plan),
            "code": cache.source_hash(type(self.strategy)),
            "environment": campaign.environment(), "updates_per_record": 1}))

    def _flatten(self, carry) -> list[np.ndarray]:
        return [np.asarray(jax.random.key_data(x)) if k else np.asarray(x)
                for x, k in zip(jax.tree.leaves(carry), self._is_key)]

    def _unflatten(self, leaves):
        return jax.tree.unflatten(self._treedef, [jax.random.wrap_key_data(jnp.asarray(x))
                                                  if k else jnp.asarray(x)
                                                  for x, k in zip(leaves, self._is_key)])

    # ------------------------------------------------------------------ the loop
    @property
    def told(self) -> int:
        """Evaluations told so far (counted ones: at most the budget)."""
        return min(len(self.records) * self.batch, self.budget)

    @property
    def done(self) -> bool:
        """Whether the budget is spent."""
        return len(self.records) >= self.n_updates

    def ask(self, n: int | None = None) -> Asked:
        """The next batch of concrete scenarios (``n``, if given, must be the batch). Asking
        again before telling returns the same batch. The last batch holds only the budget's
        rest (the search asked a whole batch; the scenarios past the budget are not
        evaluated)."""
        if n is not None and n != self.batch:
            raise ValueError(f"ask({n!r}): this search asks {self.batch} scenarios per update "
                             "(set batch= when creating the Falsifier)")
        self._check_open()
        if self.done:
            raise ValueError(f"the budget of {self.budget} evaluations is spent; call finish()")
        if self._pending is None:
            t = time.perf_counter()
            idx, carry, k_tell = self._ask(self._carry)
            idx = np.asarray(idx, np.int32)
            self._asked_at = time.perf_counter()
            self._ask_s = self._asked_at - t
            self.clock.add("search", self._ask_s)
            u = len(self.records)
            evaluation = u * self.batch + np.arange(1, self.batch + 1, dtype=np.int64)
            n = int(np.sum(evaluation <= self.budget))  # the last batch: the budget's rest
            values = {name: np.asarray(self.space.exact_values[p], np.float64)[idx[:n, p]]
                      for p, name in enumerate(self.space.names)}
            asked = Asked(u, evaluation[:n], idx[:n], values, dict(zip(self.space.names,
                                                                       self.space.units)))
            self._pending = (asked, carry, k_tell, idx)
        return self._pending[0]

    def tell(self, asked: Asked, robustness, collision=None,
             signals: Mapping[str, Any] | None = None, failed=None,
             trajectory: Mapping[str, Any] | None = None) -> None:
        """The results of ``asked`` (the batch :meth:`ask` returned last).

        Args:
          robustness: ``(B,)`` the requirement's robustness of each scenario (negative:
            violated); finite wherever ``failed`` is not set.
          collision: ``(B,)`` bool (or 1 and 0), the failures the search looks for (default
            ``robustness < 0``: the requirement's violations); the robustness then ranks
            the near misses (as the built-in runs rank them by the clash robustness).
          signals: any of :data:`SIGNALS`, ``(B,)`` each.
          failed: ``(B,)`` bool: evaluations that failed (recorded as failed, with their
            robustness ignored; the search learns nothing from them).
          trajectory: ``{name: (B, T)}`` per-step histories (names from
            :data:`jaxfalsify.base.worker.TRAJECTORY`; NaN after a scenario's end), kept in the
            run folder's ``trajectories.npz`` and drawn in its figures.
        Raises ValueError (one line, naming the scenario) on missing or non-finite values."""
        self._check_open()
        if self._pending is None or asked is not self._pending[0]:
            raise ValueError("tell() takes the batch the last ask() returned")
        n, B = len(asked), self.batch
        failed = np.zeros(n, bool) if failed is None else self._flags(asked, "failed", failed)
        rob = self._column("robustness", robustness, np.float64, n)
        signals = dict(signals or {})
        unknown = sorted(set(signals) - set(SIGNALS))
        if unknown:
            raise ValueError(f"signal '{unknown[0]}' is not one of {', '.join(SIGNALS)}")
        sig = {k: self._column(k, v, np.float64, n) for k, v in signals.items()}
        coll = rob < 0 if collision is None else self._flags(asked, "collision", collision)
        traj = {} if trajectory is None else trajectory_arrays(trajectory, n)
        for name, col in (("robustness", rob), *sig.items()):
            bad = ~np.isfinite(col) & ~failed
            if name == "min_ttc":  # no approach at all: an infinite TTC is an answer
                bad &= ~np.isposinf(col)
            if bad.any():
                i = int(np.argmax(bad))
                raise ValueError(f"{name} of evaluation {int(asked.evaluation[i])} "
                                 f"({self._describe(asked, i)}) is {col[i]}: pass a finite "
                                 "value, or mark it failed")
        counted = ~failed
        reward = sig.get("reward", -rob)
        violated = coll & counted

        def full(x, fill, dtype):  # (n,) -> (B,): the rows past the budget count nothing
            return np.concatenate([np.asarray(x), np.full(B - n, fill)]).astype(dtype)

        r = full(np.where(counted, reward, -np.inf), -np.inf, np.float32)
        rob32 = full(np.where(counted, rob, np.inf), np.inf, np.float32)
        ttc = full(np.where(counted, sig.get("min_ttc", np.inf), np.inf), np.inf, np.float32)
        _, carry, k_tell, idx = self._pending
        t = time.perf_counter()
        self._carry = jax.block_until_ready(self._tell(carry, k_tell, jnp.asarray(idx), r,
                                                       rob32, full(violated, False, bool),
                                                       ttc))
        tell_s = time.perf_counter() - t
        self.clock.add("search", tell_s)
        self.search_seconds.append(self._ask_s + tell_s)
        self.evaluation_seconds.append(t - self._asked_at)
        nan = np.full(n, np.nan, np.float32)
        record = {"indices": asked.indices,
                  "reward": np.where(failed, np.nan, reward).astype(np.float32),
                  "reward_rss": nan, "reward_distance": nan, "reward_collision": nan,
                  "collision": coll & ~failed,
                  "min_distance": np.where(failed, np.nan, sig.get("min_distance", nan))
                  .astype(np.float32),
                  "final_distance": np.where(failed, np.nan, sig.get("final_distance", nan))
                  .astype(np.float32),
                  "high_risk_share": nan, "high_risk_share_second_half": nan,
                  "robustness": np.where(failed, np.nan, rob).astype(np.float32),
                  "nonfinite": failed, "violated": violated, "failed": failed,
                  **{k: np.where(failed[:, None], np.nan, v).astype(np.float32)
                     for k, v in traj.items()}}
        self.records.append(record)
        self._pending = None
        with self.clock("checkpoint"):
            self.ckpt.save(len(self.records) - 1, self._flatten(self._carry), record, self.told)
            self._status("running", evaluations=self.budget, evaluations_done=self.told)
        self.progress.update(self.told, failures=int(sum(np.sum(x["violated"])
                                                         for x in self.records)))

    def _column(self, name, x, dtype, n: int) -> np.ndarray:
        try:
            a = np.asarray(x, dtype)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be {n} numbers (got {type(x).__name__})") from None
        if a.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), one per asked scenario "
                             f"(got {a.shape})")
        return a

    def _flags(self, asked: Asked, name: str, x) -> np.ndarray:
        """``(n,)`` bool from booleans or the numbers 0 and 1; anything else (a string, NaN,
        0.5) is refused in one line naming the first such evaluation, rather than read as
        true."""
        n = len(asked)
        a = np.asarray(x, object if isinstance(x, (list, tuple)) else None)
        if a.shape != (n,):
            raise ValueError(f"{name} must have shape ({n},), one per asked scenario "
                             f"(got {a.shape})")
        i = first_non_flag(a)
        if i is not None:
            raise ValueError(f"{name} of evaluation {int(asked.evaluation[i])} "
                             f"({self._describe(asked, i)}) is {shown(a[i])}: pass true or "
                             "false (or 1 or 0)")
        return a.astype(float).astype(bool)

    def _describe(self, asked: Asked, i: int) -> str:
        return ", ".join(f"{n}={v[i]:g}" for n, v in asked.values.items())

    def _check_open(self):
        if self._finished:
            raise ValueError("this Falsifier is finished")

    # ------------------------------------------------------------------ results
    def result(self) -> campaign.Result:
        """Every evaluation told so far, as a :class:`jaxfalsify.engine.campaign.Result` (fields
        ``RECORD_FIELDS`` and ``failed``; its search seconds are the ask and tell calls', one
        "chunk" per update: :meth:`~jaxfalsify.engine.campaign.Result.search_seconds_at`)."""
        if not self.records:
            raise ValueError("nothing told yet")
        cat = {k: np.concatenate([r[k] for r in self.records]) for k in self.records[0]
               if not k.startswith("trajectory/")}
        idx = cat.pop("indices").astype(np.int32)
        t = np.asarray(self.search_seconds, np.float64)
        return campaign.Result(self.space, self.batch, idx, cat, self.clock.phases.get(
            "compile", 0.0), float(np.nansum(t)), t, 1)

    def trajectories(self) -> dict[str, np.ndarray]:
        """``{name: (N, T) float32}`` every evaluation's told trajectory (NaN where none was
        told, and after a scenario's end; ``T`` the longest told), and ``evaluation (N,)``;
        empty when no trajectory was told."""
        names = sorted({k for r in self.records for k in r if k.startswith("trajectory/")})
        if not names:
            return {}
        out = {"evaluation": np.arange(1, self.told + 1)}
        for k in names:
            steps = max(r[k].shape[1] for r in self.records if k in r)
            rows = [np.pad(r[k], ((0, 0), (0, steps - r[k].shape[1])),
                           constant_values=np.nan) if k in r else
                    np.full((len(r["reward"]), steps), np.nan, np.float32)
                    for r in self.records]
            out[k.split("/", 1)[1]] = np.concatenate(rows).astype(np.float32)
        return out

    def finish(self, figures: bool = True) -> runs.RunOutcome:
        """Write the results (``evaluations.parquet``, ``summary.json``, ``critical.csv``,
        figures and ``report.md``, ``timing.json``), mark the run complete, remove the
        checkpoint and release the folder. Callable once the budget is spent (or earlier:
        the results of the evaluations told so far, and the run is complete)."""
        self._check_open()
        res = self.result()
        self.progress.close()
        try:
            with self.clock("writing"):
                summary = summary_dict(res, self.config)
                write_parquet(self.out / "evaluations.parquet", runs.evaluations_table(res))
                write_atomic(self.out / "critical.csv", runs.critical_csv(res))
                write_json(self.out / "summary.json", summary, indent=2)
                traj = self.trajectories()
                if traj:
                    save_npz(self.out / TRAJECTORIES, traj)
            if figures:
                with self.clock("figures"):
                    figures_lib.make_figures(self.out)
                    report_lib.write_report(self.out, timing={
                        **self.clock.summary(), "resumed_from_evaluation": self.start_from})
            timing = {**self.clock.summary(), "resumed_from_evaluation": self.start_from}
            write_json(self.out / "timing.json", timing, indent=2)
            self._status("complete", evaluations_done=res.n, evaluations=res.n)
            self.ckpt.remove()
        finally:
            self._finished = True
            self._lock.release()
        return runs.RunOutcome(self.out, self.config, res, summary, timing)

    def close(self, error: BaseException | None = None) -> None:
        """Release the folder without finishing: it stays resumable (``status.json`` says
        interrupted, or failed with ``error``'s text when an error ended the loop). Nothing
        told is lost."""
        if self._finished:
            return
        self.progress.close()
        self._finished = True
        try:
            if error is None:
                self._status("interrupted", evaluations_done=self.told,
                             evaluations=self.budget)
            else:
                self._status("failed", evaluations_done=self.told, evaluations=self.budget,
                             error=error_text(error))
        finally:
            self._lock.release()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def _python_words(text: str, out: Path) -> str:
    """A folder error in the Falsifier's words (its arguments, not the CLI's flags)."""
    shell = store.shell_path(out)
    for flag, arg in ((f"--resume {shell}", "resume=True"), (f"--resume {out}", "resume=True"),
                      (f"--out {out}", f"out={str(out)!r}"), ("--resume", "resume=True"),
                      ("--force", "force=True")):
        text = text.replace(flag, arg)
    return text


def summary_dict(res: campaign.Result, rc: RunConfig) -> dict:
    """``summary.json`` of an evaluator's run: a run's, with the evaluator and the failed
    evaluations."""
    s = runs.summary_dict(res, rc)
    failed = np.asarray(res.fields["failed"], bool)
    s["evaluator"] = rc.evaluator
    s["n_failed"] = int(failed.sum())
    s["failed_evaluations"] = [int(e) for e in np.nonzero(failed)[0][:100] + 1]
    return s
