"""Failure clusters (``analysis.failure_clusters``): distinct critical scenarios joined when their
index vectors differ by at most 1 in every parameter. Checked against a hand-built failure set,
against a brute-force O(n^2) neighbour graph searched breadth-first, and end to end through a
run's ``critical.csv``, ``summary.json``, closing lines, report and figure."""

import csv
import json
import shutil
from collections import deque

import numpy as np
import pyarrow.parquet as pq
import pytest

from jaxfalsify.jobs import runs
from jaxfalsify.outputs import analysis


# ----------------------------------------------------------------------------- oracles
def bfs_components(points) -> list[int]:
    """Each point's component under Chebyshev distance <= 1, by brute force: every pair
    compared, breadth-first search from each unvisited point in row order (so components are
    numbered by their first row)."""
    pts = [tuple(int(v) for v in p) for p in points]
    n = len(pts)
    near = [[j for j in range(n) if j != i and max((abs(a - b) for a, b in zip(pts[i], pts[j])),
                                                     default=0) <= 1] for i in range(n)]
    label = [-1] * n
    c = 0
    for s in range(n):
        if label[s] >= 0:
            continue
        label[s] = c
        todo = deque([s])
        while todo:
            i = todo.popleft()
            for j in near[i]:
                if label[j] < 0:
                    label[j] = c
                    todo.append(j)
        c += 1
    return label


def oracle_clusters(indices, collision, nonfinite, reward):
    """Distinct failing scenarios (a dict of index tuples, first row kept), ranked by reward
    then first row; their brute-force components numbered by decreasing size, ties by the
    best rank in the cluster. Returns ``(ranked tuples, cluster number per tuple, first row
    per tuple)``."""
    first = {}
    for row, (idx, c, nf) in enumerate(zip(indices, collision, nonfinite)):
        if c and not nf:
            first.setdefault(tuple(int(v) for v in idx), row)
    ranked = sorted(first, key=lambda t: (-float(reward[first[t]]), first[t]))
    comp = bfs_components(ranked)
    members = {}
    for rank, c in enumerate(comp):
        members.setdefault(c, []).append(rank)
    order = sorted(members, key=lambda c: (-len(members[c]), min(members[c])))
    number = {c: k + 1 for k, c in enumerate(order)}
    return ranked, [number[c] for c in comp], first


# ----------------------------------------------------------------------------- hand-built set
def test_three_blobs_in_a_3d_grid():
    """A diagonal chain (joined through corners), two blobs of 3 (a tie, broken by the best
    reward), a single cell two steps from a blob (kept apart), a non-finite collision that
    would bridge them (ignored), repeats and non-colliding neighbours (ignored)."""
    A = [(0, 0, 0), (1, 1, 1), (2, 2, 2), (2, 3, 1)]  # each step a diagonal
    B = [(5, 0, 0), (5, 1, 0), (6, 1, 1)]
    C = [(8, 1, 1)]  # two steps from (6, 1, 1): its own cluster
    D = [(0, 7, 7), (1, 8, 8), (0, 8, 7)]
    evals = [  # (index vector, collision, nonfinite, reward), in evaluation order
        (A[0], 1, 0, 0.10), (B[0], 1, 0, 0.20), ((7, 1, 1), 1, 1, 0.90),  # non-finite bridge
        ((3, 3, 3), 0, 0, 0.95),  # next to A, no collision
        (A[1], 1, 0, 0.30), (D[0], 1, 0, 0.50), (C[0], 1, 0, 0.05), (A[2], 1, 0, 0.15),
        (B[1], 1, 0, 0.25), (D[1], 1, 0, 0.12), (A[0], 1, 0, 0.99),  # a repeat: first counts
        (B[2], 1, 0, 0.40), (D[2], 1, 0, 0.11), (A[3], 1, 0, 0.12),
    ]
    idx = np.array([e[0] for e in evals], np.int32)
    fields = {"collision": np.array([e[1] for e in evals], bool),
              "nonfinite": np.array([e[2] for e in evals], bool),
              "reward": np.array([e[3] for e in evals], np.float32)}
    fc = analysis.failure_clusters(idx, fields)
    # by hand: A has 4; D (best 0.50) before B (best 0.40); C alone
    want = {**{t: 1 for t in A}, **{t: 2 for t in D}, **{t: 3 for t in B}, C[0]: 4}
    got = {tuple(int(v) for v in row): int(lab) for row, lab in zip(fc.indices, fc.labels)}
    assert got == want
    assert fc.k == 4 and fc.n == 11
    assert fc.sizes.tolist() == [4, 3, 3, 1]
    # first evaluation (1-based) of any member: A at 1, D at 6, B at 2, C at 7
    assert fc.first_evaluation.tolist() == [1, 6, 2, 7]
    # representatives: the best reward of each cluster (A's 0.99 repeat does not count)
    reps = [tuple(int(v) for v in fc.indices[j]) for j in fc.representative]
    assert reps == [A[1], D[0], B[2], C[0]]
    # labels are in distinct_critical's order (rank 1 first)
    crit = analysis.distinct_critical(idx, fields)
    assert [c["indices"] for c in crit] == [tuple(int(v) for v in r) for r in fc.indices]
    assert [c["row"] for c in crit] == fc.rows.tolist()


def test_components_edge_cases_and_bad_input():
    assert analysis.chebyshev_components(np.zeros((0, 3), np.int32)).shape == (0,)
    # one parameter: a run of consecutive values, a gap of 2 splits
    assert analysis.chebyshev_components([[3], [4], [6], [5], [9]]).tolist() == [0, 0, 0, 0, 1]
    # repeated rows join; negative and huge coordinates are plain integers
    pts = [[-5, 10**12], [-4, 10**12 + 1], [-5, 10**12], [7, 0]]
    assert analysis.chebyshev_components(pts).tolist() == [0, 0, 0, 1]
    no = analysis.failure_clusters(np.zeros((5, 2), np.int32),
                                   {"collision": np.zeros(5, bool), "nonfinite": np.zeros(5, bool),
                                    "reward": np.zeros(5)})
    assert no.k == 0 and no.n == 0 and no.indices.shape == (0, 2)
    for bad in (np.zeros((3, 2)), np.zeros(4, np.int32), [[0.5, 1.0]]):
        with pytest.raises(ValueError, match="points must be a 2-D integer array") as e:
            analysis.chebyshev_components(bad)
        assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------- random sets
@pytest.mark.parametrize("seed", range(6))
def test_components_match_brute_force_on_random_sets(seed):
    rng = np.random.default_rng(seed)
    for _ in range(25):
        P = int(rng.integers(1, 7))
        n = int(rng.integers(1, 90))
        pts = rng.integers(0, int(rng.integers(2, 7)), (n, P))
        assert analysis.chebyshev_components(pts).tolist() == bfs_components(pts)


@pytest.mark.parametrize("P", [11, 13])
def test_components_with_more_parameters_than_aligned(P):
    """Beyond ALIGNED_DIMS parameters the candidates are checked pair by pair: still exact."""
    assert P > analysis.ALIGNED_DIMS
    rng = np.random.default_rng(P)
    pts = rng.integers(0, 3, (120, P))
    assert analysis.chebyshev_components(pts).tolist() == bfs_components(pts)


def test_components_with_coordinates_too_wide_for_one_key():
    """Spread-out points with a near copy each: more cells than an int64 numbers."""
    rng = np.random.default_rng(7)
    base = rng.integers(0, 10**6, (80, 10))
    pts = np.concatenate([base, base + rng.integers(-1, 2, base.shape),
                          base + rng.integers(2, 4, base.shape)])
    pts = pts[rng.permutation(len(pts))]
    assert analysis.chebyshev_components(pts).tolist() == bfs_components(pts)


@pytest.mark.parametrize("seed", range(4))
def test_failure_clusters_match_the_oracle_on_random_runs(seed):
    rng = np.random.default_rng(100 + seed)
    N, P = 400, int(rng.integers(2, 5))
    idx = rng.integers(0, 5, (N, P)).astype(np.int32)
    fields = {"collision": rng.random(N) < 0.4, "nonfinite": rng.random(N) < 0.05,
              "reward": rng.integers(0, 30, N).astype(np.float32)}  # ties in reward
    ranked, number, first = oracle_clusters(idx, fields["collision"], fields["nonfinite"],
                                            fields["reward"])
    fc = analysis.failure_clusters(idx, fields)
    assert [tuple(int(v) for v in r) for r in fc.indices] == ranked
    assert fc.labels.tolist() == number
    k = max(number)
    assert fc.sizes.tolist() == [number.count(c) for c in range(1, k + 1)]
    assert fc.first_evaluation.tolist() == [
        min(first[t] for t, c in zip(ranked, number) if c == cl) + 1 for cl in range(1, k + 1)]
    assert fc.representative.tolist() == [number.index(cl) for cl in range(1, k + 1)]


# ----------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
    out = tmp_path_factory.mktemp("clusters") / "run"
    o = runs.execute(runs.RunConfig(strategy="random", evaluations=2000, batch=200, seed=1),
                     out, figures=False)
    return out, o


def test_run_outputs_agree_with_the_oracle(run_folder):
    out, o = run_folder
    ep = pq.read_table(out / "evaluations.parquet").to_pydict()
    sp = o.result.space
    idx = np.stack([ep[f"{n}_idx"] for n in sp.names], -1)
    ranked, number, first = oracle_clusters(idx, ep["collision"], ep["nonfinite"], ep["reward"])
    k = max(number)
    assert k > 1 and len(ranked) > k  # some clusters hold several scenarios
    rows = list(csv.DictReader(open(out / "critical.csv")))
    assert [int(r["rank"]) for r in rows] == list(range(1, len(ranked) + 1))
    # each critical.csv row: its scenario (through the evaluation that first found it) and
    # its cluster as the brute-force graph numbers it
    seen = [tuple(int(v) for v in idx[int(r["first_evaluation"]) - 1]) for r in rows]
    assert seen == ranked
    assert [int(r["cluster"]) for r in rows] == number
    # each row's values, outcome and count, read off the evaluations one row at a time
    crit = [tuple(int(v) for v in idx[j]) for j in range(len(idx))
            if ep["collision"][j] and not ep["nonfinite"][j]]
    for r, key in zip(rows, seen):
        j = int(r["first_evaluation"]) - 1
        assert [r[n] for n in sp.names] == [f"{float(sp.table[p][key[p]]):g}"
                                            for p in range(len(sp.names))]
        assert r["reward"] == f"{float(np.float32(ep['reward'][j])):.6f}"
        assert r["min_distance"] == f"{float(np.float32(ep['min_distance'][j])):.4f}"
        assert int(r["times_evaluated"]) == crit.count(key)
    s = json.loads((out / "summary.json").read_text())
    assert s["n_failure_clusters"] == k and s["n_distinct_critical"] == len(ranked)
    listed = s["failure_clusters"]
    assert len(listed) == min(k, runs.CLUSTERS_LISTED)
    assert s["failure_clusters_omitted"] == k - len(listed)
    for entry in listed:
        members = [r for r in rows if int(r["cluster"]) == entry["cluster"]]
        assert entry["size"] == len(members)
        assert entry["first_evaluation"] == min(int(r["first_evaluation"]) for r in members)
        best = members[0]  # critical.csv is ranked: the cluster's best member comes first
        rep = entry["representative"]
        assert rep["critical_rank"] == int(best["rank"])
        assert rep["evaluation"] == int(best["first_evaluation"])
        assert tuple(rep["indices"]) == ranked[int(best["rank"]) - 1]
        assert rep["params"] == {n: pytest.approx(float(best[n]), rel=1e-5) for n in sp.names}
        assert rep["reward"] == pytest.approx(float(best["reward"]), abs=1e-6)
    sizes = [e["size"] for e in listed]
    assert sizes == sorted(sizes, reverse=True)
    line = runs.run_lines(s)[0]
    assert f"{len(ranked)} distinct critical scenarios in {k} failure clusters (largest " \
           f"{number.count(1)})" in line


def test_report_and_figure_show_the_clusters(run_folder, tmp_path):
    from jaxfalsify.outputs.figures import _plt, cluster_figure, load_run
    from jaxfalsify.outputs.report import write_report

    out, _ = run_folder
    s = json.loads((out / "summary.json").read_text())
    # a folder whose summary predates the cluster keys: the report derives them from
    # evaluations.parquet all the same
    old = tmp_path / "old"
    shutil.copytree(out, old)
    for key in ("n_failure_clusters", "failure_clusters", "failure_clusters_omitted"):
        s.pop(key)
    (old / "summary.json").write_text(json.dumps(s))
    text = write_report(old).read_text()
    rows = list(csv.DictReader(open(out / "critical.csv")))
    labels = [int(r["cluster"]) for r in rows]
    k = max(labels)
    assert f"| failure clusters | {k} (largest: {labels.count(1)} of the {len(rows)} " in text
    assert "## Failure clusters" in text
    first_row = next(line for line in text.splitlines() if line.startswith("| 1 | "))
    assert first_row.startswith(f"| 1 | {labels.count(1)} | ")
    plt = _plt()
    sp, _, _, ep = load_run(old)
    fig = cluster_figure(plt, sp, ep)
    bars = fig.axes[0].patches
    assert [int(b.get_height()) for b in bars] == [labels.count(c) for c in
                                                   range(1, min(k, 20) + 1)]
    drawn = sum(len(c.get_offsets()) for c in fig.axes[1].collections)
    assert drawn == len(rows) + min(k, 9)  # every distinct critical scenario, and stars
    plt.close(fig)
