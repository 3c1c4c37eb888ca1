"""Failure-rate estimates side by side: draws and wall time to a 10 % relative error (95 %
interval) by naive Monte Carlo and by importance sampling with the cross-entropy proposal,
against the exact rate of each space (every scenario evaluated).

    python experiments/bench_estimate.py              # three spaces, 3 seeds each
    python experiments/bench_estimate.py --seeds 5
    python experiments/bench_estimate.py --large    # a space too large to sweep (about 20 min)

For each space: the exact rate (:func:`jaxfalsify.jobs.estimate.exact_rate`); Monte Carlo run to
the target where that takes at most ``--mc-limit`` draws, else the draws it would need,
``z^2 (1 - p) / (p r^2)`` at the exact rate (marked *computed*); importance sampling run per
seed (draws of the proposal's fitting and of the estimate, both counted, and wall time
including them), with whether its interval holds the exact rate. Results also go to
``experiments/results/bench_estimate.json``.

``--large`` runs the spaces too large to sweep instead (``LARGE``; results in
``bench_estimate_large.json``): there the reference is one long naive Monte Carlo run (to the
same target, at most ``--mc-limit-large`` draws), which is also the Monte Carlo row, and
"covered" counts the importance-sampling intervals that hold the Monte Carlo estimate.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import jaxfalsify as jf
from jaxfalsify.jobs import estimate as est

SPACES = [  # (label, space, SUT, SUT parameters, requirement)
    ("paper, carla-tm", "paper", "carla-tm", {}, "collision"),
    ("island-dash, carla-tm", "experiments/suite/island-dash.toml", "carla-tm",
     {"walker_time": 2.5}, "collision"),
    ("aeb-9e6, sensor-aeb", "experiments/suite/aeb-9e6.toml", "sensor-aeb",
     {"ttc_full": 2.0, "ttc_partial": 3.0}, "collision"),
]
LARGE = [  # too large to sweep: the reference is a long Monte Carlo run
    ("calibrated-aeb, sensor-aeb", "experiments/spaces/calibrated-aeb.toml", "sensor-aeb", {},
     "collision"),
]
Z = 1.959963984540054


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--target", type=float, default=0.1)
    ap.add_argument("--mc-limit", type=int, default=4_000_000)
    ap.add_argument("--large", action="store_true",
                    help="the spaces too large to sweep, against a long Monte Carlo run")
    ap.add_argument("--mc-limit-large", type=int, default=200_000_000)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    if args.out is None:
        args.out = Path(__file__).parent / "results" / (
            "bench_estimate_large.json" if args.large else "bench_estimate.json")
    if args.large:
        return large(args)
    rows = []
    print(f"{'space':<24}{'exact rate':>12}{'estimator':>10}{'draws':>14}{'seconds':>9}"
          f"{'x fewer draws':>15}{'covered':>9}")
    for label, space, sut, params, req in SPACES:
        sp = jf.load_space(space)
        t0 = time.perf_counter()
        truth = est.exact_rate(sp, sut, params, req)
        p = truth["rate"]
        row = {"space": label, "scenarios": sp.size, "exact_rate": p,
               "exact_seconds": time.perf_counter() - t0, "requirement": req}
        need = Z * Z * (1 - p) / (p * args.target ** 2)
        if need <= args.mc_limit:
            mc = [est.estimate(est.EstimateConfig(
                space=space, sut=sut, sut_params=params, requirement=req, method="mc",
                target_rel_error=args.target, seed=s, samples=args.mc_limit))
                for s in range(args.seeds)]
            mc_draws = float(np.median([m["samples"] for m in mc]))
            mc_seconds = float(np.median([m["seconds"] for m in mc]))
            cov = sum(m["interval"][0] <= p <= m["interval"][1] for m in mc)
            how = "run"
        else:
            mc_draws, mc_seconds, cov, how = need, float("nan"), None, "computed"
        row["mc"] = {"draws": mc_draws, "seconds": mc_seconds, "covered": cov, "how": how}
        print(f"{label:<24}{p:>12.3g}{'mc':>10}{mc_draws:>14,.0f}"
              f"{mc_seconds:>9.1f}{1.0:>15.2f}"
              f"{'' if cov is None else f'{cov}/{args.seeds}':>9}"
              + ("  (computed from the exact rate)" if how == "computed" else ""), flush=True)
        runs = [est.estimate(est.EstimateConfig(
            space=space, sut=sut, sut_params=params, requirement=req, method="is",
            target_rel_error=args.target, seed=s)) for s in range(args.seeds)]
        draws = [r["samples"] for r in runs]  # the fitting stage's draws included
        secs = [r["seconds"] for r in runs]
        cov = sum(r["interval"][0] <= p <= r["interval"][1] for r in runs)
        d, t = float(np.median(draws)), float(np.median(secs))
        row["is"] = {"draws": draws, "seconds": secs, "covered": cov,
                     "estimates": [r["estimate"] for r in runs],
                     "reached": [r["reached_target"] for r in runs]}
        print(f"{'':<24}{'':>12}{'is':>10}{d:>14,.0f}{t:>9.1f}{mc_draws / d:>15.2f}"
              f"{f'{cov}/{args.seeds}':>9}", flush=True)
        rows.append(row)
    _write(args, rows)


def _write(args, rows: list[dict]) -> None:
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"target_rel_error": args.target, "seeds": args.seeds,
                                    "rows": rows}, indent=1, default=float) + "\n")


def large(args) -> None:
    """The spaces too large to sweep: one long Monte Carlo run (the reference and the Monte
    Carlo row), then importance sampling per seed."""
    rows = []
    print(f"{'space':<28}{'estimator':>10}{'estimate':>11}{'draws':>14}{'seconds':>9}"
          f"{'x fewer draws':>15}{'holds MC':>9}")
    for label, space, sut, params, req in LARGE:
        sp = jf.load_space(space)
        mc = est.estimate(est.EstimateConfig(
            space=space, sut=sut, sut_params=params, requirement=req, method="mc",
            target_rel_error=args.target, seed=0, samples=args.mc_limit_large))
        p = mc["estimate"]
        row = {"space": label, "scenarios": float(sp.size), "requirement": req,
               "mc": {"draws": mc["samples"], "seconds": mc["seconds"], "estimate": p,
                      "interval": mc["interval"], "violations": mc["violations"],
                      "reached": mc["reached_target"]}}
        print(f"{label:<28}{'mc':>10}{p:>11.3g}{mc['samples']:>14,.0f}{mc['seconds']:>9.1f}"
              f"{1.0:>15.2f}   interval [{mc['interval'][0]:.3g}, {mc['interval'][1]:.3g}]",
              flush=True)
        runs, holds = [], []
        for s in range(args.seeds):
            r = est.estimate(est.EstimateConfig(
                space=space, sut=sut, sut_params=params, requirement=req, method="is",
                target_rel_error=args.target, seed=s))
            runs.append(r)
            holds.append(r["interval"][0] <= p <= r["interval"][1])
            print(f"{'':<28}{'is':>10}{r['estimate']:>11.3g}{r['samples']:>14,.0f}"
                  f"{r['seconds']:>9.1f}{mc['samples'] / r['samples']:>15.2f}"
                  f"{'yes' if holds[-1] else 'no':>9}"
                  f"   interval [{r['interval'][0]:.3g}, {r['interval'][1]:.3g}]", flush=True)
        draws = [r["samples"] for r in runs]
        row["is"] = {"draws": draws, "seconds": [r["seconds"] for r in runs],
                     "estimates": [r["estimate"] for r in runs],
                     "intervals": [r["interval"] for r in runs],
                     "reached": [r["reached_target"] for r in runs],
                     "holds_mc_estimate": sum(holds)}
        print(f"{'':<28}{'is median':>10}{'':>11}{float(np.median(draws)):>14,.0f}"
              f"{float(np.median(row['is']['seconds'])):>9.1f}"
              f"{mc['samples'] / float(np.median(draws)):>15.2f}"
              f"{row['is']['holds_mc_estimate']:>7}/{args.seeds}", flush=True)
        rows.append(row)
    _write(args, rows)


if __name__ == "__main__":
    main()
