"""What a campaign found, computed once for every output (closing report, ``report.md``,
``summary.json``, ``critical.csv``, figures, replay, export).

Everything works on a campaign's records: ``indices (N, P)`` int and ``fields`` ``{name: (N,)}``
in evaluation order (row ``i`` is evaluation ``i + 1``), as a :class:`campaign.Result` holds them
and ``evaluations.parquet`` stores them (:func:`from_evaluations`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxfalsify.base.config import plain

__all__ = [
    "ranked_reward", "collided", "critical", "best", "first_collision", "first_critical",
    "best_reached", "moving_mean", "learner_converged", "typical_non_critical",
    "distinct_critical", "distinct_critical_rows", "ALIGNED_DIMS", "chebyshev_components",
    "FailureClusters", "failure_clusters", "from_evaluations", "OUTCOME_ROWS", "table_ii",
    "format_value", "text_table", "markdown_table"
]


def ranked_reward(fields: dict) -> np.ndarray:
    """Rewards as float64 with NaN (non-finite rollouts) as -inf: they never rank best."""
    r = np.asarray(fields["reward"], np.float64)
    return np.where(np.isnan(r), -np.inf, r)


def collided(fields: dict) -> np.ndarray:
    """Which evaluations collided (a finite rollout whose boxes touched)."""
    return np.asarray(fields["collision"], bool) & ~np.asarray(fields["nonfinite"], bool)


def critical(fields: dict) -> np.ndarray:
    """Which evaluations violated the run's requirement (``violated``; a run that names none,
    or records of a run without the column: the collisions)."""
    if "violated" not in fields:
        return collided(fields)
    return np.asarray(fields["violated"], bool) & ~np.asarray(fields["nonfinite"], bool)


def best(fields: dict) -> int:
    """Row of the best evaluation (the first one reaching the maximum reward)."""
    return int(np.argmax(ranked_reward(fields)))


def first_collision(fields: dict) -> int | None:
    """Evaluation number (1-based) of the first collision, None if there was none."""
    hits = np.nonzero(collided(fields))[0]
    return int(hits[0]) + 1 if hits.size else None


def first_critical(fields: dict) -> int | None:
    """Evaluation number (1-based) of the first violation of the run's requirement."""
    hits = np.nonzero(critical(fields))[0]
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
    """Row of the evaluation with the median reward among those that satisfy the paper's
    requirement, always not clash (robustness >= 0: the box gap never below epsilon), paper
    Table II's 'non-challenging', that neither collided nor violated the run's requirement;
    among those if every one clashed; None if every evaluation collided, violated the
    requirement or was non-finite."""
    fine = ~collided(fields) & ~critical(fields) & ~np.asarray(fields["nonfinite"], bool)
    ok = np.nonzero(fine & (np.asarray(fields["robustness"]) >= 0))[0]
    if ok.size == 0:
        ok = np.nonzero(fine)[0]
    if ok.size == 0:
        return None
    r = np.asarray(fields["reward"])[ok]
    return int(ok[np.argsort(r, kind="stable")[len(ok) // 2]])


def distinct_critical_rows(indices: np.ndarray, fields: dict):
    """The distinct critical scenarios in :func:`distinct_critical`'s order, as arrays:
    ``(index vectors (n, P), first evaluation's row (n,), times evaluated (n,))``."""
    idx = np.asarray(indices)
    rows = np.nonzero(critical(fields))[0]
    if rows.size == 0:
        return (np.zeros((0, idx.shape[1]), idx.dtype), np.zeros(0, np.int64),
                np.zeros(0, np.int64))
    sel = idx[rows].astype(np.int64)
    # one int64 code per index vector (mixed radix; the radices' product is at most the
    # space's size, below 2**63): a 1-D unique is ~10x faster than np.unique(axis=0)
    radix = sel.max(axis=0) + 1
    weights = np.concatenate([np.cumprod(radix[::-1])[::-1][1:], [1]])
    _, first, counts = np.unique(sel @ weights, return_index=True, return_counts=True)
    keys = idx[rows][first]
    first_rows = rows[first]
    reward = np.asarray(fields["reward"])[first_rows]
    order = np.lexsort((first_rows, -reward))
    return keys[order], first_rows[order], counts[order]


def distinct_critical(indices: np.ndarray, fields: dict) -> list[dict]:
    """Distinct collision scenarios, ranked by reward (then by first evaluation): per scenario
    its ``indices``, ``row`` (first evaluation's row), ``first_evaluation``,
    ``times_evaluated`` and the first evaluation's fields."""
    keys, first_rows, counts = distinct_critical_rows(indices, fields)
    return [{"indices": tuple(int(v) for v in k), "row": int(r), "first_evaluation": int(r) + 1,
             "times_evaluated": int(c), **{f: plain(np.asarray(v)[r]) for f, v in fields.items()}}
            for k, r, c in zip(keys, first_rows, counts)]


# ----------------------------------------------------------------------------- failure clusters
ALIGNED_DIMS = 10  # coordinates whose 2^k cell alignments are enumerated (chebyshev_components)


def _link(parent: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Join the pairs of rows ``(u[i], v[i])`` in the forest ``parent`` ``(n,)``, given and
    returned flat (each entry its tree's root, the smallest row of the tree). Hook and
    compress: each round hooks every larger root of a pair still apart to the smallest root
    it meets, then jumps pointers to the roots; O(log n) rounds."""
    while u.size:
        ru, rv = parent[u], parent[v]
        apart = ru != rv
        u, v, ru, rv = u[apart], v[apart], ru[apart], rv[apart]
        if not u.size:
            break
        np.minimum.at(parent, np.maximum(ru, rv), np.minimum(ru, rv))
        while True:
            up = parent[parent]
            if np.array_equal(up, parent):
                break
            parent = up
    return parent


def chebyshev_components(points) -> np.ndarray:
    """Connected components of integer points under Chebyshev distance 1: two points are
    neighbours when they differ by at most 1 in every coordinate (the 3^P - 1 cells around a
    grid cell, diagonals included); a component is a set of points joined by a chain of
    neighbours.

    Args:
      points: ``(n, P)`` ints (grid index vectors); repeated rows join (distance 0).
    Returns:
      ``(n,)`` int64: each point's component, numbered 0.. in the order of each component's
      first row (row 0 is in component 0).
    Raises:
      ValueError: ``points`` not a 2-D integer array.

    Method: two points are neighbours exactly when, for some alignment ``a`` in {0, 1}^P, they
    fall into the same cell of the grid of 2-wide cells ``(x + a) // 2`` (per coordinate, the
    even-aligned or the odd-aligned cell of two consecutive values); a cell holds only mutual
    neighbours. So each of the 2^P alignments partitions the points into groups of neighbours
    (one sort of n keys), and a vectorised union-find joins each group: O(2^P n log n) time,
    O(n) memory, no pairwise comparisons (10^6 points on one CPU core: about 1.5 s for P = 5,
    8 s for P = 8). Coordinates constant over all points are dropped first, and gaps of more
    than one value along a coordinate shrink to two (neighbourhood unchanged). With more than
    ``ALIGNED_DIMS`` (10) varying coordinates, only the 10 with the most distinct values are
    aligned (2^10 partitions); each group then holds candidates, checked on the other
    coordinates pair by pair in sorted order: exact, but quadratic in the size of the
    largest group.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or not (np.issubdtype(pts.dtype, np.integer) or pts.size == 0):
        raise ValueError(f"points must be a 2-D integer array (got shape {pts.shape}, "
                         f"dtype {pts.dtype})")
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0, np.int64)
    cols = []  # (distinct values, coordinate with gaps shrunk to 2) of each varying column
    for c in pts.T.astype(np.int64):
        vals, inv = np.unique(c, return_inverse=True)
        if vals.size > 1:
            pos = np.concatenate([[0], np.cumsum(np.minimum(np.diff(vals), 2))])
            cols.append((vals.size, pos[inv.reshape(-1)]))
    cols = [c for _, c in sorted(cols, key=lambda dc: -dc[0])]  # stable: most values first
    aligned, rest = cols[:ALIGNED_DIMS], cols[ALIGNED_DIMS:]
    half = [(c >> 1, (c + 1) >> 1) for c in aligned]  # each value's cell in both alignments
    radix = [int(h1.max()) + 1 for _, h1 in half]
    if np.prod([float(r) for r in radix]) < 2.0**62:  # one int64 per cell: a mixed radix
        stride = np.cumprod([1] + radix[:-1]).astype(np.int64)
        half = [(h0 * s, h1 * s) for (h0, h1), s in zip(half, stride)]

        def cell(bits):
            return sum((h[b] for h, b in zip(half, bits)), np.zeros(n, np.int64))
    else:  # too many cells for an int64: number the distinct ones
        def cell(bits):
            return np.unique(np.stack([h[b] for h, b in zip(half, bits)], 1), axis=0,
                             return_inverse=True)[1].reshape(-1)
    rest = np.stack(rest, 1) if rest else None
    parent = np.arange(n)
    for a in range(2 ** len(aligned)):
        key = cell([(a >> j) & 1 for j in range(len(aligned))])
        order = np.argsort(key)  # any order within a group: the labels do not depend on it
        same = key[order[1:]] == key[order[:-1]]
        if rest is None:  # a group's points are mutual neighbours: chain them in sorted order
            parent = _link(parent, order[1:][same], order[:-1][same])
        else:
            run = same  # run[i]: sorted positions i and i + j in one group (all pairs, by j)
            for j in range(1, n):
                if j > 1:
                    run = run[:-1] & same[j - 1:]
                if not run.any():
                    break
                i = np.nonzero(run)[0]
                u, v = order[i], order[i + j]
                near = np.all(np.abs(rest[u] - rest[v]) <= 1, axis=1)
                parent = _link(parent, u[near], v[near])
        if parent.max() == 0:  # one component: nothing left to join
            break
    _, label = np.unique(parent, return_inverse=True)  # roots are each component's first row
    return label.reshape(-1).astype(np.int64)


@dataclasses.dataclass(frozen=True)
class FailureClusters:
    """The failure clusters of a run's records (:func:`failure_clusters`). ``n`` distinct
    critical scenarios in :func:`distinct_critical`'s order (rank 1 first), ``k`` clusters
    numbered 1..k (cluster 1 the largest)."""

    indices: np.ndarray  # (n, P) int: each distinct critical scenario's index vector
    rows: np.ndarray  # (n,) int: the row of its first evaluation
    labels: np.ndarray  # (n,) int: its cluster number, 1..k
    sizes: np.ndarray  # (k,) int: distinct critical scenarios per cluster, cluster 1 first
    first_evaluation: np.ndarray  # (k,) int: 1-based evaluation that first found the cluster
    representative: np.ndarray  # (k,) int: position (0-based rank) of its best member

    @property
    def n(self) -> int:
        return int(self.labels.size)

    @property
    def k(self) -> int:
        return int(self.sizes.size)


def failure_clusters(indices: np.ndarray, fields: dict) -> FailureClusters:
    """Group the distinct critical scenarios (:func:`distinct_critical`: distinct index
    vectors of the collisions) into failure clusters: two distinct critical scenarios are
    neighbours when their index vectors differ by at most 1 in every parameter (Chebyshev
    distance 1 in the value grid: the 3^P - 1 surrounding cells, diagonals included); the
    clusters are the connected components of that neighbour graph
    (:func:`chebyshev_components`). Clusters are numbered 1.. by decreasing size (distinct
    critical scenarios), ties by the rank of their best member (best reward, then earliest
    first evaluation, as ``critical.csv`` ranks); a cluster's representative is that best
    member.

    Args:
      indices: ``(N, P)`` int index vectors of the evaluations, in evaluation order.
      fields: ``{name: (N,)}`` with ``collision``, ``nonfinite`` and ``reward``.
    Returns:
      :class:`FailureClusters` (empty arrays when nothing collided).
    """
    idx = np.asarray(indices)
    keys, rows, _ = distinct_critical_rows(idx, fields)
    comp = chebyshev_components(keys)  # numbered by first member in rank order
    sizes = np.bincount(comp) if comp.size else np.zeros(0, np.int64)
    order = np.argsort(-sizes, kind="stable")  # ties: smaller best rank first
    number = np.empty_like(order)
    number[order] = np.arange(order.size)
    labels = number[comp] + 1
    first = np.full(order.size, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(first, labels - 1, rows.astype(np.int64) + 1)
    rep = np.full(order.size, np.iinfo(np.int64).max, np.int64)
    np.minimum.at(rep, labels - 1, np.arange(labels.size))
    return FailureClusters(keys.astype(np.int64).reshape(-1, idx.shape[1]),
                           rows.astype(np.int64), labels.astype(np.int64),
                           sizes[order].astype(np.int64), first, rep)


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
    head_b = "Challenging (best)" if critical(fields)[b] else "Best (no violation)"
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

    def line(r):
        return r[0].ljust(widths[0]) + "".join(c.rjust(w + 4)
                                               for c, w in zip(r[1:], widths[1:]))

    return "\n".join([line(header)] + [line(r) for r in rows])


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    return "\n".join(["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
                     + ["| " + " | ".join(r) + " |" for r in rows])
