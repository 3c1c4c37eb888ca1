"""Search wall time in ``compare``: each seed's search seconds to its first collision and its
distinct collisions per search second, compilation apart. Every assertion checks the reported
numbers against an independent oracle: the interpolation formula worked by hand or applied to
the measured chunk times and the records' first collision, and the per-seed numbers that
compare.json itself holds. No assertion depends on how fast the machine is."""

import json

import numpy as np
import pytest
from conftest import TINY_SPACE, run_campaign

import jaxfalsify as jf
from jaxfalsify.base.progress import Progress
from jaxfalsify.engine import campaign
from jaxfalsify.jobs import compare, compare_stats, compare_tables, suites

NO_COLLISION_SPACE = TINY_SPACE.replace("values = [7, 9]", "values = [1, 2]", 1)  # carla-tm:
# none of its 32 scenarios collides (checked against the sweep below)


def _result(chunk_seconds, batch, per_chunk, n, collision_at=(), seeds_per_call=1):
    """A hand-built campaign Result of ``n`` evaluations with the given chunk times."""
    fields = {f: np.zeros(n, np.float32) for f in campaign.RECORD_FIELDS}
    fields["collision"] = np.isin(np.arange(1, n + 1), collision_at)
    fields["violated"] = fields["collision"]  # a comparison's critical: collisions
    fields["nonfinite"] = np.zeros(n, bool)

    class _Space:
        shape = (n,)

    idx = np.arange(n, dtype=np.int32)[:, None]  # every evaluation its own scenario
    return campaign.Result(_Space(), batch, idx, fields, 0.5, float(np.nansum(chunk_seconds or 0)),
                           None if chunk_seconds is None else np.asarray(chunk_seconds, float),
                           per_chunk, seeds_per_call)


def _expected(chunk_seconds, batch, lengths, evaluation, seeds_per_call=1):
    """The documented attribution, written out: each chunk's time spread evenly over the
    updates it ran (``lengths``: updates per chunk), summed to the end of the update holding
    ``evaluation``."""
    per_update = np.concatenate([np.full(n, t / n) for t, n in zip(chunk_seconds, lengths)])
    update = (evaluation - 1) // batch
    return float(np.sum(per_update[:update + 1])) / seeds_per_call


def _lengths(first, per, n_updates):
    """Updates per chunk: ``first``, then ``per`` each, the last the rest."""
    out, left = [min(first, n_updates)], n_updates - min(first, n_updates)
    while left > 0:
        out.append(min(per, left))
        left -= out[-1]
    return out


def test_search_seconds_at_by_hand():
    """Batch 4, 3 updates per chunk, chunks of 0.3, 0.6 and 0.9 s: an update costs 0.1 s in the
    first chunk, 0.2 s in the second, 0.3 s in the third."""
    r = _result([0.3, 0.6, 0.9], batch=4, per_chunk=3, n=36)
    got = [r.search_seconds_at(e) for e in (1, 4, 5, 12, 13, 24, 25, 36)]
    np.testing.assert_allclose(got, [0.1, 0.1, 0.2, 0.3, 0.5, 0.9, 1.2, 1.8])
    # two seeds in one compiled call: an even share each
    half = _result([0.3, 0.6, 0.9], batch=4, per_chunk=3, n=36, seeds_per_call=2)
    assert half.search_seconds_at(13) == pytest.approx(0.25)
    # a first chunk of one update and a shorter last one (9 updates: 1, 3, 3, 2): 0.3 s for
    # update 0, 0.2 s for each of updates 1-3, 0.3 s each of 4-6, 0.45 s each of 7-8
    r = _result([0.3, 0.6, 0.9, 0.9], batch=4, per_chunk=3, n=36)
    r.chunk_updates = (1, 3, 3, 2)
    got = [r.search_seconds_at(e) for e in (1, 4, 5, 16, 17, 28, 29, 36)]
    np.testing.assert_allclose(got, [0.3, 0.3, 0.5, 0.9, 1.2, 1.8, 2.25, 2.7])
    # a chunk restored from a checkpoint (not timed here) leaves the time from there unknown
    restored = _result([np.nan, 0.6, 0.9], batch=4, per_chunk=3, n=36)
    assert restored.search_seconds_at(13) is None and restored.search_seconds_at(1) is None
    assert _result(None, batch=4, per_chunk=3, n=36).search_seconds_at(5) is None
    for bad in (0, 37, 2.0, True):
        with pytest.raises(ValueError, match=f"evaluation must be an integer in 1..36 "
                                             rf"\(got {bad!r}\)"):
            r.search_seconds_at(bad)


def test_seed_stats_time_figures_by_hand():
    """First collision at evaluation 10 (update 2, the first chunk's last): 0.3 s; the budget's
    search seconds 1.8 s; two distinct collisions (evaluations 10 and 30) per 1.8 s. At a
    budget of 8 (no collision yet) no time to the first collision: None, not 0; the search
    seconds are those to the end of update 1."""
    truth = {"global_max_reward": 0.0, "global_min_reward": 0.0}
    r = _result([0.3, 0.6, 0.9], batch=4, per_chunk=3, n=36, collision_at=(10, 30))
    st = compare_stats.seed_stats(0, r, truth)
    assert st["first_collision"] == 10
    assert st["first_collision_seconds"] == pytest.approx(0.3)
    assert st["search_seconds"] == pytest.approx(1.8)
    assert st["distinct"] == 2 and st["failures_per_second"] == pytest.approx(2 / 1.8)
    early = compare_stats.seed_stats(0, r, truth, budget=8)
    assert early["first_collision"] is None and early["first_collision_seconds"] is None
    assert early["search_seconds"] == pytest.approx(0.2) and early["failures_per_second"] == 0
    untimed = compare_stats.seed_stats(0, _result(None, 4, 3, 36, collision_at=(10,)), truth)
    assert untimed["first_collision"] == 10
    assert all(untimed[k] is None for k in compare_stats.SEED_TIME_KEYS)


def test_the_median_time_to_the_first_collision_counts_seeds_without_one_as_never():
    def seed(first_s, search_s=2.0):
        return {"first_collision_seconds": first_s, "search_seconds": search_s}

    med = compare_stats.first_collision_seconds_median
    assert med([seed(0.5), seed(1.5), seed(None)]) == 1.5  # [0.5, 1.5, never]
    assert med([seed(0.5), seed(None)]) is None  # half found none: the median is never
    assert med([seed(None)] * 3) is None
    assert med([seed(0.5), seed(1.0, None)]) is None  # a seed not timed: no median


def test_a_campaigns_first_failure_is_given_the_time_of_its_update(tmp_path):
    """A real campaign (batch 4, chunks of 4 updates): one measured time per chunk; the first
    collision's search seconds are the formula applied to the measured chunk times at the
    update the records hold it in, within [0, the chunks' sum]; the chunks' sum lies within
    the search loop's wall time. Two seeds in one call share each chunk's time."""
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SPACE)
    sp = jf.load_space(str(path))
    r = run_campaign(sp, "random", batch=4, evaluations=64, seed=0, every=4)
    p = campaign.plan(64, 4, every=4)
    assert (r.updates_per_chunk, r.seeds_per_call) == (4, 1)
    t = r.chunk_seconds
    lengths = _lengths(1, 4, 16)  # 1, 4, 4, 4, 3
    assert t.shape == (p.n_chunks,) == (5,) and np.all(np.isfinite(t)) and np.all(t >= 0)
    assert r.compile_seconds >= 0 and np.sum(t) <= r.search_seconds
    hits = np.nonzero(r.fields["collision"] & ~r.fields["nonfinite"])[0]
    assert hits.size, "the tiny space's 3 collisions in 32 should be met in 64 draws"
    first = int(hits[0]) + 1
    got = r.search_seconds_at(first)
    assert got == pytest.approx(_expected(t, 4, lengths, first))
    assert 0 <= got <= np.sum(t) * (1 + 1e-12)
    assert r.search_seconds_at(64) == pytest.approx(np.sum(t))  # the budget ends a chunk
    two = campaign.run_seeds(sp, *_make("random", sp), p, [0, 1])
    assert [x.seeds_per_call for x in two] == [2, 2]
    np.testing.assert_array_equal(two[0].chunk_seconds, two[1].chunk_seconds)
    assert two[1].search_seconds_at(first) == pytest.approx(
        _expected(two[1].chunk_seconds, 4, lengths, first, seeds_per_call=2))


def _make(strategy, sp, batch=4):
    from jaxfalsify import search
    from jaxfalsify.suts import registry as sut_lib

    s, sp_ = sut_lib.make("carla-tm")
    strat, params = search.make(strategy, sp.shape, batch)
    return s, sp_, strat, params


class _Bar(Progress):
    def __init__(self):
        self.total = self.done = None

    def start(self, total, done=0, unit="eval", desc=""):
        self.total = total

    def update(self, done, **stats):
        self.done = done


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    """``compare`` of random and cem (batch 200) on the tiny space, 3 seeds x 8000
    evaluations (40 updates in chunks of 2), with the 400- and 1-evaluation budgets; every
    campaign Result it ran captured."""
    tmp = tmp_path_factory.mktemp("cmp")
    space = tmp / "tiny.toml"
    space.write_text(TINY_SPACE)
    calls = []
    real = campaign.run_seeds

    def recording(*a, **kw):
        out = real(*a, **kw)
        calls.append((list(a[6]), out))  # a: space, SUT, params, strategy, params, plan, seeds
        return out

    mp = pytest.MonkeyPatch()
    mp.setattr(campaign, "run_seeds", recording)
    bar = _Bar()
    try:
        res = compare.execute(compare.CompareConfig(
            strategies=("random", "cem"), seeds=3, evaluations=8000, space=str(space),
            overhead=False, jobs=1, budgets=(1, 400)), tmp / "out", progress=bar)
    finally:
        mp.undo()
    doc = json.loads((tmp / "out" / "compare.json").read_text())
    return res, doc, calls, bar, (tmp / "out" / "compare.md").read_text()


def test_compare_times_each_seed_and_reports_its_first_collision(compared):
    res, doc, calls, bar, md = compared
    # one seed per compiled call: each seed's time is its own, not a share
    assert [seeds for seeds, _ in calls] == [[0], [1], [2]] * 2
    results = {"random": [r for _, (r,) in calls[:3]], "cem": [r for _, (r,) in calls[3:]]}
    assert bar.done == bar.total == 2 * 3 * 8000  # the bar counts every evaluation
    for b in doc["budgets"]:
        budget = b["budget"]
        for row in b["rows"]:
            for s, r in zip(row["per_seed"], results[row["strategy"]]):
                assert (r.batch, r.updates_per_chunk, r.seeds_per_call) == (200, 2, 1)
                t = r.chunk_seconds
                assert len(t) == 21 and np.all(np.isfinite(t))
                # the first collision from the records, and the formula at its update
                hits = np.nonzero(r.fields["collision"][:budget]
                                  & ~r.fields["nonfinite"][:budget])[0]
                first = int(hits[0]) + 1 if hits.size else None
                assert s["first_collision"] == first
                if first is None:
                    assert s["first_collision_seconds"] is None  # null, not 0
                else:
                    assert s["first_collision_seconds"] == pytest.approx(
                        _expected(t, 200, _lengths(1, 2, 40), first))
                    assert 0 <= s["first_collision_seconds"] <= s["search_seconds"]
                assert s["search_seconds"] == pytest.approx(
                    _expected(t, 200, _lengths(1, 2, 40), budget))
                assert s["search_seconds"] <= np.sum(t) * (1 + 1e-12)
                # failures per second from compare.json's own per-seed numbers
                assert s["failures_per_second"] == pytest.approx(
                    s["distinct"] / s["search_seconds"])
            # the medians, recomputed from the per-seed rows
            firsts = [np.inf if s["first_collision_seconds"] is None
                      else s["first_collision_seconds"] for s in row["per_seed"]]
            m = float(np.median(firsts))
            assert row["first_collision_seconds_median"] == (
                pytest.approx(m) if np.isfinite(m) else None)
            assert row["search_seconds_median"] == pytest.approx(
                np.median([s["search_seconds"] for s in row["per_seed"]]))
            assert row["failures_per_second_median"] == pytest.approx(
                np.median([s["failures_per_second"] for s in row["per_seed"]]))
            # compile seconds: every seed's compilation (and the program's tracing or
            # loading before it), none of which is in any seed's search seconds
            assert row["compile_seconds"] >= sum(r.compile_seconds
                                                 for r in results[row["strategy"]])
    # the budget of one evaluation: a seed whose first draw missed has no time (null)
    one = doc["budgets"][0]
    assert one["budget"] == 1
    assert any(s["first_collision_seconds"] is None for r in one["rows"]
               for s in r["per_seed"])
    # the markdown tables show the JSON's medians, as formatted there
    for row in doc["rows"]:
        line = next(x for x in md.splitlines() if x.startswith(f"| {row['strategy']} | 3/3 |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[3] == compare_tables._seconds(row["first_collision_seconds_median"])
        assert cells[4] == compare_tables._seconds(row["failures_per_second_median"])
        assert cells[-2] == f"{row['compile_seconds']:.1f}"
    assert compare_tables.TIME_NOTE in md


def test_the_suite_tables_show_the_times(compared):
    """The per-budget table (compare.md and suite.md): each budget's cell ends with that
    budget's median search seconds to the first collision; the failures per second and the
    compile seconds at the largest budget."""
    res = compared[0]
    text = suites.suite_markdown({"suite": "t", "seeds": 3, "entries": [res]})
    assert compare_tables.TIME_NOTE in text
    for k, name in enumerate(["random", "cem"]):
        line = next(x for x in text.splitlines() if x.startswith(f"| {name} |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        for j, b in enumerate(res["budgets"]):
            row = b["rows"][k]
            assert cells[1 + j].endswith(
                " / " + compare_tables._seconds(row["first_collision_seconds_median"]))
        top = res["budgets"][-1]["rows"][k]
        assert cells[len(res["budgets"]) + 2] == compare_tables._seconds(
            top["failures_per_second_median"])
        assert cells[-1] == f"{top['compile_seconds']:.1f}"


def test_a_strategy_that_finds_nothing_reports_no_time(tmp_path):
    """A space without a collision: every seed's time to the first collision is null (not 0),
    so is the median, and the table says "-"; the seeds were timed all the same (search
    seconds a number, zero failures per second)."""
    from jaxfalsify.engine.truth import sweep_arrays

    space = tmp_path / "safe.toml"
    space.write_text(NO_COLLISION_SPACE)
    assert not sweep_arrays(jf.load_space(str(space)), "carla-tm",
                            fields=("collision",))["collision"].any()
    res = compare.execute(compare.CompareConfig(
        strategies=("random",), seeds=2, evaluations=400, space=str(space), overhead=False,
        jobs=1), tmp_path / "out")
    doc = json.loads((tmp_path / "out" / "compare.json").read_text())
    row = doc["rows"][0]
    assert row["first_collision_seconds_median"] is None
    for s in row["per_seed"]:
        assert s["first_collision"] is None and s["first_collision_seconds"] is None
        assert isinstance(s["search_seconds"], float) and s["failures_per_second"] == 0.0
    assert row["failures_per_second_median"] == 0.0
    line = next(x for x in compare_tables.table_markdown(res).splitlines()
                if x.startswith("| random |"))
    assert line.split("|")[4].strip() == "-"
