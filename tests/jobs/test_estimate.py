"""Failure-rate estimates: the importance weights against a NumPy computation of the
proposal's probabilities, the draws' distribution against the proposal, interval coverage
against the exact rate of an exhaustively evaluated space (fixed seeds), and the command."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.core import requirements as req_lib
from jaxfalsify.io import store
from jaxfalsify.jobs import estimate as est
from jaxfalsify.suts import registry as sut_lib


@pytest.fixture(scope="module")
def paper():
    return jf.load_space("paper")


@pytest.fixture(scope="module")
def exact(paper):
    """Every scenario of the paper space evaluated one by one through ``jf.evaluate``."""
    idx = np.stack(np.unravel_index(np.arange(paper.size), paper.shape), -1)
    out = jf.evaluate(paper.scenario(idx))
    return float(np.mean(np.asarray(out.collision) & ~np.asarray(out.nonfinite)))


def _random_proposal(sp, k, rng):
    shape = np.asarray(sp.shape)
    width = int(shape.max())
    probs = rng.dirichlet(np.full(width, 0.3), size=(k, len(shape)))
    probs = np.where(np.arange(width)[None, None] < shape[None, :, None], probs, 0.0)
    probs /= probs.sum(-1, keepdims=True)
    with np.errstate(divide="ignore"):
        return est.Proposal(np.log(rng.dirichlet(np.ones(k))).astype(np.float32),
                            np.log(probs).astype(np.float32)), probs


def test_exact_rate_is_the_share_of_evaluated_collisions(paper, exact):
    got = est.exact_rate(paper, requirement="collision")
    assert got["scenarios"] == paper.size and got["rate"] == pytest.approx(exact, abs=1e-12)


@pytest.fixture(scope="module")
def draw_program(paper):
    return est._compile(paper, sut_lib.resolve("carla-tm"), req_lib.resolve("clash"), 20000)


@pytest.mark.parametrize("zero, share", [(None, 0.2), (0, 0.2), (1, 0.2), (2, 0.2),
                                         (None, 1.0)])
def test_weights_and_draws_follow_the_defensive_mixture(paper, draw_program, zero, share):
    """A mixture of three components (``zero``: that one's weight 0) with a uniform share:
    the log-weights against a NumPy computation of p/q, the draws' values and pairs of values
    against the mixture's probabilities (``share`` 1: uniform draws, weight 1)."""
    rng = np.random.default_rng(5)
    q, probs = _random_proposal(paper, 3, rng)
    if zero is not None:
        lw = q.log_weight.astype(np.float64)
        lw[zero] = -np.inf
        lw -= np.log(np.exp(lw).sum())
        q = est.Proposal(lw.astype(np.float32), q.log_prob)
    weights = np.exp(q.log_weight.astype(np.float64))
    sut = sut_lib.resolve("carla-tm")
    req = req_lib.resolve("clash")
    run = draw_program
    idx, rob, logw = (np.asarray(a) for a in run(
        jf.core.sim.seed_key(3), q.log_weight, q.log_prob, np.float32(math.log(share)),
        sut.default_params, req.default_params))
    # NumPy: p = 1/size; q(x) = sum_k w_k prod_j probs[k, j, x_j]
    n = len(idx)
    qx = np.zeros(n)
    for k in range(len(weights)):
        qx += weights[k] * np.prod([probs[k, j, idx[:, j]] for j in range(idx.shape[1])], 0)
    p = 1.0 / paper.size
    want = np.log(p) - np.log(share * p + (1 - share) * qx)
    np.testing.assert_allclose(logw, want, rtol=0, atol=2e-4)
    # the draws: the first parameter's values against the mixture's marginal (4 sigma)
    marginal = share / paper.shape[0] + (1 - share) * (weights[:, None] * probs[:, 0,
                                                       :paper.shape[0]]).sum(0)
    counts = np.bincount(idx[:, 0], minlength=paper.shape[0])
    sigma = np.sqrt(n * marginal * (1 - marginal))
    assert np.all(np.abs(counts - n * marginal) <= 4 * sigma + 1)
    # two parameters jointly (one component per draw for all its values): the pair's counts
    # against the mixture's pair probabilities, by a chi-square test at the 1e-4 level
    m0, m1 = paper.shape[0], paper.shape[1]
    pair = share / (m0 * m1) + (1 - share) * np.einsum(
        "k,ka,kb->ab", weights, probs[:, 0, :m0], probs[:, 1, :m1])
    seen = np.bincount(idx[:, 0] * m1 + idx[:, 1], minlength=m0 * m1).reshape(m0, m1)
    expected = n * pair
    keep = expected >= 5  # the chi-square approximation's rule; the rest pooled into one cell
    cells = np.append(seen[keep], seen[~keep].sum())
    want = np.append(expected[keep], expected[~keep].sum())
    from scipy.stats import chi2

    stat = float(np.sum((cells - want) ** 2 / np.maximum(want, 1e-12)))
    assert stat < chi2.ppf(1 - 1e-4, len(cells) - 1)
    if zero is not None or share == 1.0:
        return
    # the requirement's robustness of those draws, through the public evaluate
    out = jf.evaluate(paper.scenario(idx[:2000]))
    np.testing.assert_allclose(rob[:2000], np.asarray(out.min_distance) - 1.0, atol=1e-5)


def _em_one_by_one(idx, w, shape, k, start, iterations, floor):
    """The cross-entropy stage's weighted EM written scenario by scenario and value by value in
    plain Python: the reference for :func:`est.fit_mixture`. ``start``: each draw's component
    (a hard start) or a mixture ``(weights [k], probs [k][j][value])`` whose posterior over
    the components starts the EM (a warm start)."""
    n, n_par = len(idx), len(idx[0])

    def posterior(i, weight, prob):  # draw i's responsibilities under a mixture
        like = [weight[c] * math.prod(prob[c][j][idx[i][j]] for j in range(n_par))
                for c in range(k)]
        return [x / sum(like) for x in like]

    if isinstance(start, tuple):
        resp = [posterior(i, *start) for i in range(n)]
    else:
        resp = [[1.0 if start[i] == c else 0.0 for c in range(k)] for i in range(n)]
    total = sum(w)
    w = [x / total for x in w]
    for _ in range(iterations):
        mass = [sum(resp[i][c] * w[i] for i in range(n)) + 1e-300 for c in range(k)]
        weight = [m / sum(mass) for m in mass]
        prob = [[[0.0] * int(shape[j]) for j in range(n_par)] for _ in range(k)]
        for c in range(k):
            for i in range(n):
                for j in range(n_par):
                    prob[c][j][idx[i][j]] += resp[i][c] * w[i] / mass[c]
            for j in range(n_par):
                prob[c][j] = [(1 - floor) * v + floor / shape[j] for v in prob[c][j]]
        resp = [posterior(i, weight, prob) for i in range(n)]
    return weight, prob


def _assert_fit_is(q, weight, prob, shape):
    """``q`` (a fitted proposal) holds the reference EM's weights and probabilities."""
    np.testing.assert_allclose(np.exp(q.log_weight), weight, rtol=1e-5)
    for c in range(len(weight)):
        for j, m in enumerate(shape):
            np.testing.assert_allclose(np.exp(q.log_prob[c, j, :m]), prob[c][j], rtol=1e-5)
            assert np.all(np.isneginf(q.log_prob[c, j, m:]))


def _mixture_of(q, components, shape):
    """Components of a proposal as the reference EM's ``(weights, probs)``, float64."""
    return ([float(np.exp(np.float64(q.log_weight[c]))) for c in components],
            [[np.exp(q.log_prob[c, j, :m].astype(np.float64)).tolist()
              for j, m in enumerate(shape)] for c in components])


def test_the_mixture_fit_matches_em_computed_one_scenario_at_a_time():
    rng = np.random.default_rng(5)
    shape = np.array([4, 7, 3])
    idx = np.stack([rng.integers(0, m, 60) for m in shape], 1)
    w = rng.random(60) + 0.1
    k, iterations, floor = 3, 6, 1e-2
    start = np.random.default_rng(9).integers(0, k, 60)  # fit_mixture's random hard start
    q = est.fit_mixture(idx, w, shape, k, np.random.default_rng(9), iterations, floor)
    weight, prob = _em_one_by_one(idx.tolist(), w.tolist(), shape, k, start.tolist(),
                                  iterations, floor)
    _assert_fit_is(q, weight, prob, shape)


def test_a_warm_started_fit_matches_em_started_from_the_previous_mixture():
    rng = np.random.default_rng(6)
    shape = np.array([5, 3, 6])
    idx = np.stack([rng.integers(0, m, 50) for m in shape], 1)
    w = rng.random(50) + 0.1
    k, iterations, floor = 3, 4, 1e-2
    weights = rng.dirichlet(np.ones(k))
    probs = [[list(rng.dirichlet(np.ones(m))) for m in shape] for _ in range(k)]
    table = np.full((k, len(shape), int(shape.max())), -np.inf)
    for c in range(k):
        for j, m in enumerate(shape):
            table[c, j, :m] = np.log(probs[c][j])
    start = est.Proposal(np.log(weights).astype(np.float32), table.astype(np.float32))
    q = est.fit_mixture(idx, w, shape, k, np.random.default_rng(0), iterations, floor,
                        start=start)
    # the reference starts from the float32 tables the proposal holds
    weight, prob = _em_one_by_one(idx.tolist(), w.tolist(), shape, k,
                                  _mixture_of(start, range(k), shape), iterations, floor)
    _assert_fit_is(q, weight, prob, shape)
    # fewer components than the start: the EM starts from its two heaviest, reweighted
    q2 = est.fit_mixture(idx, w, shape, 2, np.random.default_rng(0), iterations, floor,
                         start=start)
    heavy = sorted(np.argsort(-weights)[:2])
    weight2, prob2 = _em_one_by_one(idx.tolist(), w.tolist(), shape, 2,
                                    _mixture_of(start, heavy, shape), iterations, floor)
    _assert_fit_is(q2, weight2, prob2, shape)
    # more components than the start: the random hard start, as without one
    cold = est.fit_mixture(idx, w, shape, 4, np.random.default_rng(0), iterations, floor)
    other = est.fit_mixture(idx, w, shape, 4, np.random.default_rng(0), iterations, floor,
                            start=start)
    np.testing.assert_array_equal(cold.log_prob, other.log_prob)


def test_violations_the_proposal_misses_are_counted_and_reported():
    t = est.Tally("is", 0.95)
    violated = np.array([True, True, False, True, True])
    weight = np.array([1.0, 0.01, 50.0, 9.5, 0.02])  # p/q; 1: a uniform draw
    t.add(violated, np.log(weight).astype(np.float32))
    assert t.above_uniform == 1  # the violation of weight 9.5 only
    total = 1.0 + 0.01 + 9.5 + 0.02
    np.testing.assert_allclose(t.s1, total, rtol=1e-6)
    np.testing.assert_allclose(t.w_max / t.s1, 9.5 / total, rtol=1e-6)
    s = {"interval": [1e-6, 2e-6], "method": "is", "requirement": "collision",
         "estimate": 1.5e-6, "confidence": 0.95, "relative_half_width": 0.3,
         "estimator": "importance-sampling", "samples": 5, "violations": 4,
         "proposal_samples": 0, "seconds": 1.0, "reached_target": True,
         "violations_above_uniform": 1, "largest_weight_share": 9.5 / total}
    line = est.summary_lines(s)[-1]
    assert line.startswith("1 violating draw came from where the proposal has less mass")
    assert f"{9.5 / total:.0%} of the estimate" in line
    assert not any("proposal misses" in x for x in
                   est.summary_lines({**s, "violations_above_uniform": 0}))


@pytest.mark.parametrize("size, draws, says", [(60_000, 393_216, True), (1e6, 1e6, True),
                                               (1e5, 65_536, False), (6e15, 3e6, False)])
def test_the_closing_lines_point_to_a_sweep_where_it_evaluates_fewer(size, draws, says):
    s = {"interval": [1e-4, 2e-4], "method": "is", "requirement": "collision",
         "estimate": 1.5e-4, "confidence": 0.95, "relative_half_width": 0.1,
         "estimator": "importance-sampling", "samples": int(draws), "violations": 40,
         "proposal_samples": 0, "seconds": 1.0, "reached_target": True, "space_size": size}
    lines = [x for x in est.summary_lines(s) if "--method exact" in x]
    assert len(lines) == int(says)
    if says:
        assert lines[0].startswith(f"the space has {int(size):,} scenarios, no more than "
                                   f"these {int(draws):,} draws")


@pytest.mark.parametrize("method, draws", [("mc", 1500), ("is", 600)])
def test_intervals_cover_the_exact_rate(paper, exact, method, draws):
    """40 seeds of each estimator at a 95 % level: the interval holds the exact rate in at
    least 34 (the chance of 33 or fewer with a true coverage of 95 % is below 0.2 %)."""
    covered = []
    for seed in range(40):
        s = est.estimate(est.EstimateConfig(
            requirement="collision", method=method, samples=draws, batch=draws,
            target_rel_error=1e-9, seed=seed, ce_samples=2000, ce_levels=3))
        lo, hi = s["interval"]
        covered.append(lo <= exact <= hi)
        assert s["samples"] == s["proposal_samples"] + draws
    assert sum(covered) >= 34, sum(covered)


def test_the_estimate_leaves_out_the_first_stages_it_is_told_to():
    """Three stages of weighted draws; with the first left out the estimate, its interval and
    the diagnostics are those of the other two's draws alone (a NumPy computation over them),
    while ``n`` still counts every draw."""
    rng = np.random.default_rng(3)
    stages = [(rng.random(n) < p, rng.normal(0, 2, n)) for n, p in
              ((500, 0.02), (400, 0.1), (300, 0.2))]
    stages[0][0][0], stages[0][1][0] = True, 12.0  # the heaviest violation, left out
    t = est.Tally("is", 0.9)
    for i, (v, lw) in enumerate(stages):
        t.add(v, lw, 1.0 if i == 0 else 0.1, new_stage=True)
    t.leave_out(1)
    v = np.concatenate([x[0] for x in stages[1:]])
    w = np.exp(np.concatenate([x[1] for x in stages[1:]])) * v
    n = len(w)
    mean = w.mean()
    half = 1.6448536269514722 * w.std(ddof=1) / math.sqrt(n)
    assert t.n == 1200 and t.counted == n and t.bad == int(v.sum())
    np.testing.assert_allclose([t.estimate, t.low, t.high], [mean, mean - half, mean + half],
                               rtol=1e-9)
    np.testing.assert_allclose(t.uniform_draws, 0.1 * n)
    np.testing.assert_allclose(t.w_max, w.max())
    assert t.above_uniform == int(np.sum(v & (np.concatenate([x[1] for x in stages[1:]])
                                              > 1e-6)))


@pytest.mark.parametrize("method", ["mc", "is"])
def test_no_violation_gives_an_interval_above_zero(method):
    """A requirement never violated (time-to-collision >= 0 s): the estimate is 0 and the
    interval's upper end is at least Clopper-Pearson's, and within 0.1 % of it, for no success
    in the draws' uniform mass (each draw counts its proposal's uniform share: 1 for the
    uniform first level, ``defensive`` for the others; scipy's beta quantile), not 0; Monte
    Carlo's Wilson upper end is of the same order (oracle: Clopper-Pearson's for all its
    draws, which Wilson's exceeds)."""
    from scipy.stats import beta

    s = est.estimate(est.EstimateConfig(
        requirement="ttc", requirement_params={"min_ttc": 0.0}, method=method, samples=1000,
        batch=1000, ce_samples=2000, ce_levels=3, seed=0))
    assert s["violations"] == 0 and s["estimate"] == 0.0 and s["interval"][0] == 0.0
    if method == "is":
        assert s["proposal_samples"] == 3 * 2000
        mass = 2000 + 0.1 * (2 * 2000 + 1000)  # the uniform level, then defensive mixtures
        cp = float(beta.ppf(0.975, 1, mass))
        assert cp <= s["interval"][1] <= 1.001 * cp
    else:
        cp = float(beta.ppf(0.975, 1, s["samples"]))
        assert cp <= s["interval"][1] <= 1.1 * cp
    assert "[0, 0]" not in " ".join(est.summary_lines(s))


def test_the_first_quarter_of_the_levels_is_left_out_of_the_estimate():
    """Eight cross-entropy levels of a requirement never violated (all eight run): the
    estimate leaves out the first two levels' draws (a quarter), so the interval's upper end
    is Clopper-Pearson's for the uniform mass of the other six levels' and the final draws
    alone (the exponential bound exceeds it by a factor of at most ``1 + ln(40) / mass``);
    ``ce_burn_in=0`` counts every level's."""
    from scipy.stats import beta

    for burn_in, left in ((0.25, 2), (0.0, 0)):
        s = est.estimate(est.EstimateConfig(
            requirement="ttc", requirement_params={"min_ttc": 0.0}, method="is", samples=1000,
            batch=1000, ce_samples=2000, ce_levels=8, ce_burn_in=burn_in, seed=0))
        assert s["proposal_levels"] == 8 and s["left_out_levels"] == left
        assert s["samples"] == 8 * 2000 + 1000
        assert s["counted_samples"] == (8 - left) * 2000 + 1000
        # the uniform first level counts 1 per draw, the others' defensive mixtures 0.1
        mass = 2000 + 0.1 * (7 * 2000 + 1000) if left == 0 else 0.1 * ((8 - left) * 2000
                                                                        + 1000)
        cp = float(beta.ppf(0.975, 1, mass))  # Clopper-Pearson's upper end
        assert cp <= s["interval"][1] <= (1 + math.log(40) / mass) * cp
    line = est.summary_lines({**s, "left_out_levels": 2, "violations": 0,
                              "counted_samples": 13000})[1]
    assert "the estimate counts 13,000 of them (0 violating), leaving out those of the " \
        "first 2 levels" in line


def test_importance_sampling_narrows_the_interval_at_equal_draws(paper, exact):
    """At the same number of final draws the importance-sampling interval is narrower than
    Monte Carlo's on the paper space's collisions (3.7 %; 2x narrower measured)."""
    width = {}
    for method in ("mc", "is"):
        s = est.estimate(est.EstimateConfig(requirement="collision", method=method,
                                            samples=4000, batch=4000, target_rel_error=1e-9,
                                            seed=1, ce_samples=65536))
        width[method] = s["interval"][1] - s["interval"][0]
        assert s["interval"][0] <= exact <= s["interval"][1]
    assert width["is"] < width["mc"] / 1.5


def test_the_command_writes_config_and_summary(tmp_path, capsys):
    out = tmp_path / "est"
    assert main(["estimate", "--requirement", "ttc", "--requirement-param", "min_ttc=1",
                 "--method", "mc", "--samples", "4096", "--batch", "4096", "--out", str(out),
                 "--quiet"]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["requirement"] == "ttc" and s["requirement_params"] == {"min_ttc": 1.0}
    assert s["samples"] == 4096 and s["interval"][0] <= s["estimate"] <= s["interval"][1]
    assert json.loads((out / "status.json").read_text())["state"] == "complete"
    assert 'kind = "estimate"' in (out / "config.toml").read_text()
    said = capsys.readouterr().out
    assert f"ttc violated with probability {s['estimate']:.4g}" in said
    assert main(["estimate", "--out", str(out), "--quiet"]) == 2  # finished: not overwritten
    assert "already holds summary.json" in capsys.readouterr().err


@pytest.mark.parametrize("argv, says", [
    (["--requirement", "nope"], "unknown requirement 'nope'"),
    (["--requirement-param", "eps=1"], "has no parameter 'eps'"),
    (["--requirement", "collision", "--requirement-param", "epsilon=1"], "has no parameter"),
    (["--confidence", "1.5"], "--confidence 1.5: must be in (0, 1)"),
    (["--method", "bogus"], "invalid choice: 'bogus'"),
])
def test_bad_estimate_input_is_one_line_and_writes_nothing(tmp_path, capsys, argv, says):
    out = tmp_path / "never"
    assert main(["estimate", *argv, "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and says in err[0], err
    assert not out.exists()


def test_the_exact_method_counts_every_scenario(tmp_path, paper, exact, capsys):
    assert main(["estimate", "--method", "exact", "--requirement", "collision", "--out",
                 str(tmp_path / "x"), "--quiet"]) == 0
    s = json.loads((tmp_path / "x" / "summary.json").read_text())
    assert s["samples"] == paper.size and s["estimate"] == pytest.approx(exact, abs=1e-12)
    assert s["violations"] == round(exact * paper.size)
    said = f"violated by {round(exact * paper.size):,} of the {paper.size:,} scenarios"
    assert said in capsys.readouterr().out
    huge = str(Path(__file__).parents[2] / "experiments" / "spaces" / "strong-aeb.toml")
    assert main(["estimate", "--method", "exact", "--space", huge, "--out",
                 str(tmp_path / "y"), "--quiet"]) == 2
    assert "than can be evaluated one by one" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()


@pytest.mark.parametrize("method", ["mc", "is"])
def test_a_stop_request_ends_the_draws_and_the_folder_says_interrupted(tmp_path, method):
    """A stop request (Ctrl-C, SIGTERM) seen at the third check (Monte Carlo: after two
    batches of 1000) or the second (importance sampling: after the first cross-entropy
    level of 2000 draws, before any more): summary.json holds the estimate of those draws
    with ``"interrupted": true``, status.json says interrupted, the closing lines say so
    instead of asking for more draws. Oracles: the draws counted by the checks; Monte
    Carlo's estimate is the violating share of its draws and its interval Wilson's, computed
    here from the score formula."""
    seen = {"checks": 0}

    def stop():
        seen["checks"] += 1
        return seen["checks"] >= (3 if method == "mc" else 2)

    c = est.EstimateConfig(requirement="collision", method=method, samples=100_000,
                           batch=1000, target_rel_error=1e-9, seed=0, ce_samples=2000)
    s = est.execute(c, tmp_path / "e", stop=stop)
    assert s["interrupted"] is True and s["reached_target"] is False
    assert s["samples"] == 2000 and s["proposal_samples"] == (0 if method == "mc" else 2000)
    if method == "mc":
        k, n, z = s["violations"], s["samples"], 1.959963984540054
        p = k / n
        mid, half = (p + z * z / (2 * n)), z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
        assert s["estimate"] == k / n
        np.testing.assert_allclose(s["interval"], [(mid - half) / (1 + z * z / n),
                                                   (mid + half) / (1 + z * z / n)], rtol=1e-9)
    status = json.loads((tmp_path / "e" / "status.json").read_text())
    assert status["state"] == "interrupted" and status["samples_done"] == 2000
    assert json.loads((tmp_path / "e" / "summary.json").read_text())["interrupted"] is True
    lines = est.summary_lines(s)
    assert "interrupted after 2,000 draws" in lines[-1] and "raise --samples" not in " ".join(
        lines)
    # an estimate cannot be resumed: no --resume is offered; the folder is started over with
    # --force, and until then kept
    assert "resume" not in status
    with pytest.raises(store.FolderError, match="holds an estimate that did not complete "
                                                r"\(see its status.json\); pass --force"):
        est.execute(c, tmp_path / "e")
    kept = json.loads((tmp_path / "e" / "summary.json").read_text())
    assert kept["samples"] == 2000 and kept["estimate"] == s["estimate"]


def test_ctrl_c_ends_an_estimate_with_exit_130_and_says_so(tmp_path):
    """The command, interrupted by SIGINT while drawing: exit 130, the interruption said in
    the closing lines, never that the results are complete."""
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "e"
    proc = subprocess.Popen([sys.executable, "-m", "jaxfalsify.cli", "estimate", "--method",
                             "mc", "--samples", "1000000000", "--batch", "4096",
                             "--target-rel-error", "1e-9", "--out", str(out), "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        try:
            if json.loads((out / "status.json").read_text())["state"] == "running":
                break
        except (FileNotFoundError, json.JSONDecodeError):
            pass
        time.sleep(0.05)
    time.sleep(1.0)  # some batches drawn
    proc.send_signal(signal.SIGINT)
    said, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "results are complete" not in err
    s = json.loads((out / "summary.json").read_text())
    assert s["interrupted"] is True and 0 < s["samples"] < 1_000_000_000
    assert f"interrupted after {s['samples']:,} draws" in said
    assert json.loads((out / "status.json").read_text())["state"] == "interrupted"


@pytest.mark.parametrize("key, value", [("ce_samples", 0), ("ce_levels", 0),
                                        ("ce_components", 0), ("ce_iterations", 0),
                                        ("ce_burn_in", 1.0), ("ce_burn_in", -0.1)])
def test_a_cross_entropy_setting_out_of_range_is_refused_by_name(key, value):
    with pytest.raises(ValueError, match=key):
        est.EstimateConfig(**{key: value}).check()
