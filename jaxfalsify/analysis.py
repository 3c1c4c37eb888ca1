"""What a campaign found, computed once for every output (closing report, ``report.md``,
``summary.json``, ``critical.csv``, figures, replay, export).

Everything works on a campaign's records: ``indices (N, P)`` int and ``fields`` ``{name: (N,)}``
in evaluation order (row ``i`` is evaluation ``i + 1``), as a :class:`campaign.Result` holds them
and ``evaluations.parquet`` stores them (:func:`from_evaluations`).
"""

from __future__ import annotations

import numpy as np

from jaxfalsify.config import plain


def ranked_reward(fields: dict) -> np.ndarray:
    """Rewards as float64 with NaN (non-finite rollouts) as -inf: they never rank best."""
    r = np.asarray(fields["reward"], np.float64)
    return np.where(np.isnan(r), -np.inf, r)


def collided(fields: dict) -> np.ndarray:
    return np.asarray(fields["collision"], bool) & ~np.asarray(fields["nonfinite"], bool)


def best(fields: dict) -> int:
    """Row of the best evaluation (the first one reaching the maximum reward)."""
    return int(np.argmax(ranked_reward(fields)))


def first_collision(fields: dict) -> int | None:
    """Evaluation number (1-based) of the first collision, None if there was none."""
    hits = np.nonzero(collided(fields))[0]
    return int(hits[0]) + 1 if hits.size else None


def best_reached(fields: dict) -> int | None:
    """First evaluation after which the running best stays within 1 % of its final value;
    None when no evaluation has a finite reward."""
    run = np.maximum.accumulate(ranked_reward(fields))
    final = run[-1]
    if not np.isfinite(final):
        return None
    return int(np.argmax(run >= final - 0.01 * abs(final))) + 1


def moving_mean(fields: dict, window: int = 100) -> np.ndarray:
    """The reward's moving mean over the last ``window`` evaluations (fewer at the start;
    non-finite rewards skipped): ``(N,)``."""
    r = ranked_reward(fields)
    ok = np.isfinite(r)
    c = np.concatenate([[0.0], np.cumsum(np.where(ok, r, 0.0))])
    n = np.concatenate([[0], np.cumsum(ok)])
    i = np.arange(1, len(r) + 1)
    lo = np.maximum(i - window, 0)
    cnt = n[i] - n[lo]
    return np.where(cnt > 0, (c[i] - c[lo]) / np.maximum(cnt, 1), np.nan)


def learner_converged(fields: dict, window: int = 100, tol: float = 0.05) -> int | None:
    """The first evaluation from which the learner's moving mean reward (over ``window``
    evaluations) stays within ``tol`` (5 %) of its final value, relative to the range of the
    rewards seen (a mean near zero has no meaningful percentage); None before two windows.
    Unlike :func:`best_reached` (the running best), this is about what the learner
    *samples*: a converged learner keeps drawing scenarios as good as its final ones."""
    m = moving_mean(fields, window)
    if len(m) < 2 * window or not np.isfinite(m[-1]):
        return None
    r = ranked_reward(fields)
    span = np.ptp(r[np.isfinite(r)]) if np.any(np.isfinite(r)) else 0.0
    far = np.nonzero(~(np.abs(m - m[-1]) <= tol * max(span, 1e-9)))[0]
    return int(far[-1]) + 2 if far.size else 1


def typical_non_critical(fields: dict) -> int | None:
    """Row of the non-colliding evaluation with the median reward (paper Table II's
    'non-challenging'); None if every evaluation collided or was non-finite."""
    ok = np.nonzero(~np.asarray(fields["collision"], bool)
                    & ~np.asarray(fields["nonfinite"], bool))[0]
    if ok.size == 0:
        return None
    r = np.asarray(fields["reward"])[ok]
    return int(ok[np.argsort(r, kind="stable")[len(ok) // 2]])


def distinct_critical(indices: np.ndarray, fields: dict) -> list[dict]:
    """Distinct collision scenarios, ranked by reward (then by first evaluation): per scenario
    its ``indices``, ``row`` (first evaluation's row), ``first_evaluation``,
    ``times_evaluated`` and the first evaluation's fields."""
    rows = np.nonzero(collided(fields))[0]
    if rows.size == 0:
        return []
    keys, first, counts = np.unique(np.asarray(indices)[rows], axis=0, return_index=True,
                                    return_counts=True)
    first_rows = rows[first]
    reward = np.asarray(fields["reward"])[first_rows]
    order = np.lexsort((first_rows, -reward))
    return [{"indices": tuple(int(v) for v in keys[j]), "row": int(first_rows[j]),
             "first_evaluation": int(first_rows[j]) + 1, "times_evaluated": int(counts[j]),
             **{f: plain(np.asarray(v)[first_rows[j]]) for f, v in fields.items()}}
            for j in order]


def from_evaluations(ep: dict, space) -> tuple[np.ndarray, dict]:
    """``(indices (N, P), fields)`` from ``evaluations.parquet`` columns."""
    idx = np.stack([np.asarray(ep[f"{n}_idx"]) for n in space.names], -1).astype(np.int32)
    return idx, ep


# ----------------------------------------------------------------------------- Table II
OUTCOME_ROWS = (("reward", ".4f"), ("collision", ""), ("min_distance", ".2f"),
                ("final_distance", ".2f"), ("high_risk_share_second_half", ".2f"))


def table_ii(space, indices: np.ndarray, fields: dict) -> tuple[list[str], list[list[str]]]:
    """The best scenario beside a typical non-critical one, in the paper's Table II layout:
    ``(header, rows)`` of strings, shared by the closing report and ``report.md``."""
    b = best(fields)
    t = typical_non_critical(fields)
    head_b = "Challenging (best)" if collided(fields)[b] else "Best (no collision)"
    header = ["parameter", head_b, "Non-challenging (typical)"]
    rows = []
    for p, (n, u) in enumerate(zip(space.names, space.units)):
        unit = f" {u}" if u in ("m", "m/s") else ""
        cells = [n]
        for r in (b, t):
            cells.append("-" if r is None else
                         format_value(space, p, space.table[p][int(indices[r][p])]) + unit)
        rows.append(cells)
    for f, fmt in OUTCOME_ROWS:
        cells = [f]
        for r in (b, t):
            cells.append("-" if r is None else format(np.asarray(fields[f])[r].item(), fmt))
        rows.append(cells)
    return header, rows


def format_value(space, p: int, v: float) -> str:
    """A parameter value as the simulator used it: a draw with the decimals its space declares,
    integers without any, explicit ``values`` as written (the shortest text that reads back
    to the same number: ``0.0125``, not ``0.013``)."""
    par = space.parameters[p]
    if par.distribution == "integers" or float(v).is_integer() and par.distribution == "values":
        return f"{v:.0f}" if float(v).is_integer() else f"{v:g}"
    if par.distribution == "values":
        return np.format_float_positional(float(v), unique=True, trim="-")
    return f"{v:.{par.decimals}f}"


def text_table(header: list[str], rows: list[list[str]]) -> str:
    widths = [max(len(r[i]) for r in [header] + rows) for i in range(len(header))]
    line = lambda r: (r[0].ljust(widths[0]) + "".join(c.rjust(w + 4) for c, w in
                                                       zip(r[1:], widths[1:])))
    return "\n".join([line(header)] + [line(r) for r in rows])


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
                     + ["| " + " | ".join(r) + " |" for r in rows])
