"""``jaxfalsify compare``: strategies on the same space and SUT, many seeds, against the
exhaustive sweep as ground truth (from the per-user cache, see
:func:`jaxfalsify.engine.truth.ground_truth`). The comparison job: its configuration
(:class:`CompareConfig`), the ground truth's summary (:func:`truth_summary`), the searches, the
search-overhead timing and the files written (:func:`execute`).

One concern: the comparison job (its configuration, searches, timing and
files); statistics and tables are in ``compare_stats`` and ``compare_tables``.

Per strategy (one compiled program, its seeds run through it one after another), the figures of
:mod:`jaxfalsify.jobs.compare_stats` (:func:`~jaxfalsify.jobs.compare_stats.seed_stats`,
:func:`~jaxfalsify.jobs.compare_stats.strategy_row`), and:

* search overhead: seconds per 1000 evaluations the strategy's own ``ask``/``tell`` take without
  simulation (timed after all searches, one strategy at a time, on ``OVERHEAD_SEEDS`` seeds in
  one compiled call; ``result["overhead"]``);
* wall seconds for all seeds together, compilation included (with ``jobs`` > 1 the strategies
  run side by side, ``jobs`` at a time, so each one's wall time includes sharing the machine).

The strategies run ``jobs`` at a time in threads (XLA runs a compiled campaign without Python's
lock, and a campaign of small batches keeps one core busy): on 2 cores two side by side take
about half the time of one after the other. Every result is the same whatever ``jobs`` is
(each strategy's seeds are their own compiled calls); only the measured seconds differ.

Search time. Each seed is its own call of the strategy's compiled campaign program (compiled
once, ahead of the first chunk: ``compile_seconds``, not part of any seed's search time), so
each seed's time is measured, not a share of a call over all seeds (seeds mapped inside one
call run one after another and cannot be timed apart from the host; the results are the same
either way). :func:`jaxfalsify.engine.campaign.drive` times every chunk of updates on the host (the
call until its records are on the host, so the device work is done); a seed's search seconds
at evaluation ``e`` are the chunks before the one holding ``e``'s update, plus that chunk's
seconds divided evenly among its updates, up to the end of ``e``'s update
(:meth:`jaxfalsify.engine.campaign.Result.search_seconds_at`; resolution one update, exact at chunk
boundaries). Per seed: ``first_collision_seconds`` (None when the seed found no collision
within the budget, never 0), ``search_seconds`` (to the end of the update holding the budget's
last evaluation) and ``failures_per_second`` (distinct collision scenarios /
``search_seconds``). With ``jobs`` > 1 the strategies share the machine while they search, so
their seconds include that sharing; ``jobs = 1`` times each strategy alone.

``compare.json`` holds every figure per seed (``per_seed`` rows); ``compare.md`` the tables
of :mod:`jaxfalsify.jobs.compare_tables`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from jaxfalsify import search
from jaxfalsify.base import config as cfg
from jaxfalsify.base.distributed import agree, barrier, share
from jaxfalsify.base.progress import Clock, Progress
from jaxfalsify.core import requirements, sim
from jaxfalsify.engine import campaign
from jaxfalsify.engine.lifecycle import sut_raised
from jaxfalsify.engine.problem import Problem, RunConfig, check_int, check_once
from jaxfalsify.engine.truth import ground_truth
from jaxfalsify.io import cache, store
from jaxfalsify.io.files import sha256, write_atomic, write_json
from jaxfalsify.io.store import Interrupted
from jaxfalsify.jobs.compare_stats import (
    TOL,
    median,
    seed_stats,
    strategy_row,
    uniform_first_collision,
)
from jaxfalsify.jobs.compare_tables import budgets_markdown, table_markdown
from jaxfalsify.jobs.runs import check_strategy_memory, timestamp
from jaxfalsify.scenario.space import MAX_SIZE
from jaxfalsify.suts import registry as sut_lib

__all__ = ["DEFAULT_STRATEGIES", "CompareConfig", "execute", "truth_summary"]

# the per-evaluation comparison at each strategy's own batch and the paper's budget: the
# sample-efficient reinforce/screened stands for the REINFORCE family there (reinforce/default
# asks 4096 per update: compare it with --batch 4096 and a budget of many updates)
DEFAULT_STRATEGIES = ("reinforce/screened", "reinforce/factorised", "reinforce/paper", "random",
                      "grid", "cem", "anneal", "cmaes")


@dataclasses.dataclass(frozen=True)
class CompareConfig(Problem):
    strategies: tuple[str, ...] = DEFAULT_STRATEGIES
    seeds: int = 10
    evaluations: int = 4000
    overhead: bool = True  # time each strategy's ask/tell alone (search overhead)
    budgets: tuple[int, ...] = ()  # also report at these smaller budgets (first evaluations)
    # options per strategy, e.g. {"cem": {"elite_frac": 0.2}} (the registry's defaults otherwise)
    strategy_params: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    jobs: int = 0  # strategies searched side by side (0: one per CPU core, at most 4)
    batch: int | None = None  # scenarios per update of every strategy (None: each its own)
    requirement: str = "collision"  # what is critical (a run's --requirement): the ground
    # truth's and the searches' "collisions" are its violations
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)

    def resolved_jobs(self) -> int:
        """``jobs``, 0 resolved to the usable CPU cores (at most 4 and the strategy count)."""
        n = self.jobs or min(4, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                             else (os.cpu_count() or 1))
        return max(1, min(n, len(self.strategies)))

    def run_config(self, strategy: str) -> RunConfig:
        return RunConfig(space=self.space, space_seed=self.space_seed, sut=self.sut,
                         sut_params=self.sut_params, strategy=strategy,
                         strategy_params=dict(self.strategy_params.get(strategy, {})),
                         evaluations=self.evaluations, batch=self.batch,
                         requirement=self.requirement,
                         requirement_params=dict(self.requirement_params))

    def check(self, num_processes: int = 1) -> None:
        """Everything validated and every strategy built; memory for this process's share
        of the seeds (``num_processes`` share them)."""

        check_int("seeds", self.seeds, 1, 10_000)
        check_int("jobs", self.jobs, 0, 256)
        if self.batch is not None:
            check_int("batch", self.batch, 1, 10**6)
        for b in self.budgets:
            check_int("budgets", b, 1, self.evaluations)
        check_once("budgets", self.budgets)
        if isinstance(self.strategies, str) or not all(isinstance(s, str)
                                                       for s in self.strategies):
            raise ValueError(f"strategies must be a list of names, e.g. ('random',) (got "
                             f"{self.strategies!r})")
        if not self.strategies:
            raise ValueError("strategies: none given")
        seen: dict[str, str] = {}
        for s in self.strategies:
            c = search.canonical(s)
            if c in seen:  # one row per strategy: a second would be dropped silently
                raise ValueError(f"strategies: {s!r} given twice"
                                 + (f" ({seen[c]!r} names it too)" if seen[c] != s else ""))
            seen[c] = s
        for s in self.strategy_params:
            if s not in self.strategies:
                raise ValueError(f"strategy_params: {s!r} is not among the strategies "
                                 f"({', '.join(self.strategies)})")
        # every entry built (the space, the SUT, the options, the batch against the space)
        # before a folder is locked or a ground truth swept
        builds = [self.run_config(s).build() for s in self.strategies]
        self.check_memory(builds[0].space, num_processes)

        for s, b in zip(self.strategies, builds):
            check_strategy_memory(b, s, self.strategy_params.get(s, {}))

    def check_memory(self, sp, num_processes: int = 1) -> None:
        """Every evaluated scenario's record is kept until the end (this process's share of
        the seeds), and the ground truth's arrays: refused (one line) above half the
        available memory."""

        per_eval = (len(sp.shape) + len(campaign.RECORD_FIELDS)) * 8 * 2
        n, seeds = len(self.strategies), -(-self.seeds // num_processes)
        # the ground truth's collision, reward and nonfinite per scenario (a sample of
        # TRUTH_SAMPLE for a space too large to sweep)
        truth = (sp.size if sp.size <= MAX_SIZE else TRUTH_SAMPLE) * 32  # peak, float64 copies
        cfg.check_memory(seeds * self.evaluations * n * per_eval + truth,
                         f"{n} strateg{'y' if n == 1 else 'ies'} x {seeds} seeds x "
                         f"{self.evaluations} evaluations", "lower --seeds or --evaluations")

    def to_toml(self) -> str:
        return cfg.dumps_toml({"kind": "compare", "strategies": list(self.strategies),
                               "seeds": self.seeds, "evaluations": self.evaluations,
                               **({"batch": self.batch} if self.batch is not None else {}),
                               "jobs": self.resolved_jobs(), "space_seed": self.space_seed,
                               "budgets": list(self.budgets), "overhead": self.overhead,
                               "sut": sut_lib.recorded_spec(self.sut),
                               "sut_params": dict(self.sut_params),
                               "strategy_params": {k: dict(v) for k, v
                                                   in self.strategy_params.items()},
                               **({"requirement": sut_lib.recorded_spec(self.requirement),
                                   "requirement_params": dict(self.requirement_params)}
                                  if self.requirement != "collision" else {}),
                               "space": self.space if isinstance(self.space, Mapping)
                               else self.space})


TRUTH_SAMPLE = 1_000_000  # uniform scenarios that estimate the collision share of a space
# too large to sweep


def sampled_truth(sp, b, budget: int | None = None, n: int | None = None,
                  seed: int = 0) -> dict:
    """What can be known of a space too large to sweep: its collision share estimated from
    ``n`` uniformly drawn scenarios (with a 95 % Clopper-Pearson interval), and uniform random
    search's expectation from that estimate. No global maximum."""
    from scipy import stats as st

    n = TRUTH_SAMPLE if n is None else n
    import jax

    s = sut_lib.resolve(b.sut)
    params = sut_lib.with_params(s, b.sut_params)
    layout, table = sp.layout, sp.table_array
    chunk = 1 << 16

    req, rparams = b.requirement, b.requirement_params

    @jax.jit
    def run(idx, key_data, params):  # one compiled call per chunk (sut.NAME values traced)
        out, _ = sim.batch_rollout(layout.scenario(idx, table), jax.numpy.arange(chunk),
                                   jax.random.wrap_key_data(key_data), s, params)
        hit = out.collision if req is None else \
            requirements.robustness(req, out, rparams) < 0  # the requirement's violations
        return hit & ~out.nonfinite, jax.numpy.where(
            jax.numpy.isnan(out.reward), -jax.numpy.inf, out.reward)

    rng = np.random.default_rng([seed, 7919])
    shape = np.asarray(sp.shape)
    coll = 0
    best = -np.inf
    key_data = sim.seed_key_data(seed)
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        idx = np.zeros((chunk, len(shape)), np.int32)
        idx[:m] = (rng.random((m, len(shape))) * shape).astype(np.int32)
        c, r = run(idx, key_data, params)
        coll += int(np.sum(np.asarray(c)[:m]))
        best = max(best, float(np.max(np.asarray(r)[:m])))
    lo = float(st.beta.ppf(0.025, coll, n - coll + 1)) if coll else 0.0
    hi = float(st.beta.ppf(0.975, coll + 1, n - coll))
    out = {"n_scenarios": int(sp.size), "n_collisions": None, "sampled": n,
           "sampled_collisions": coll, "collision_share": coll / n,
           "collision_share_ci95": [lo, hi], "global_max_reward": None,
           "global_min_reward": None, "global_max_ties": None, "sampled_best_reward": best,
           "uniform_corner_share": float(2.0 ** np.sum(shape > 1) / sp.size)}
    if budget is not None:
        u = uniform_first_collision(n, coll, budget)
        u["estimated"] = True
        out["uniform_first_collision"] = u
    return out


def truth_summary(sp, b, budget: int | None = None) -> dict:
    if sp.size > MAX_SIZE:
        return sampled_truth(sp, b, budget)
    t = ground_truth(sp, b.sut, b.sut_params, requirement=b.requirement,
                     requirement_params=b.requirement_params)
    r = np.where(np.isnan(t["reward"]), -np.inf, t["reward"]).astype(np.float64)
    finite = r[np.isfinite(r)]
    # None when no rollout has a finite reward (a SUT that returns NaN or inf everywhere)
    gmax = float(finite.max()) if finite.size else None
    n_coll = int(np.sum(t["collision"]))
    shape = np.asarray(sp.shape)
    hits = sp.unravel(np.nonzero(t["collision"])[0])
    multi = shape > 1
    # the failure set lies away from every edge of the index box (an interior island)
    interior = bool(n_coll and multi.any() and np.all((hits[:, multi] > 0)
                                      & (hits[:, multi] < shape[multi] - 1)))
    out = {"n_scenarios": int(len(r)), "n_collisions": n_coll,
           "collision_share": n_coll / len(r), "n_nonfinite": int(len(r) - finite.size),
           "global_max_reward": gmax,
           "global_min_reward": float(finite.min()) if finite.size else None,
           # as a seed 'reaches' it
           "global_max_ties": int(np.sum(r >= gmax - TOL)) if finite.size else 0,
           "failures_interior": interior,
           "failure_index_range": ({n: [int(hits[:, p].min()), int(hits[:, p].max())]
                                    for p, n in enumerate(sp.names)} if n_coll else None),
           "uniform_corner_share": float(2.0 ** np.sum(shape > 1) / len(r))}
    if budget is not None:
        out["uniform_first_collision"] = uniform_first_collision(len(r), n_coll, budget)
    return out


def overhead_program(strategy, strategy_params, p: campaign.Plan, n_seeds: int):
    """The compiled ask/tell loop that :func:`search_overhead` times, and its arguments:
    ``(compiled, args, evaluations per call in thousands)``. Kept in the per-user cache (see
    :func:`jaxfalsify.io.cache.exported_jit`) and compiled ahead, so loading it can happen while
    other strategies search and the timing covers the loop alone."""
    import jax
    import jax.numpy as jnp

    B = strategy.batch
    f32 = [np.asarray(x, np.float32) for x in jax.tree.leaves(strategy_params)]
    tree = jax.tree.structure(strategy_params)

    def one_seed(key, params):
        def upd(state, k):
            k_ask, k_tell = jax.random.split(k)
            idx, state = strategy.ask(k_ask, state, params)
            z = jnp.zeros(B, jnp.float32)
            state = strategy.tell_outcome(k_tell, state, idx, z, z + 1.0,
                                          jnp.zeros(B, bool), params)
            return state, idx[0, 0]

        k_init, k_run = jax.random.split(key)
        # the barrier keeps XLA from folding the start state's constants into a short scan's
        # unrolled first update (seconds of compile, and not the work a run does)
        start = jax.lax.optimization_barrier(strategy.start(k_init, params))
        _, out = jax.lax.scan(upd, start, jax.random.split(k_run, p.n_updates))
        return out.sum()

    def fn(key_data, leaves):
        params = jax.tree.unflatten(tree, leaves)
        keys = jax.random.split(jax.random.wrap_key_data(key_data), n_seeds)
        return jax.lax.map(lambda k: one_seed(k, params), keys)

    args = (sim.seed_key_data(0), f32)
    static = {"strategy": repr(strategy), "params": str(tree), "updates": p.n_updates,
              "seeds": n_seeds}
    prog = cache.exported_jit(fn, "overhead", static, (args[0], f32), lambda: args)
    return prog.call.lower(*args).compile(), args, n_seeds * p.n_updates * B / 1000.0


def search_overhead(strategy, strategy_params, p: campaign.Plan, n_seeds: int,
                    prepared=None) -> float:
    """Seconds per 1000 evaluations (per seed) of the strategy's own ask/tell loop for the
    campaign's updates, without simulation (zero rewards, no collisions), ``n_seeds`` seeds in
    one compiled call as the campaign runs them (hyperparameters traced, as there): one call of
    :func:`overhead_program` (or the ``prepared`` one) timed."""
    import jax

    compiled, args, thousands = prepared or overhead_program(strategy, strategy_params, p,
                                                             n_seeds)
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    return (time.perf_counter() - t0) / thousands


OVERHEAD_SEEDS = 2  # seeds the search-overhead timing runs (a per-evaluation figure)


def _search_side_by_side(builds, seeds: list[int], jobs: int, progress: Progress, stop,
                         out: Path, evaluations: int, overhead_seeds: int = 0) -> dict:
    """Every strategy's campaigns on ``seeds``, ``jobs`` strategies at a time in threads (a
    strategy's seeds one after another, each its own call of the strategy's compiled program,
    so that each seed's search time is measured), one progress bar over all of them. Returns
    ``{label: {"results", "wall", "compile"}}`` (seconds; ``compile``: tracing and exporting
    or loading the program, and compiling it, which the first seed does and the others find
    done) and
    ``"_wall"`` (the whole); with ``overhead_seeds`` each strategy's overhead program is
    loaded after its search (``"overhead_program"``), to be timed later. A stop request,
    Ctrl-C or an error in one strategy stops the others at their next chunk; then
    :class:`~jaxfalsify.jobs.runs.Interrupted` (or the error) is raised and nothing is written."""
    from concurrent.futures import ThreadPoolExecutor, wait

    halt = threading.Event()
    lock = threading.Lock()
    done: dict[str, int] = {}
    finished: list[str] = []
    total = sum(b.plan.evaluations for _, b in builds) * len(seeds)  # all evaluations
    bar = {"started": False}

    def halted() -> bool:
        return halt.is_set() or (stop is not None and bool(stop()))

    def tick(label, n):
        with lock:
            done[label] = n
            if not bar["started"]:
                progress.start(total, 0, "eval", f"{len(builds)} strategies x {len(seeds)} "
                               f"seeds, {jobs} side by side")
                bar["started"] = True
            progress.update(sum(done.values()), strategies=f"{len(finished)}/{len(builds)}")

    def one(item):
        label, b = item
        t0 = time.perf_counter()
        if seeds:  # traced and exported (or loaded): counted with the compilation
            campaign.program(campaign.Campaign(b.space.layout, b.sut, b.strategy,
                                               b.plan.updates_per_chunk, b.requirement),
                             campaign.args_for(b.space, b.sut_params, b.strategy_params,
                                               sim.WORLD, b.plan.evaluations,
                                               b.requirement_params), 1)
        prepare = time.perf_counter() - t0
        results = []
        for k, seed in enumerate(seeds):  # one call per seed: each seed's time is measured
            before = k * b.plan.evaluations
            results += campaign.run_seeds(
                b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan, [seed],
                requirement=b.requirement, requirement_params=b.requirement_params,
                progress=lambda n, _r, label=label, before=before: tick(label, before + n),
                stop=halted)
        wall = time.perf_counter() - t0
        prepared = (overhead_program(b.strategy, b.strategy_params, b.plan, overhead_seeds)
                    if overhead_seeds and not halted() else None)
        with lock:
            finished.append(label)
        # the first seed compiles the program; the others find it compiled (milliseconds)
        return {"results": results, "wall": wall, "overhead_program": prepared,
                "compile": prepare + float(sum(r.compile_seconds for r in results))}

    progress.phase(f"searching: {len(builds)} strategies x {len(seeds)} seeds x {evaluations} "
                   f"evaluations, {jobs} side by side (each compiles or loads its program "
                   f"first, then runs its seeds one after another)")
    t0 = time.perf_counter()
    ex = ThreadPoolExecutor(jobs, thread_name_prefix="jaxfalsify-compare")
    futures = [ex.submit(one, item) for item in builds]
    try:
        wait(futures, return_when="FIRST_EXCEPTION")
        for f in futures:
            if f.done() and f.exception() is not None:
                raise f.exception()
        out_map = {label: f.result() for (label, _), f in zip(builds, futures)}
    except BaseException as e:
        halt.set()
        for f in futures:
            f.cancel()
        ex.shutdown(wait=True)
        progress.close()
        if isinstance(e, (campaign.Stopped, KeyboardInterrupt)):
            raise Interrupted("compare", out, len(finished), len(builds), "strategies",
                              resumable=False) from None
        raise
    ex.shutdown(wait=True)
    progress.close()
    out_map["_wall"] = time.perf_counter() - t0
    return out_map


def execute(config: CompareConfig, out: Path | str | None, *, force: bool = False,
            progress: Progress | None = None, stop=None, process_id: int = 0,
            num_processes: int = 1, startup_seconds: float = 0.0) -> dict:
    """Run every strategy on seeds 0..seeds-1 and write ``compare.json``/``compare.md`` to
    ``out``. With several processes (``jax.distributed``), process i runs its contiguous share
    of the seeds and writes a part; process 0 merges. ``out`` None: a new folder
    ``runs/compare-<time>`` (``-2``, ... when taken). Returns the result (its folder under
    ``"out"``)."""
    cfg.check_type(config, CompareConfig, "config")
    clock = Clock(startup_seconds)
    progress = progress or Progress()
    if out is None and num_processes > 1:
        raise ValueError("a comparison of several processes needs out (a shared folder)")
    config.check(num_processes)
    base = config.run_config(config.strategies[0]).build()

    agree("comparison configuration", sha256(json.dumps({  # not --jobs: per host
        "strategies": list(config.strategies), "seeds": config.seeds,
        "evaluations": config.evaluations, "budgets": list(config.budgets),
        "overhead": config.overhead, "space": base.space.describe(),
        "space_seed": config.space_seed, "sut_params": sut_lib.params_dict(base.sut_params),
        "strategy_params": {k: dict(v) for k, v in config.strategy_params.items()},
        "processes": num_processes, "code": cache.source_hash(base.sut.act, base.sut.init)},
        sort_keys=True, default=str).encode()))
    if out is None:
        out, lk = store.open_new_folder(Path("runs") / f"compare-{timestamp()}", "compare")
        existed = earlier = False
    else:
        out = Path(out)
        existed = out.exists()
        earlier = store.complete(out, "compare")  # kept until this one's files replace them
        lk = store.open_folder(out, "compare", force=force,
                               name=".lock" if process_id == 0 else
                               f".lock-part-{process_id:05d}")
    try:
        lk.claim("compare")
        return _execute(config, out, base, progress, process_id, num_processes, clock, stop)
    except BaseException as e:
        if num_processes == 1 and not earlier and (sut_raised(e) or store.nothing_written(out)):
            store.discard(out, "compare", lk, existed)  # SUT raised / nothing written
        raise
    finally:
        lk.release()


def _execute(config: CompareConfig, out: Path, base, progress: Progress, process_id: int,
             num_processes: int, clock: Clock, stop) -> dict:

    sp = base.space
    progress.phase(f"ground truth: every scenario of {sp.name} ({sp.size:,}) x {config.sut}")
    with clock("ground_truth"):
        truth = truth_summary(sp, base, config.evaluations) if process_id == 0 else None
        barrier("jaxfalsify-compare-truth")
        if truth is None:
            truth = truth_summary(sp, base, config.evaluations)  # cached by process 0: a load
    lo, hi = share(config.seeds, process_id, num_processes)
    mine = list(range(lo, hi))
    builds = [(search.canonical(e), config.run_config(e).build()) for e in config.strategies]
    jobs = config.resolved_jobs()
    n_over = min(len(mine), OVERHEAD_SEEDS) if config.overhead else 0
    searched = _search_side_by_side(builds, mine, jobs, progress, stop, out, config.evaluations,
                                    n_over)
    if jobs == 1:
        for label, _ in builds:
            clock.add("compile", searched[label]["compile"])
            clock.add("search", searched[label]["wall"] - searched[label]["compile"])
    else:  # compiling/loading and searching overlap across strategies: one phase
        clock.add("compile_and_search", searched["_wall"])
    parts: dict[str, dict] = {}
    for label, b in builds:
        results = searched[label]["results"]
        stats = [seed_stats(s, r, truth, config.evaluations) for s, r in zip(mine, results)]
        small = {bb: [seed_stats(s, r, truth, bb) for s, r in zip(mine, results)]
                 for bb in sorted(set(config.budgets)) if bb < config.evaluations}
        with clock("overhead"):  # one strategy at a time, after all searches: uncontended
            overhead = (search_overhead(b.strategy, b.strategy_params, b.plan, n_over,
                                        searched[label]["overhead_program"])
                        if n_over else None)
        parts[label] = {"stats": stats, "wall": searched[label]["wall"], "overhead": overhead,
                        "compile": searched[label]["compile"],
                        "small": {str(bb): v for bb, v in small.items()}}
    if num_processes > 1:
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / f".compare.part-{process_id:05d}.json", parts)
        barrier("jaxfalsify-compare-parts")
        all_parts = [json.loads((out / f".compare.part-{i:05d}.json").read_text())
                     for i in range(num_processes)]
        barrier("jaxfalsify-compare-parts-read")  # process 0 deletes them when it is done
        merged = {k: {"stats": sum((p[k]["stats"] for p in all_parts), []),
                      "wall": max(p[k]["wall"] for p in all_parts),
                      "compile": max(p[k]["compile"] for p in all_parts),
                      "overhead": median(p[k].get("overhead") for p in all_parts),
                      "small": {b: sum((p[k]["small"][b] for p in all_parts), [])
                                for b in parts[k]["small"]}}
                  for k in parts}
    else:
        merged = parts
    rows = [strategy_row(k, v["stats"], truth, v["wall"], v["compile"])
            for k, v in merged.items()]
    by_budget = []
    for b in sorted(set(config.budgets) | {config.evaluations}):
        if b == config.evaluations:
            b_rows = rows
        else:
            b_rows = [strategy_row(k, v["small"][str(b)], truth, v["wall"], v["compile"])
                      for k, v in merged.items()]
        u = (uniform_first_collision(truth["n_scenarios"], truth["n_collisions"], b)
             if truth["n_collisions"] is not None else
             uniform_first_collision(truth["sampled"], truth["sampled_collisions"], b))
        by_budget.append({"budget": b, "uniform_first_collision": u, "rows": b_rows})
    result = {"space": sp.name, "space_seed": config.space_seed, "sut": config.sut,
              "sut_params": dict(config.sut_params), "requirement": config.requirement,
              "requirement_params": sut_lib.params_dict(base.requirement_params)
              if base.requirement is not None else {},
              "evaluations": config.evaluations, "seeds": config.seeds,
              "processes": num_processes, "jobs": jobs, **truth, "rows": rows,
              "budgets": by_budget,
              "overhead": {k: v.get("overhead") for k, v in merged.items()},
              "versions": cfg.versions()}
    if process_id == 0:
        with clock("writing"):
            out.mkdir(parents=True, exist_ok=True)
            write_atomic(out / "config.toml", config.to_toml())
            write_json(out / "compare.json", result, indent=2)
            md = table_markdown(result)
            if config.budgets:  # the smaller budgets' table too, not only on the console
                md += "\n\n" + budgets_markdown(result)
            write_atomic(out / "compare.md", md + "\n")
            write_json(out / "timing.json", clock.summary(), indent=2)
            store.drop_earlier(out)  # an earlier job's results kept by --force: replaced now
        for i in range(num_processes if num_processes > 1 else 0):
            (out / f".compare.part-{i:05d}.json").unlink(missing_ok=True)
    result["timing"] = clock.summary()
    result["out"] = str(out)
    return result
