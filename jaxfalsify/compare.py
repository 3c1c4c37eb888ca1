"""``jaxfalsify compare``: strategies on the same space and SUT, many seeds, against the
exhaustive sweep as ground truth (from the per-user cache, see :func:`jaxfalsify.sweep.ground_truth`).

Per strategy (its seeds in one compiled call), see :func:`seed_stats` and :func:`strategy_row`:

* seeds that found a collision;
* evaluations to the first collision, median and IQR over **all** seeds, a seed that found none
  counting ``budget + 1`` (censored; a median above the budget means most seeds found none),
  beside uniform random's analytic expectation (:func:`uniform_first_collision`);
* the best reward, normalised as ``(best - global min) / (global max - global min)`` in [0, 1]
  (1 = the global maximum; never negative, whatever the sign of the rewards), median over the
  seeds with a finite best; and how many seeds reached the global maximum;
* distinct collision scenarios found (median) over all of the space;
* the share of evaluations on box corners (every parameter at its first or last value;
  uniform random's share is ``2^P' / N``, P' the parameters with two or more values);
* the mean reward of the last quarter of the evaluations (the last 1000 of 4000);
* search overhead: seconds per 1000 evaluations the strategy's own ``ask``/``tell`` take without
  simulation (timed separately after compilation, all seeds at once; ``result["overhead"]``);
* wall seconds for all seeds together, compilation included.

``compare.json`` holds every figure per seed (``per_seed`` rows).
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from jaxfalsify import analysis, campaign, config as cfg, search, store
from jaxfalsify.progress import Clock, Progress
from jaxfalsify.runs import RunConfig

TOL = 1e-6  # reward equality with the global maximum (rewards are float32 sums)
DEFAULT_STRATEGIES = ("reinforce/default", "reinforce/paper", "random", "grid", "cem",
                      "anneal", "cmaes")


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

    def run_config(self, strategy: str) -> RunConfig:
        return RunConfig(space=self.space, space_seed=self.space_seed, sut=self.sut,
                         sut_params=self.sut_params, strategy=strategy,
                         evaluations=self.evaluations)

    def check(self) -> None:
        from jaxfalsify.runs import check_int

        check_int("seeds", self.seeds, 1, 10_000)
        if not self.strategies:
            raise ValueError("strategies: none given")
        for s in self.strategies:
            search.canonical(s)
        self.run_config(self.strategies[0]).build()

    def to_toml(self) -> str:
        return cfg.dumps_toml({"kind": "compare", "strategies": list(self.strategies),
                               "seeds": self.seeds, "evaluations": self.evaluations,
                               "space_seed": self.space_seed, "sut": self.sut,
                               "sut_params": dict(self.sut_params),
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


def seed_stats(seed: int, r: campaign.Result, truth: dict, budget: int | None = None) -> dict:
    """One seed's figures (see the module docstring). ``truth``: :func:`truth_summary`."""
    budget = r.n if budget is None else int(budget)
    gmax, gmin = truth["global_max_reward"], truth["global_min_reward"]
    ranked = analysis.ranked_reward(r.fields)
    best = float(ranked.max()) if r.n else -np.inf
    first = analysis.first_collision(r.fields)
    tail = ranked[r.n - max(1, r.n // 4):] if r.n else ranked
    tail = tail[np.isfinite(tail)]
    return {"seed": seed, "first_collision": first,
            "first_collision_censored": first if first is not None else budget + 1,
            "best": best if np.isfinite(best) else None,
            "best_normalised": (float((best - gmin) / (gmax - gmin)) if np.isfinite(best)
                                and gmax > gmin else (1.0 if np.isfinite(best) else None)),
            "reached_global_max": bool(np.isfinite(best) and best >= gmax - TOL),
            "distinct": len(analysis.distinct_critical(r.indices, r.fields)),
            "corner_share": float(np.mean(corner_mask(r.indices, r.space.shape)))
            if r.n else 0.0,
            "final_mean_reward": float(np.mean(tail)) if tail.size else None}


def _median(xs) -> float:
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else float("nan")


def strategy_row(name: str, stats: list[dict], truth: dict, wall: float) -> dict:
    first = np.array([s["first_collision_censored"] for s in stats], np.float64)
    q = np.percentile(first, [25, 50, 75])
    found = sum(s["first_collision"] is not None for s in stats)
    best_norm = _median(s["best_normalised"] for s in stats)
    return {"strategy": name, "seeds": len(stats),
            "found_collision_share": found / len(stats),
            "first_collision_median": float(q[1]),
            "first_collision_iqr": [float(q[0]), float(q[2])],
            "best_normalised_median": best_norm,
            "best_over_global_max_median": best_norm,  # the former name: the same figure
            "seeds_reaching_global_max": int(sum(s["reached_global_max"] for s in stats)),
            "distinct_critical_median": _median(s["distinct"] for s in stats),
            "all_critical": int(truth["n_collisions"]),
            "corner_share_median": _median(s["corner_share"] for s in stats),
            "final_mean_reward_median": _median(s["final_mean_reward"] for s in stats),
            "wall_seconds": wall, "per_seed": stats}


def truth_summary(sp, b, budget: int | None = None) -> dict:
    from jaxfalsify.sweep import ground_truth

    t = ground_truth(sp, b.sut, b.sut_params)
    r = np.where(np.isnan(t["reward"]), -np.inf, t["reward"]).astype(np.float64)
    gmax = float(r.max())
    finite = r[np.isfinite(r)]
    n_coll = int(np.sum(t["collision"]))
    shape = np.asarray(sp.shape)
    out = {"n_scenarios": int(len(r)), "n_collisions": n_coll, "global_max_reward": gmax,
           "global_min_reward": float(finite.min()) if finite.size else gmax,
           "global_max_ties": int(np.sum(r == gmax)),
           "uniform_corner_share": float(2.0 ** np.sum(shape > 1) / len(r))}
    if budget is not None:
        out["uniform_first_collision"] = uniform_first_collision(len(r), n_coll, budget)
    return out


def search_overhead(strategy, strategy_params, p: campaign.Plan, n_seeds: int) -> float:
    """Seconds per 1000 evaluations (per seed) of the strategy's own ask/tell loop for the
    campaign's updates, without simulation (zero rewards, no collisions), all seeds in one
    compiled call as the campaign runs them; timed on a second call, after compilation."""
    import jax
    import jax.numpy as jnp

    B = strategy.batch

    def one_seed(key):
        def upd(state, k):
            k_ask, k_tell = jax.random.split(k)
            idx, state = strategy.ask(k_ask, state, strategy_params)
            z = jnp.zeros(B, jnp.float32)
            state = strategy.tell_outcome(k_tell, state, idx, z, z + 1.0,
                                          jnp.zeros(B, bool), strategy_params)
            return state, idx[0, 0]

        k_init, k_run = jax.random.split(key)
        _, out = jax.lax.scan(upd, strategy.init(k_init, strategy_params),
                              jax.random.split(k_run, p.n_updates))
        return out.sum()

    fn = jax.jit(lambda keys: jax.lax.map(one_seed, keys))
    keys = jax.random.split(jax.random.key(0), n_seeds)
    jax.block_until_ready(fn(keys))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(keys))
    return (time.perf_counter() - t0) / (n_seeds * p.n_updates * B / 1000.0)


def execute(config: CompareConfig, out: Path | str, *, force: bool = False,
            progress: Progress | None = None, stop=None, process_id: int = 0,
            num_processes: int = 1, startup_seconds: float = 0.0) -> dict:
    """Run every strategy on seeds 0..seeds-1 and write ``compare.json``/``compare.md`` to
    ``out``. With several processes (``jax.distributed``), process i runs its contiguous share
    of the seeds and writes a part; process 0 merges. Returns the result."""

    clock = Clock(startup_seconds)
    progress = progress or Progress()
    out = Path(out)
    config.check()
    base = config.run_config(config.strategies[0]).build()
    lk = store.open_folder(out, "compare", force=force,
                           name=".lock" if process_id == 0 else f".lock-part-{process_id:05d}")
    try:
        lk.claim("compare")
        return _execute(config, out, base, progress, process_id, num_processes, clock, stop)
    finally:
        lk.release()


def _execute(config: CompareConfig, out: Path, base, progress: Progress, process_id: int,
             num_processes: int, clock: Clock, stop) -> dict:
    from jaxfalsify.distributed import barrier, share

    sp = base.space
    progress.phase(f"ground truth: every scenario of {sp.name} ({sp.size:,}) x {config.sut}")
    with clock("ground_truth"):
        truth = truth_summary(sp, base, config.evaluations) if process_id == 0 else None
        barrier("jaxfalsify-compare-truth")
        if truth is None:
            truth = truth_summary(sp, base, config.evaluations)  # cached by process 0: a load
    lo, hi = share(config.seeds, process_id, num_processes)
    mine = list(range(lo, hi))
    parts: dict[str, dict] = {}
    for k, entry in enumerate(config.strategies):
        b = config.run_config(entry).build()
        label = search.canonical(entry)
        t0 = time.perf_counter()
        progress.phase(f"[{k + 1}/{len(config.strategies)}] {label}: compiling "
                       f"{len(mine)} seeds x {config.evaluations} evaluations")
        started = {}

        def chunk_done(done, records, label=label):
            if not started:
                progress.start(b.plan.budget, done, "eval", f"{label} ({len(mine)} seeds)")
                started["yes"] = True
            progress.update(done)

        try:
            results = campaign.run_seeds(sp, b.sut, b.sut_params, b.strategy,
                                         b.strategy_params, b.plan, mine, progress=chunk_done,
                                         stop=stop) if mine else []
        except (campaign.Stopped, KeyboardInterrupt):
            progress.close()
            from jaxfalsify.runs import Interrupted

            raise Interrupted("compare", out, k, len(config.strategies), "strategies (nothing "
                              "written; rerun the comparison)") from None
        progress.close()
        wall = time.perf_counter() - t0
        stats = [seed_stats(s, r, truth, config.evaluations) for s, r in zip(mine, results)]
        with clock("overhead"):
            overhead = (search_overhead(b.strategy, b.strategy_params, b.plan, len(mine))
                        if mine and config.overhead else None)
        parts[label] = {"stats": stats, "wall": wall, "overhead": overhead,
                        "compile": results[0].compile_seconds if results else 0.0}
        clock.add("compile", parts[label]["compile"])
        clock.add("search", wall - parts[label]["compile"])
    if num_processes > 1:
        out.mkdir(parents=True, exist_ok=True)
        store.write_json(out / f".compare.part-{process_id:05d}.json", parts)
        barrier("jaxfalsify-compare-parts")
        all_parts = [json.loads((out / f".compare.part-{i:05d}.json").read_text())
                     for i in range(num_processes)]
        merged = {k: {"stats": sum((p[k]["stats"] for p in all_parts), []),
                      "wall": max(p[k]["wall"] for p in all_parts),
                      "overhead": _median(p[k].get("overhead") for p in all_parts)}
                  for k in parts}
    else:
        merged = parts
    rows = [strategy_row(k, v["stats"], truth, v["wall"]) for k, v in merged.items()]
    result = {"space": sp.name, "space_seed": config.space_seed, "sut": config.sut,
              "evaluations": config.evaluations, "seeds": config.seeds,
              "processes": num_processes, **truth, "rows": rows,
              "overhead": {k: v.get("overhead") for k, v in merged.items()},
              "versions": cfg.versions()}
    if process_id == 0:
        with clock("writing"):
            out.mkdir(parents=True, exist_ok=True)
            store.write_atomic(out / "config.toml", config.to_toml())
            store.write_json(out / "compare.json", result, indent=2)
            store.write_atomic(out / "compare.md", table_markdown(result) + "\n")
            store.write_json(out / "timing.json", clock.summary(), indent=2)
        for i in range(num_processes if num_processes > 1 else 0):
            (out / f".compare.part-{i:05d}.json").unlink(missing_ok=True)
    result["timing"] = clock.summary()
    return result


def _num(x, fmt: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def table_markdown(result: dict) -> str:
    """The comparison as a Markdown table, with uniform random's analytic expectation."""
    budget = result["evaluations"]
    head = ("| strategy | seeds with a collision | evaluations to first collision, median "
            f"[IQR] (none = {budget + 1}) | best, normalised (median) | seeds at global max | "
            "distinct critical found (median) / all | evaluations on box corners (median) | "
            "mean reward, last quarter (median) | overhead s / 1000 evaluations | "
            "wall s (all seeds) |")
    lines = [head, "|" + "---|" * 10]
    overhead = result.get("overhead", {})
    for r in result["rows"]:
        iqr = r["first_collision_iqr"]
        first = f"{r['first_collision_median']:g} [{iqr[0]:g}, {iqr[1]:g}]"
        lines.append(f"| {r['strategy']} | {r['found_collision_share'] * r['seeds']:.0f}/"
                     f"{r['seeds']} | {first} | {_num(r['best_normalised_median'], '.4f')} | "
                     f"{r['seeds_reaching_global_max']}/{r['seeds']} | "
                     f"{_num(r['distinct_critical_median'], 'g')} / {r['all_critical']} | "
                     f"{_num(r['corner_share_median'], '.2%')} | "
                     f"{_num(r['final_mean_reward_median'], '.4f')} | "
                     f"{_num(overhead.get(r['strategy']), '.3f')} | "
                     f"{r['wall_seconds']:.1f} |")
    u = result.get("uniform_first_collision")
    if u:
        lines.append("")
        lines.append(f"Uniform random, analytically ({result['n_collisions']} collisions in "
                     f"{result['n_scenarios']} scenarios, p = {u['p']:.3g}): expected evaluations "
                     f"to the first collision 1/p = {_num(u['expected'], '.4g')} (median "
                     f"{_num(u['median'], '.4g')}); censored at {budget + 1}: expected "
                     f"{u['expected_censored']:.4g}, median {u['median_censored']:g}; a collision "
                     f"within {budget} evaluations with probability {u['found_probability']:.3f}."
                     f" Uniform's share of evaluations on box corners: "
                     f"{result['uniform_corner_share']:.2%}.")
    lines.append("Best, normalised: (best - global min) / (global max - global min) over the "
                 f"space ({result['global_min_reward']:.4f} .. {result['global_max_reward']:.4f})"
                 ", median over seeds with a finite best.")
    return "\n".join(lines)
