"""Search strategies on one space and SUT over many seeds, with compare's statistics.

    python experiments/search_dev.py --space experiments/spaces/rare-2e4.toml --sut sensor-aeb \\
        --sut-param ttc_full=2.0 --sut-param ttc_partial=3.0 \\
        --strategies reinforce/default,random,cmaes --seeds 10 --evaluations 4000 \\
        [--opt reinforce/default:lr=0.1] [--json out.json]

Prints one row per strategy: seeds with a collision, evaluations to the first collision
(median [IQR] over all seeds, a seed without one counting budget + 1), seeds at the global
maximum, distinct collisions, share of evaluations on box corners, mean reward of the last
quarter, wall seconds; and uniform random's analytic expectation.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

import jaxfalsify as jf
from jaxfalsify import campaign, compare, search
from jaxfalsify import sut as sut_lib


def _value(v: str):
    try:
        return float(v)
    except ValueError:
        return v


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--space", default="paper")
    ap.add_argument("--sut", default="sensor-aeb")
    ap.add_argument("--sut-param", action="append", default=[])
    ap.add_argument("--strategies", default="reinforce/default,random,cmaes")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--evaluations", type=int, default=4000)
    ap.add_argument("--batch", action="append", default=[], help="STRATEGY:N")
    ap.add_argument("--opt", action="append", default=[], help="STRATEGY:NAME=VALUE")
    ap.add_argument("--overhead", action="store_true")
    ap.add_argument("--json")
    a = ap.parse_args(argv)

    sp = jf.load_space(a.space)
    sut_params = {k: float(v) for k, v in (s.split("=") for s in a.sut_param)}
    s, sp_params = sut_lib.make(a.sut, **sut_params)

    import types

    truth = compare.truth_summary(sp, types.SimpleNamespace(sut=a.sut, sut_params=sut_params),
                                  a.evaluations)
    u = truth["uniform_first_collision"]
    print(f"{sp.name} ({sp.size:,} scenarios) x {a.sut} {sut_params}: {truth['n_collisions']} "
          f"collisions (share {u['p']:.2e}), global max {truth['global_max_reward']:.4f} "
          f"({truth['global_max_ties']} ties); uniform: 1/p = {u['expected']:.4g}, median "
          f"{u['median']:.4g}, censored expectation {u['expected_censored']:.4g}, P(found in "
          f"budget) = {u['found_probability']:.3f}; corner share {truth['uniform_corner_share']:.2e}")
    opts: dict[str, dict] = {}
    for o in a.opt:
        name, kv = o.split(":", 1)
        k, v = kv.split("=")
        opts.setdefault(name, {})[k] = _value(v)
    batches = {b.split(":")[0]: int(b.split(":")[1]) for b in a.batch}
    rows = []
    for name in a.strategies.split(","):
        strat, params = search.make(name, sp.shape, batches.get(name), **opts.get(name, {}))
        plan = campaign.plan(a.evaluations, strat.batch)
        t0 = time.perf_counter()
        res = campaign.run_seeds(sp, s, sp_params, strat, params, plan, list(range(a.seeds)))
        wall = time.perf_counter() - t0
        stats = [compare.seed_stats(i, r, truth, a.evaluations) for i, r in enumerate(res)]
        row = compare.strategy_row(name + "".join(f" {k}={v}" for k, v in
                                                  opts.get(name, {}).items())
                                   + (f" b={strat.batch}" if name in batches else ""),
                                   stats, truth, wall)
        row["search_seconds"] = res[0].search_seconds
        if a.overhead:
            row["overhead"] = compare.search_overhead(strat, params, plan, a.seeds)
        rows.append(row)
        iqr = row["first_collision_iqr"]
        print(f"{row['strategy']:40s} found {row['found_collision_share'] * a.seeds:.0f}/{a.seeds}"
              f"  first {row['first_collision_median']:g} [{iqr[0]:g}, {iqr[1]:g}]"
              f"  gmax {row['seeds_reaching_global_max']}/{a.seeds}"
              f"  best_n {row['best_normalised_median']:.3f}"
              f"  distinct {row['distinct_critical_median']:g}"
              f"  corners {row['corner_share_median']:.2e}"
              f"  last-quarter {row['final_mean_reward_median']:.4f}"
              f"  final>=0.9gmax {sum((s['final_mean_reward'] or -1) >= 0.9 * truth['global_max_reward'] for s in stats)}/{a.seeds}"
              f"  wall {wall:.1f}s search {res[0].search_seconds:.1f}s"
              + (f"  overhead {row['overhead'] * 1000:.3f} ms/1000" if a.overhead else ""),
              flush=True)
    out = {"space": sp.name, "sut": a.sut, "sut_params": sut_params, **truth, "rows": rows,
           "evaluations": a.evaluations}
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1, default=lambda x: None if x is None else float(x))
    return out


if __name__ == "__main__":
    main()
