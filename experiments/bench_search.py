"""Search strategies side by side at the same batch: wall time and evaluations to the first
collision, distinct collisions found, in one process.

    python experiments/bench_search.py [--spaces aeb-9e6 ...] [--seeds 10] [--batch 4096]
                                       [--strategies reinforce/default random cmaes cem]
                                       [--evaluations 2048000] [--json out.json]

Each strategy x seed is one campaign (``jaxfalsify.campaign.run``, compiled once per strategy
and reused for every seed), timed per chunk of updates on the host; the search time to the first
collision is the chunks' measured seconds up to the end of the update that held it
(``Result.search_seconds_at``), compilation excluded and reported apart. A seed that finds no
collision within the budget counts as the budget's full search time (a lower bound: the median
is then reported with ``>``). Ratios are against ``random`` at the same batch, same process.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from jaxfalsify import analysis, campaign, runs

SUITE = Path(__file__).parent / "suite"
SPACES_DIR = Path(__file__).parent / "spaces"
SPACES = {
    # name: (space file, SUT, SUT parameters)
    "aeb-9e6": (SUITE / "aeb-9e6.toml", "sensor-aeb", {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "aeb-6e5": (SUITE / "aeb-6e5.toml", "sensor-aeb", {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "huge-aeb": (SUITE / "huge-aeb.toml", "sensor-aeb", {}),
    "paper": ("paper", "carla-tm", {}),
    "rare-aeb-near": (SPACES_DIR / "rare-aeb-near.toml", "sensor-aeb",
                      {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "rare-aeb-far": (SPACES_DIR / "rare-aeb-far.toml", "sensor-aeb",
                     {"ttc_full": 2.0, "ttc_partial": 3.0}),
}


def estimate_share(space_name, draws, per_seed=1 << 20):
    """Collision share from ``draws`` uniform draws (``random`` campaigns of ``per_seed``
    evaluations, one seed after another so memory stays flat): ``(collisions, draws)``."""
    space, sut, sut_params = SPACES[space_name]
    b = runs.RunConfig(space=str(space), sut=sut, sut_params=sut_params, strategy="random",
                       evaluations=per_seed, batch=1 << 16).build()
    hits = n = 0
    for seed in range(-(-draws // per_seed)):
        res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                           10_000 + seed)
        hits += int(analysis.collided(res.fields).sum())
        n += res.n
    return hits, n


def one(space_name, strategy, seeds, batch, evaluations, every):
    space, sut, sut_params = SPACES[space_name]
    rc = runs.RunConfig(space=str(space), sut=sut, sut_params=sut_params, strategy=strategy,
                        evaluations=evaluations, batch=batch, checkpoint_every=every)
    b = rc.build()
    rows = []
    for seed in seeds:
        res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                           seed)
        first = analysis.first_collision(res.fields)
        t_first = res.search_seconds_at(first) if first else None
        hit = analysis.collided(res.fields)
        distinct = len(np.unique(res.indices[hit], axis=0)) if hit.any() else 0
        rows.append({"seed": seed, "first_collision": first, "seconds_to_first": t_first,
                     "search_seconds": res.search_seconds, "compile_seconds":
                     res.compile_seconds, "collisions": int(hit.sum()),
                     "distinct_collisions": distinct})
    return rows


def poisson_interval(k: int) -> tuple[float, float]:
    """Exact 95 % interval of a Poisson mean given ``k`` events (Garwood), by bisection on
    the Poisson CDF (no SciPy)."""
    def cdf(x, lam):
        term = total = np.exp(-lam)
        for i in range(1, x + 1):
            term *= lam / i
            total += term
        return total

    def solve(f, lo, hi):
        for _ in range(200):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if f(mid) else (lo, mid)
        return (lo + hi) / 2

    lower = 0.0 if k == 0 else solve(lambda lam: 1 - cdf(k - 1, lam) < 0.025, 0.0, 10.0 * k + 10)
    upper = solve(lambda lam: cdf(k, lam) > 0.025, 0.0, 10.0 * k + 10)
    return lower, upper


def median_time(rows):
    t = [r["seconds_to_first"] if r["seconds_to_first"] is not None else r["search_seconds"]
         for r in rows]
    censored = sum(r["seconds_to_first"] is None for r in rows)
    return float(np.median(t)), censored


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spaces", nargs="+", default=["aeb-9e6", "huge-aeb"])
    ap.add_argument("--strategies", nargs="+",
                    default=["random", "reinforce/default", "cmaes", "cem"])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--batch", type=int, default=4096)
    ap.add_argument("--evaluations", type=int, default=4096 * 200)
    ap.add_argument("--every", type=int, default=5, help="updates per timed chunk")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--estimate", type=int, default=0,
                    help="first estimate each space's collision share from this many uniform "
                    "draws")
    a = ap.parse_args(argv)
    out = {}
    for sp in a.spaces if a.estimate else ():
        hits, n = estimate_share(sp, a.estimate)
        lo, hi = poisson_interval(hits)
        print(f"{sp}: {hits} collisions in {n} uniform draws: share {hits / n:.2e} "
              f"(95 % interval {lo / n:.1e}-{hi / n:.1e})", flush=True)
        out.setdefault("shares", {})[sp] = {"collisions": hits, "draws": n}
    for sp in a.spaces:
        print(f"\n== {sp}: batch {a.batch}, budget {a.evaluations}, {a.seeds} seeds")
        print(f"{'strategy':20s} {'found':>6s} {'median first (eval)':>20s} "
              f"{'median s to first':>18s} {'x random':>9s} {'distinct':>9s} "
              f"{'s/update':>9s} {'compile s':>9s}")
        base = None
        for st in a.strategies:
            t0 = time.perf_counter()
            rows = one(sp, st, list(range(a.seeds)), a.batch, a.evaluations, a.every)
            med, cens = median_time(rows)
            firsts = [r["first_collision"] or a.evaluations for r in rows]
            if st == "random":
                base = med
            n_up = -(-a.evaluations // a.batch)
            per_up = np.median([r["search_seconds"] for r in rows]) / n_up
            ratio = f"{med / base:.3f}" if base else "-"
            print(f"{st:20s} {len(rows) - cens:>3d}/{len(rows):<2d} "
                  f"{np.median(firsts):>20.0f} {('>' if cens * 2 >= len(rows) else '') + f'{med:.3f}':>18s} "
                  f"{ratio:>9s} {np.median([r['distinct_collisions'] for r in rows]):>9.0f} "
                  f"{per_up * 1e3:>7.1f}ms {rows[0]['compile_seconds']:>9.1f}", flush=True)
            out.setdefault(sp, {})[st] = {"rows": rows, "median_seconds_to_first": med,
                                          "censored": cens,
                                          "wall_seconds": time.perf_counter() - t0}
    if a.json:
        a.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(a).items()},
                                      "results": out}, indent=1))


if __name__ == "__main__":
    main()
