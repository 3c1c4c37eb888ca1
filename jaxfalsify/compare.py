"""``jaxfalsify compare``: every strategy on the same space and SUT, many seeds, against the
exhaustive sweep as ground truth.

Per strategy (seeds run at once, vmapped): share of seeds that found a collision; median and
IQR of evaluations to the first collision (over the seeds that found one); best reward over
the global maximum (median over seeds) and how many seeds reached the global maximum;
distinct critical scenarios found over all critical scenarios of the space (median); wall
seconds for all seeds together, compilation included.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from jaxfalsify import campaign, config as cfg
from jaxfalsify import sut as sut_lib
from jaxfalsify.runs import RunConfig
from jaxfalsify.space import Space

TOL = 1e-6  # reward equality with the global maximum (rewards are float32 sums)


def ground_truth(sp: Space, sut: sut_lib.SUT, sweep_dir: Path | None, quiet: bool = True
                 ) -> dict:
    """Load the sweep's summary (running the sweep into ``sweep_dir`` if it is missing)."""
    from jaxfalsify.sweep import run_sweep

    d = sweep_dir or Path("sweeps") / f"{Path(sp.name).stem}-{sut.name}-s{sp.seed}"
    summary_file = d / "summary.json"
    if summary_file.exists():
        s = json.loads(summary_file.read_text())
        if (s.get("n_scenarios") == sp.size and s.get("sut") == sut.name
                and s.get("seed") == sp.seed):
            return {**s, "dir": str(d), "loaded": True}
    s = run_sweep(sp, sut.name, d)
    return {**cfg.jsonable(s), "dir": str(d), "loaded": False}


def seed_stats(seed: int, r: campaign.Result) -> dict:
    return {"seed": seed, "first_collision": campaign.first_collision_evaluation(r),
            "best": float(r.ranked_reward().max()),
            "distinct": len(campaign.distinct_critical(r))}


def strategy_row(name: str, stats: list[dict], truth: dict, wall: float) -> dict:
    found = [s["first_collision"] for s in stats if s["first_collision"] is not None]
    best = np.array([s["best"] for s in stats])
    gmax = truth["global_max_reward"]
    distinct = np.array([s["distinct"] for s in stats])
    q = np.percentile(found, [25, 50, 75]) if found else [np.nan] * 3
    return {"strategy": name, "seeds": len(stats),
            "found_collision_share": len(found) / len(stats),
            "first_collision_median": float(q[1]), "first_collision_iqr": [float(q[0]),
                                                                           float(q[2])],
            "best_over_global_max_median": float(np.median(best / gmax)),
            "seeds_reaching_global_max": int(np.sum(best >= gmax - TOL)),
            "distinct_critical_median": float(np.median(distinct)),
            "all_critical": int(truth["n_collisions"]),
            "wall_seconds": wall}


def run_compare(strategies: list[str], seeds: int, budget: int, base: RunConfig,
                sweep_dir: Path | None = None, progress=None, process_id: int = 0,
                num_processes: int = 1, out_dir: Path | None = None) -> dict:
    """Every strategy on seeds 0..seeds-1. With several processes (``jax.distributed``),
    process i runs its contiguous share of the seeds and writes a part; process 0 merges."""
    from jaxfalsify.distributed import barrier, share

    sp, sut, _, _ = base.build()
    if process_id == 0:
        truth = ground_truth(sp, sut, sweep_dir)
    barrier("jaxfalsify-compare-truth")
    if process_id != 0:
        truth = ground_truth(sp, sut, sweep_dir)  # written by process 0: just loads it
    lo, hi = share(seeds, process_id, num_processes)
    mine = list(range(lo, hi))
    parts: dict[str, dict] = {}
    for entry in strategies:
        name, _, preset = entry.partition("/")  # reinforce/paper picks a preset
        rc = RunConfig(space=base.space, space_seed=base.space_seed, sut=base.sut,
                       strategy=name,
                       preset=(preset or base.preset) if name == "reinforce" else None,
                       episodes=budget)
        sp, sut, strat, plan = rc.build()
        label = f"reinforce/{rc.resolved().preset}" if name == "reinforce" else name
        t0 = time.perf_counter()
        results = campaign.run_seeds(sp, sut, strat, plan, mine) if mine else []
        parts[label] = {"stats": [seed_stats(s, r) for s, r in zip(mine, results)],
                        "wall": time.perf_counter() - t0}
        if progress and num_processes == 1:
            progress(strategy_row(label, parts[label]["stats"], truth, parts[label]["wall"]))
    if num_processes > 1:
        out_dir.mkdir(parents=True, exist_ok=True)
        cfg.write_atomic(out_dir / f".compare.part-{process_id:05d}.json",
                         json.dumps(cfg.jsonable(parts)) + "\n")
        barrier("jaxfalsify-compare-parts")
        all_parts = [json.loads((out_dir / f".compare.part-{i:05d}.json").read_text())
                     for i in range(num_processes)]
        merged = {k: {"stats": sum((p[k]["stats"] for p in all_parts), []),
                      "wall": max(p[k]["wall"] for p in all_parts)} for k in parts}
    else:
        merged = parts
    rows = [strategy_row(k, v["stats"], truth, v["wall"]) for k, v in merged.items()]
    return {"space": sp.name, "space_seed": sp.seed, "sut": sut.name, "budget": budget,
            "seeds": seeds, "processes": num_processes,
            "global_max_reward": truth["global_max_reward"],
            "n_scenarios": truth["n_scenarios"], "all_critical": truth["n_collisions"],
            "ground_truth": truth["dir"], "rows": rows, "versions": cfg.versions()}


def table_markdown(result: dict) -> str:
    head = ("| strategy | seeds with a collision | evaluations to first collision, median "
            "[IQR] | best / global max (median) | seeds at global max | distinct critical "
            "found (median) / all | wall s (all seeds) |")
    lines = [head, "|" + "---|" * 7]
    for r in result["rows"]:
        iqr = r["first_collision_iqr"]
        first = ("-" if np.isnan(r["first_collision_median"]) else
                 f"{r['first_collision_median']:g} [{iqr[0]:g}, {iqr[1]:g}]")
        lines.append(f"| {r['strategy']} | {r['found_collision_share'] * r['seeds']:.0f}/"
                     f"{r['seeds']} | {first} | {r['best_over_global_max_median']:.4f} | "
                     f"{r['seeds_reaching_global_max']}/{r['seeds']} | "
                     f"{r['distinct_critical_median']:g} / {r['all_critical']} | "
                     f"{r['wall_seconds']:.1f} |")
    return "\n".join(lines)
