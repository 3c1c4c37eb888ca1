"""Reproduce the paper's experiment: the `paper` REINFORCE preset on the `paper` space with the
`carla-tm` SUT, several seeds at once, 4000 episodes each.

    python experiments/paper_reproduction.py [--seeds 5] [--out
    experiments/results/paper_reproduction]

Writes the data the paper's figures show (drawn by the figures issue):

* ``reward_curve.csv`` — reward per episode for every seed, their mean, and a 100-episode moving
  average of the mean (paper Fig. 6);
* ``table_ii.json`` — seed 0's best critical scenario beside a typical non-critical one, with
  parameters and outcomes (paper Table II), and the high-risk shares over the second half
  (paper Fig. 8);
* ``distance_traces.csv`` — Euclidean distance over time for those two scenarios, with each
  step's high-risk flag (paper Fig. 7), and for 14 evaluated scenarios, 3 collisions and 11
  others (paper Fig. 9);
* ``summary.json`` — per seed: best reward, whether it is the space's global maximum, first
  collision, the episode from which the mean reward stays within 5 % of its final plateau.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path

import numpy as np

import jaxfalsify as jf
from jaxfalsify.base.config import jsonable
from jaxfalsify.engine import campaign
from jaxfalsify.engine.truth import sweep_arrays
from jaxfalsify.jobs.runs import RunConfig
from jaxfalsify.outputs import analysis


def plateau_episode(curve: np.ndarray, window: int = 100, tol: float = 0.05) -> int:
    """First episode after which the moving average stays within tol of its final value."""
    ma = np.convolve(curve, np.ones(window) / window, mode="valid")
    final = ma[-1]
    outside = np.nonzero(np.abs(ma - final) > tol * abs(final))[0]
    return int(outside[-1] + 1 + window) if outside.size else window


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--evaluations", type=int, default=4000,
                    help="budget per seed (the paper: 4000 episodes)")
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).parent / "results" / "paper_reproduction")
    args = ap.parse_args()
    b = RunConfig(strategy="reinforce/paper", evaluations=args.evaluations).build()
    sp = b.space
    t0 = time.perf_counter()
    results = campaign.run_seeds(sp, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                                 list(range(args.seeds)))
    wall = time.perf_counter() - t0
    truth = sweep_arrays(sp)
    gmax = float(np.nanmax(truth["reward"]))

    args.out.mkdir(parents=True, exist_ok=True)
    curves = np.stack([r.fields["reward"] for r in results])  # (S, N)
    mean = curves.mean(0)
    # trailing moving average over the last 100 episodes (fewer at the start, never padded)
    c = np.concatenate([[0.0], np.cumsum(mean)])
    i = np.arange(1, len(mean) + 1)
    ma = (c[i] - c[np.maximum(i - 100, 0)]) / (i - np.maximum(i - 100, 0))
    with open(args.out / "reward_curve.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", *(f"seed{s}" for s in range(args.seeds)), "mean", "mean_ma100"])
        for e in range(curves.shape[1]):
            w.writerow([e + 1, *(f"{c:.5f}" for c in curves[:, e]), f"{mean[e]:.5f}",
                        f"{ma[e]:.5f}"])

    res = results[0]
    best, t = analysis.best(res.fields), analysis.typical_non_critical(res.fields)
    pair = {"challenging": best, "non_challenging": t}
    table = {}
    for label, i in pair.items():
        table[label] = {"evaluation": i + 1, "params": sp.values_at(res.indices[i]),
                        **{f: res.fields[f][i].item() for f in campaign.RECORD_FIELDS}}
    (args.out / "table_ii.json").write_text(json.dumps(jsonable(table), indent=2) + "\n")

    # distance traces: the Table II pair, then 3 collisions + 11 others for Fig. 9
    col = np.nonzero(res.fields["collision"])[0]
    other = np.nonzero(~res.fields["collision"])[0]
    rng = np.random.default_rng(0)
    fig10 = list(rng.choice(col, min(3, col.size), replace=False)) + \
        list(rng.choice(other, min(11, other.size), replace=False))
    chosen = [("challenging", best), ("non_challenging", t)] + [(f"fig10_{k}", i)
                                                            for k, i in enumerate(fig10)]
    traj = jf.simulate(sp.scenario(np.stack([res.indices[i] for _, i in chosen])))
    with open(args.out / "distance_traces.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["trace", "evaluation", "collision", "t", "distance", "rss_distance",
                    "high_risk"])
        for k, (label, i) in enumerate(chosen):
            valid = np.asarray(traj.valid[k])
            for s in np.nonzero(valid)[0]:
                w.writerow([label, i + 1, bool(res.fields["collision"][i]),
                            f"{float(traj.t[k, s]):.1f}", f"{float(traj.distance[k, s]):.4f}",
                            f"{float(traj.rss_distance[k, s]):.4f}",
                            int(bool(traj.high_risk[k, s]))])

    per_seed = [{"seed": s, "best_reward": float(analysis.ranked_reward(r.fields).max()),
                 "global_max": bool(analysis.ranked_reward(r.fields).max() >= gmax - 1e-6),
                 "first_collision_evaluation": analysis.first_collision(r.fields),
                 "plateau_episode": plateau_episode(r.fields["reward"]),
                 "final_mean_reward_last_500": float(r.fields["reward"][-500:].mean())}
                for s, r in enumerate(results)]
    summary = {"seeds": args.seeds, "evaluations": args.evaluations, "global_max_reward": gmax,
               "plateau_episode_of_mean": plateau_episode(mean), "per_seed": per_seed,
               "wall_seconds_all_seeds": wall, "compile_seconds": results[0].compile_seconds}
    (args.out / "summary.json").write_text(json.dumps(jsonable(summary), indent=2) + "\n")

    print(f"paper preset, {args.seeds} seeds x {args.evaluations} evaluations in {wall:.1f} s "
          f"(all seeds together, compile included)")
    print("mean reward per 500 episodes: "
          + " ".join(f"{mean[i:i + 500].mean():.3f}" for i in range(0, len(mean), 500)))
    print(f"mean-reward plateau (within 5 %) from episode {summary['plateau_episode_of_mean']}")
    print(f"seeds reaching the global maximum {gmax:.4f}: "
          f"{sum(p['global_max'] for p in per_seed)}/{args.seeds}")
    print(f"{'Table II (seed 0)':<28}{'challenging':>16}{'non-challenging':>18}")
    for n in sp.names:
        print(f"{n:<28}{table['challenging']['params'][n]:>16.3f}"
              f"{table['non_challenging']['params'][n]:>18.3f}")
    for f in ("collision", "min_distance", "final_distance", "high_risk_share_second_half",
              "reward"):
        c, n = table["challenging"][f], table["non_challenging"][f]
        print(f"{f:<28}{c!s:>16.6}{n!s:>18.6}")
    print(f"wrote {args.out}/")


if __name__ == "__main__":
    main()
