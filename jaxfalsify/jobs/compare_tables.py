"""A comparison's result (:func:`jaxfalsify.jobs.compare.execute`) in words and Markdown tables:
the table per strategy (:func:`table_markdown`), the table per budget
(:func:`budgets_markdown`), uniform random's expectation in a line (:func:`uniform_line`), and
the number formats they share."""

from __future__ import annotations

import numpy as np

__all__ = [
    "share_text", "plural", "TIME_NOTE", "requirement_words", "table_markdown",
    "budgets_markdown"
]


def _num(x, fmt: str) -> str:
    return "-" if x is None or not np.isfinite(x) else format(x, fmt)


def _frac(n, of) -> str:
    return "-" if n is None else f"{n}/{of}"


def share_text(p: float | None) -> str:
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
    if x >= 10:  # whole percent (``.2g`` writes 100 as ``1e+02``)
        return f"{x:.0f}%"
    return f"{x:.2g}%" if x >= 1e-4 else f"{x:.1e}%"


def plural(n: int, word: str) -> str:
    return f"{n:,} {word}{'' if n == 1 else 's'}"


def uniform_line(result: dict, u: dict, budget: int) -> str:
    """Uniform random's analytic expectation (from the ground truth, or estimated from a
    uniform sample of a space too large to sweep)."""
    if result.get("n_collisions") is None:
        lo, hi = result["collision_share_ci95"]
        src = (f"estimated from {result['sampled']:,} uniform scenarios "
               f"({result['sampled_collisions']} collided: p = {share_text(u['p'])}, 95 % interval "
               f"{lo:.2g}..{hi:.2g})")
    else:
        src = (f"{plural(result['n_collisions'], 'collision')} in "
               f"{plural(result['n_scenarios'], 'scenario')}, p = {share_text(u['p'])}")
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
    :func:`jaxfalsify.jobs.compare_stats.first_collision_seconds_median`); at the largest budget
    the distinct failures and the distinct collisions per search second (medians), the
    box-corner share, the search overhead and the compile seconds; uniform random's
    expectation in the last row (its collision chance within the budget and
    E[min(X, budget + 1)], X its evaluations to the first collision, so it compares with the
    censored medians beside it)."""
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
