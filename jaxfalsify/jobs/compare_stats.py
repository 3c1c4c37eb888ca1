"""A comparison's figures: per seed (:func:`seed_stats`) and per strategy over its seeds
(:func:`strategy_row`), and uniform random's analytic expectation
(:func:`uniform_first_collision`). Per strategy:

* seeds that found a collision;
* evaluations to the first collision, median and IQR over **all** seeds, a seed that found none
  counting ``budget + 1`` (censored; a median above the budget means most seeds found none),
  beside uniform random's analytic expectation (:func:`uniform_first_collision`);
* search seconds to the first collision and distinct collisions per search second, per seed
  and as medians, with the strategy's compile seconds apart (see *Search time* in
  :mod:`jaxfalsify.jobs.compare`);
* the best reward, normalised as ``(best - global min) / (global max - global min)`` in [0, 1]
  (1 = the global maximum; never negative, whatever the sign of the rewards), median over the
  seeds with a finite best; and how many seeds reached the global maximum;
* distinct collision scenarios found (median) over all of the space;
* the share of evaluations on box corners (every parameter at its first or last value;
  uniform random's share is ``2^P' / N``, P' the parameters with two or more values);
* the mean reward of the last quarter of the evaluations (the last 1000 of 4000).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxfalsify.engine import campaign
from jaxfalsify.outputs import analysis

__all__ = [
    "TOL", "uniform_first_collision", "corner_mask", "seed_stats", "median",
    "first_collision_seconds_median", "strategy_row", "SEED_TIME_KEYS", "without_times"
]

TOL = 1e-6  # reward equality with the global maximum (rewards are float32 sums)


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
    (default all). ``truth``: :func:`jaxfalsify.jobs.compare.truth_summary`
    (``global_max_reward`` None when the space is too large to sweep). Times in seconds of
    search, compilation excluded (:meth:`jaxfalsify.engine.campaign.Result.search_seconds_at`):
    ``first_collision_seconds`` at the end of the update holding the first collision (None
    without one), ``search_seconds`` at the end of the update holding evaluation ``budget``,
    ``failures_per_second`` = distinct collision scenarios / ``search_seconds`` (all three None
    when ``r`` was not timed)."""
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


def median(xs) -> float:
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
    best_norm = median(s["best_normalised"] for s in stats)
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
            "distinct_critical_median": median(s["distinct"] for s in stats),
            "all_critical": truth["n_collisions"],
            "corner_share_median": median(s["corner_share"] for s in stats),
            "final_mean_reward_median": median(s["final_mean_reward"] for s in stats),
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
