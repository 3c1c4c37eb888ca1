"""``jaxfalsify compare``: strategies on the same space and SUT, many seeds, against the
exhaustive sweep as ground truth (from the per-user cache, see
:func:`jaxfalsify.sweep.ground_truth`).

Per strategy (one compiled program, its seeds run through it one after another), see
:func:`seed_stats` and :func:`strategy_row`:

* seeds that found a collision;
* evaluations to the first collision, median and IQR over **all** seeds, a seed that found none
  counting ``budget + 1`` (censored; a median above the budget means most seeds found none),
  beside uniform random's analytic expectation (:func:`uniform_first_collision`);
* search seconds to the first collision and distinct collisions per search second, per seed
  and as medians, with the strategy's compile seconds apart (see *Search time* below);
* the best reward, normalised as ``(best - global min) / (global max - global min)`` in [0, 1]
  (1 = the global maximum; never negative, whatever the sign of the rewards), median over the
  seeds with a finite best; and how many seeds reached the global maximum;
* distinct collision scenarios found (median) over all of the space;
* the share of evaluations on box corners (every parameter at its first or last value;
  uniform random's share is ``2^P' / N``, P' the parameters with two or more values);
* the mean reward of the last quarter of the evaluations (the last 1000 of 4000);
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
either way). :func:`jaxfalsify.campaign.drive` times every chunk of updates on the host (the
call until its records are on the host, so the device work is done); a seed's search seconds
at evaluation ``e`` are the chunks before the one holding ``e``'s update, plus that chunk's
seconds divided evenly among its updates, up to the end of ``e``'s update
(:meth:`jaxfalsify.campaign.Result.search_seconds_at`; resolution one update, exact at chunk
boundaries). Per seed: ``first_collision_seconds`` (None when the seed found no collision
within the budget, never 0), ``search_seconds`` (to the end of the update holding the budget's
last evaluation; updates a chunk runs past the budget are not counted) and
``failures_per_second`` (distinct collision scenarios / ``search_seconds``). With ``jobs`` > 1
the strategies share the machine while they search, so their seconds include that sharing;
``jobs = 1`` times each strategy alone.

``compare.json`` holds every figure per seed (``per_seed`` rows).
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

from jaxfalsify import analysis, cache, campaign, requirements, search, sim, store
from jaxfalsify import config as cfg
from jaxfalsify import sut as sut_lib
from jaxfalsify.distributed import agree, barrier, share
from jaxfalsify.progress import Clock, Progress
from jaxfalsify.runs import Interrupted, RunConfig, check_int, check_strategy_memory, timestamp
from jaxfalsify.space import MAX_SIZE
from jaxfalsify.sweep import ground_truth

TOL = 1e-6  # reward equality with the global maximum (rewards are float32 sums)
# the per-evaluation comparison at each strategy's own batch and the paper's budget: the
# sample-efficient reinforce/screened stands for the REINFORCE family there (reinforce/default
# asks 4096 per update: compare it with --batch 4096 and a budget of many updates)
DEFAULT_STRATEGIES = ("reinforce/screened", "reinforce/factorised", "reinforce/paper", "random",
                      "grid", "cem", "anneal", "cmaes")


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    strategies: tuple[str, ...] = DEFAULT_STRATEGIES
    seeds: int = 10
    evaluations: int = 4000
    space: Any = "paper"
    space_seed: int = 0
    sut: str = "carla-tm"
    sut_params: Mapping[str, float] = dataclasses.field(default_factory=dict)
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


def uniform_first_collision(n_scenarios: int, n_collisions: int, budget: int) -> dict:
    """Uniform random's evaluations to the first collision, analytically: sampling with
    replacement from ``N`` scenarios of which ``C`` collide, the first collision is geometric
    with ``p = C / N``: expectation ``(1 - p) / p + 1 = 1 / p`` (``inf`` if ``C = 0``), median
    ``ceil(ln 0.5 / ln(1 - p))``; censored at ``budget + 1`` as the strategies' figures are
    (no collision within the budget counts ``budget + 1``): ``E[min(X, B + 1)] =
    (1 - (1 - p)^(B + 1)) / p`` and the median ``min(median, B + 1)``; and the probability
    of at least one collision within the budget, ``1 - (1 - p)^B``."""
    B = int(budget)
    if n_collisions <= 0:
        return {"p": 0.0, "expected": float("inf"), "median": float("inf"),
                "expected_censored": float(B + 1), "median_censored": float(B + 1),
                "found_probability": 0.0}
    p = n_collisions / n_scenarios
    if p >= 1.0:
        return {"p": 1.0, "expected": 1.0, "median": 1.0, "expected_censored": 1.0,
                "median_censored": 1.0, "found_probability": 1.0}
    log_q = np.log1p(-p)
    median = float(max(1.0, np.ceil(np.log(0.5) / log_q)))
    return {"p": p, "expected": 1.0 / p, "median": median,
            "expected_censored": float(-np.expm1((B + 1) * log_q) / p),
            "median_censored": float(min(median, B + 1)),
            "found_probability": float(-np.expm1(B * log_q))}


def corner_mask(indices: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """``(N,)`` bool: the scenario is a corner of the index box (every parameter's index is
    its first or last value; a one-value parameter is always both)."""
    idx = np.asarray(indices)
    last = np.asarray(shape) - 1
    return np.all((idx == 0) | (idx == last), axis=-1)


def truncate(r: campaign.Result, budget: int) -> campaign.Result:
    """The first ``budget`` evaluations of a campaign: what a run with that budget evaluates
    (no strategy's behaviour depends on the total budget)."""
    if budget >= r.n:
        return r
    return dataclasses.replace(r, indices=r.indices[:budget],
                               fields={k: v[:budget] for k, v in r.fields.items()})


def seed_stats(seed: int, r: campaign.Result, truth: dict, budget: int | None = None) -> dict:
    """One seed's figures (see the module docstring), over its first ``budget`` evaluations
    (default all). ``truth``: :func:`truth_summary` (``global_max_reward`` None when the
    space is too large to sweep). Times in seconds of search, compilation excluded
    (:meth:`jaxfalsify.campaign.Result.search_seconds_at`): ``first_collision_seconds`` at the
    end of the update holding the first collision (None without one), ``search_seconds`` at
    the end of the update holding evaluation ``budget``, ``failures_per_second`` = distinct
    collision scenarios / ``search_seconds`` (all three None when ``r`` was not timed)."""
    budget = r.n if budget is None else int(budget)
    r = truncate(r, budget)
    gmax, gmin = truth["global_max_reward"], truth["global_min_reward"]
    if gmax is None:  # no ground truth: normalise against nothing
        gmax = gmin = None
    ranked = analysis.ranked_reward(r.fields)
    best = float(ranked.max()) if r.n else -np.inf
    first = analysis.first_critical(r.fields)  # collisions, or the requirement's violations
    tail = ranked[r.n - max(1, r.n // 4):] if r.n else ranked
    tail = tail[np.isfinite(tail)]
    distinct = len(analysis.distinct_critical(r.indices, r.fields))
    searched = r.search_seconds_at(r.n) if r.n else None  # None: not timed
    return {"seed": seed, "first_collision": first,
            "first_collision_censored": first if first is not None else budget + 1,
            "first_collision_seconds": (None if first is None or searched is None
                                        else r.search_seconds_at(first)),
            "search_seconds": searched,
            "failures_per_second": (distinct / searched if searched else None),
            "best": best if np.isfinite(best) else None,
            "best_normalised": (None if gmax is None else
                                float((best - gmin) / (gmax - gmin)) if np.isfinite(best)
                                and gmax > gmin else (1.0 if np.isfinite(best) else None)),
            "reached_global_max": (None if gmax is None else
                                   bool(np.isfinite(best) and best >= gmax - TOL)),
            "distinct": distinct,
            "corner_share": float(np.mean(corner_mask(r.indices, r.space.shape)))
            if r.n else 0.0,
            "final_mean_reward": float(np.mean(tail)) if tail.size else None}


def _median(xs) -> float:
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else float("nan")


def _time_median(xs) -> float | None:
    """Median of per-seed seconds or rates; None when any seed's is missing (not timed)."""
    xs = list(xs)
    return float(np.median(xs)) if xs and all(x is not None for x in xs) else None


def first_collision_seconds_median(stats: list[dict]) -> float | None:
    """Median over **all** seeds of the search seconds to the first collision, a seed that
    found none counting as later than any (infinite): None when that median is not finite
    (half or more of the seeds found none) or a seed was not timed."""
    if not stats or any(s.get("search_seconds") is None for s in stats):
        return None
    t = [np.inf if s["first_collision_seconds"] is None else s["first_collision_seconds"]
         for s in stats]
    m = float(np.median(np.asarray(t, np.float64)))
    return m if np.isfinite(m) else None


def strategy_row(name: str, stats: list[dict], truth: dict, wall: float,
                 compile_seconds: float | None = None) -> dict:
    """A strategy's summary over its seeds (``stats``: :func:`seed_stats` rows); ``wall`` and
    ``compile_seconds`` (lowering and compiling its program, apart from every seed's search
    seconds) in seconds."""
    first = np.array([s["first_collision_censored"] for s in stats], np.float64)
    q = np.percentile(first, [25, 50, 75])
    found = sum(s["first_collision"] is not None for s in stats)
    best_norm = _median(s["best_normalised"] for s in stats)
    return {"strategy": name, "seeds": len(stats),
            "found_collision_share": found / len(stats),
            "first_collision_median": float(q[1]),
            "first_collision_iqr": [float(q[0]), float(q[2])],
            "first_collision_seconds_median": first_collision_seconds_median(stats),
            "search_seconds_median": _time_median(s.get("search_seconds") for s in stats),
            "failures_per_second_median": _time_median(s.get("failures_per_second")
                                                       for s in stats),
            "compile_seconds": compile_seconds,
            "best_normalised_median": best_norm,
            "seeds_reaching_global_max": (None if any(s["reached_global_max"] is None
                                                      for s in stats) else
                                          int(sum(s["reached_global_max"] for s in stats))),
            "distinct_critical_median": _median(s["distinct"] for s in stats),
            "all_critical": truth["n_collisions"],
            "corner_share_median": _median(s["corner_share"] for s in stats),
            "final_mean_reward_median": _median(s["final_mean_reward"] for s in stats),
            "wall_seconds": wall, "per_seed": stats}


SEED_TIME_KEYS = ("first_collision_seconds", "search_seconds", "failures_per_second")
ROW_TIME_KEYS = ("first_collision_seconds_median", "search_seconds_median",
                 "failures_per_second_median", "compile_seconds", "wall_seconds")


def without_times(row: dict) -> dict:
    """A :func:`strategy_row` without its measured seconds and rates (:data:`ROW_TIME_KEYS`,
    and :data:`SEED_TIME_KEYS` of every per-seed row): the figures that repeat exactly
    between comparisons of the same configuration."""
    out = {k: v for k, v in row.items() if k not in ROW_TIME_KEYS}
    out["per_seed"] = [{k: v for k, v in s.items() if k not in SEED_TIME_KEYS}
                       for s in row.get("per_seed", [])]
    return out


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
    :func:`jaxfalsify.cache.exported_jit`) and compiled ahead, so loading it can happen while
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
        _, out = jax.lax.scan(upd, strategy.init(k_init, params),
                              jax.random.split(k_run, p.n_updates))
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
    :class:`~jaxfalsify.runs.Interrupted` (or the error) is raised and nothing is written."""
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

    agree("comparison configuration", store.sha256(json.dumps({  # not --jobs: per host
        "strategies": list(config.strategies), "seeds": config.seeds,
        "evaluations": config.evaluations, "budgets": list(config.budgets),
        "overhead": config.overhead, "space": base.space.describe(),
        "space_seed": config.space_seed, "sut_params": sut_lib.params_dict(base.sut_params),
        "strategy_params": {k: dict(v) for k, v in config.strategy_params.items()},
        "processes": num_processes, "code": cache.source_hash(base.sut.act, base.sut.init)},
        sort_keys=True, default=str).encode()))
    if out is None:
        out, lk = store.open_new_folder(Path("runs") / f"compare-{timestamp()}", "compare")
        existed = False
    else:
        out = Path(out)
        existed = out.exists()
        lk = store.open_folder(out, "compare", force=force,
                               name=".lock" if process_id == 0 else
                               f".lock-part-{process_id:05d}")
    try:
        lk.claim("compare")
        return _execute(config, out, base, progress, process_id, num_processes, clock, stop)
    except BaseException as e:
        if num_processes == 1 and sut_lib.callback_error(e) is not None:
            store.discard(out, "compare", lk, existed)  # the SUT raised: nothing to keep
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
        store.write_json(out / f".compare.part-{process_id:05d}.json", parts)
        barrier("jaxfalsify-compare-parts")
        all_parts = [json.loads((out / f".compare.part-{i:05d}.json").read_text())
                     for i in range(num_processes)]
        barrier("jaxfalsify-compare-parts-read")  # process 0 deletes them when it is done
        merged = {k: {"stats": sum((p[k]["stats"] for p in all_parts), []),
                      "wall": max(p[k]["wall"] for p in all_parts),
                      "compile": max(p[k]["compile"] for p in all_parts),
                      "overhead": _median(p[k].get("overhead") for p in all_parts),
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
            store.write_atomic(out / "config.toml", config.to_toml())
            store.write_json(out / "compare.json", result, indent=2)
            md = table_markdown(result)
            if config.budgets:  # the smaller budgets' table too, not only on the console
                md += "\n\n" + budgets_markdown(result)
            store.write_atomic(out / "compare.md", md + "\n")
            store.write_json(out / "timing.json", clock.summary(), indent=2)
        for i in range(num_processes if num_processes > 1 else 0):
            (out / f".compare.part-{i:05d}.json").unlink(missing_ok=True)
    result["timing"] = clock.summary()
    result["out"] = str(out)
    return result


def _num(x, fmt: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _frac(n, of) -> str:
    return "-" if n is None else f"{n}/{of}"


def _share(p: float | None) -> str:
    """A collision share for humans: scientific notation (``8.4e-03``), ``0`` for none."""
    if p is None or not np.isfinite(p):
        return "-"
    return "0" if p == 0 else f"{p:.1e}"


def _percent(p: float | None) -> str:
    """A share of evaluations in percent, two significant digits (``1.3%``, ``0.67%``,
    ``0.0025%``), ``0`` for none: one format down a column."""
    if p is None or not np.isfinite(p):
        return "-"
    if p == 0:
        return "0"
    x = 100 * p
    return f"{x:.2g}%" if x >= 1e-4 else f"{x:.1e}%"


def _plural(n: int, word: str) -> str:
    return f"{n:,} {word}{'' if n == 1 else 's'}"


def uniform_line(result: dict, u: dict, budget: int) -> str:
    """Uniform random's analytic expectation (from the ground truth, or estimated from a
    uniform sample of a space too large to sweep)."""
    if result.get("n_collisions") is None:
        lo, hi = result["collision_share_ci95"]
        src = (f"estimated from {result['sampled']:,} uniform scenarios "
               f"({result['sampled_collisions']} collided: p = {_share(u['p'])}, 95 % interval "
               f"{lo:.2g}..{hi:.2g})")
    else:
        src = (f"{_plural(result['n_collisions'], 'collision')} in "
               f"{_plural(result['n_scenarios'], 'scenario')}, p = {_share(u['p'])}")
    return (f"Uniform random, analytically ({src}): expected evaluations to the first collision "
            f"1/p = {_num(u['expected'], '.4g')} (median {_num(u['median'], '.4g')}); censored "
            f"at {budget + 1}: expected {u['expected_censored']:.4g}, median "
            f"{u['median_censored']:g}; a collision within {budget} evaluations with "
            f"probability {u['found_probability']:.3f}. Uniform's share of evaluations on box "
            f"corners: {_percent(result['uniform_corner_share'])}.")


def side_by_side(result: dict) -> str:
    """``", 2 strategies side by side"`` when the wall times were shared (else empty)."""
    jobs = result.get("jobs", 1)
    return f", {jobs} strategies side by side" if jobs > 1 else ""


def _seconds(x) -> str:
    """Seconds or a rate, three significant digits (``0.0312``, ``41.7``); ``-`` for none."""
    return _num(x, ".3g")


TIME_NOTE = ("Search s: the seed's own search time, compilation excluded (compile s, apart), "
             "to the end of the update holding the first collision (chunks of updates timed "
             "on the host, a chunk's time divided evenly among its updates); median over all "
             "seeds, a seed without a collision counting as never (- when half or more found "
             "none). Collisions per search s: distinct collision scenarios / the seed's search "
             "seconds for the budget, median.")


def requirement_words(result: dict) -> str:
    """```clash` (epsilon=1.5)`` of a comparison that names a requirement ("" without)."""
    req = result.get("requirement", "collision")
    if req == "collision":
        return ""
    params = result.get("requirement_params") or {}
    return f"`{req}`" + (" (" + ", ".join(f"{k}={v:g}" for k, v in params.items()) + ")"
                         if params else "")


def table_markdown(result: dict) -> str:
    """The comparison as a Markdown table, with uniform random's analytic expectation."""
    budget = result["evaluations"]
    head = ("| strategy | seeds with a collision | evaluations to first collision, median "
            f"[IQR] (none = {budget + 1}) | search s to first collision (median) | "
            "collisions per search s (median) | best, normalised (median) | "
            "seeds at global max | "
            "distinct critical found (median) / all | evaluations on box corners (median) | "
            "mean reward, last quarter (median) | overhead s / 1000 evaluations | "
            f"compile s | wall s (all seeds{side_by_side(result)}) |")
    lines = [head, "|" + "---|" * 13]
    if requirement_words(result):
        lines = [f"Critical: violating {requirement_words(result)} (the columns' collisions "
                 "are its violations, in the ground truth and in every search).", "", *lines]
    overhead = result.get("overhead", {})
    for r in result["rows"]:
        iqr = r["first_collision_iqr"]
        first = f"{r['first_collision_median']:g} [{iqr[0]:g}, {iqr[1]:g}]"
        lines.append(f"| {r['strategy']} | {r['found_collision_share'] * r['seeds']:.0f}/"
                     f"{r['seeds']} | {first} | "
                     f"{_seconds(r.get('first_collision_seconds_median'))} | "
                     f"{_seconds(r.get('failures_per_second_median'))} | "
                     f"{_num(r['best_normalised_median'], '.4f')} | "
                     f"{_frac(r['seeds_reaching_global_max'], r['seeds'])} | "
                     f"{_num(r['distinct_critical_median'], 'g')} / "
                     f"{'-' if r['all_critical'] is None else r['all_critical']} | "
                     f"{_percent(r['corner_share_median'])} | "
                     f"{_num(r['final_mean_reward_median'], '.4f')} | "
                     f"{_num(overhead.get(r['strategy']), '.3f')} | "
                     f"{_num(r.get('compile_seconds'), '.1f')} | "
                     f"{r['wall_seconds']:.1f} |")
    lines += ["", TIME_NOTE + (f" With {result['jobs']} strategies side by side these seconds "
                               "include sharing the machine (--jobs 1 times each alone)."
                               if result.get("jobs", 1) > 1 else "")]
    u = result.get("uniform_first_collision")
    if u:
        lines += ["", uniform_line(result, u, budget)]
    if result.get("n_collisions") is None:
        lines.append("No ground truth (the space is too large to sweep): no global maximum; "
                     "the share of collisions is estimated from a uniform sample.")
    elif result.get("global_max_reward") is None:
        lines.append(f"No scenario of the space has a finite reward (all "
                     f"{result['n_scenarios']:,} rollouts non-finite: the SUT returned NaN or "
                     "inf): no global maximum to normalise against.")
    else:
        lines.append("Best, normalised: (best - global min) / (global max - global min) over "
                     f"the space ({result['global_min_reward']:.4f} .. "
                     f"{result['global_max_reward']:.4f}), median over seeds with a finite best.")
    return "\n".join(lines)


def budgets_markdown(result: dict) -> str:
    """One table per comparison: per strategy and budget, seeds with a collision, evaluations
    to the first collision (median [IQR] over all seeds, none = budget + 1), seeds at the
    global maximum and the search seconds to the first collision (median over all seeds, see
    :func:`first_collision_seconds_median`); at the largest budget the distinct failures and
    the distinct collisions per search second (medians), the box-corner share, the search
    overhead and the compile seconds; uniform random's expectation in the last row (its
    collision chance within the budget and E[min(X, budget + 1)], X its evaluations to the
    first collision, so it compares with the censored medians beside it)."""
    blist = result["budgets"]
    top = blist[-1]["budget"]
    head = "| strategy | " + " | ".join(
        f"{b['budget']}: collision / first [IQR] / global max / search s to first"
        for b in blist) + \
        (f" | distinct failures (median at {top}) | collisions per search s (median at {top}) | "
         f"box corners (median at {top}) | overhead ms / evaluation | compile s |")
    lines = [head, "|" + "---|" * (len(blist) + 6)]
    overhead = result.get("overhead", {})
    names = [r["strategy"] for r in blist[-1]["rows"]]
    for k, name in enumerate(names):
        cells = []
        for b in blist:
            r = b["rows"][k]
            iqr = r["first_collision_iqr"]
            cells.append(f"{r['found_collision_share'] * r['seeds']:.0f}/{r['seeds']} / "
                         f"{r['first_collision_median']:g} [{iqr[0]:g}, {iqr[1]:g}] / "
                         f"{_frac(r['seeds_reaching_global_max'], r['seeds'])} / "
                         f"{_seconds(r.get('first_collision_seconds_median'))}")
        last = blist[-1]["rows"][k]
        o = overhead.get(name)
        lines.append(f"| {name} | " + " | ".join(cells) +
                     f" | {_num(last['distinct_critical_median'], 'g')} | "
                     f"{_seconds(last.get('failures_per_second_median'))} | "
                     f"{_percent(last['corner_share_median'])} | "
                     f"{'-' if o is None else f'{o:.3f}'} | "
                     f"{_num(last.get('compile_seconds'), '.1f')} |")
    cells = []
    for b in blist:
        u = b["uniform_first_collision"]
        cells.append(f"{u['found_probability']:.0%} / E[min(X, {b['budget'] + 1})] "
                     f"{_num(u['expected_censored'], '.4g')}, median {u['median_censored']:g}")
    estimated = ", p estimated from a uniform sample" if result.get("n_collisions") is None \
        else ""
    lines.append(f"| uniform random (analytic{estimated}) | " + " | ".join(cells) +
                 f" | | | {_percent(result['uniform_corner_share'])} | | |")
    return "\n".join(lines)
