"""``jaxfalsify compare``: strategies on the same space and SUT, many seeds, against the
exhaustive sweep as ground truth (from the per-user cache, see :func:`jaxfalsify.sweep.ground_truth`).

Per strategy (its seeds in one compiled call): share of seeds that found a collision; median
and IQR of evaluations to the first collision (over the seeds that found one); best reward over
the global maximum (median over seeds) and how many seeds reached the global maximum;
distinct critical scenarios found over all critical scenarios of the space (median); wall
seconds for all seeds together, compilation included. ``compare.json`` holds per-seed rows.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from jaxfalsify import analysis, campaign, config as cfg, search, store
from jaxfalsify.progress import Clock, Progress
from jaxfalsify.runs import RunConfig

TOL = 1e-6  # reward equality with the global maximum (rewards are float32 sums)
DEFAULT_STRATEGIES = ("reinforce/default", "reinforce/paper", "random", "grid", "cem",
                      "anneal", "cmaes")


@dataclasses.dataclass(frozen=True)
class CompareConfig:
    strategies: tuple[str, ...] = DEFAULT_STRATEGIES
    seeds: int = 10
    evaluations: int = 4000
    space: Any = "paper"
    space_seed: int = 0
    sut: str = "carla-tm"
    sut_params: Mapping[str, float] = dataclasses.field(default_factory=dict)

    def run_config(self, strategy: str) -> RunConfig:
        return RunConfig(space=self.space, space_seed=self.space_seed, sut=self.sut,
                         sut_params=self.sut_params, strategy=strategy,
                         evaluations=self.evaluations)

    def check(self) -> None:
        from jaxfalsify.runs import check_int

        check_int("seeds", self.seeds, 1, 10_000)
        if not self.strategies:
            raise ValueError("strategies: none given")
        for s in self.strategies:
            search.canonical(s)
        self.run_config(self.strategies[0]).build()

    def to_toml(self) -> str:
        return cfg.dumps_toml({"kind": "compare", "strategies": list(self.strategies),
                               "seeds": self.seeds, "evaluations": self.evaluations,
                               "space_seed": self.space_seed, "sut": self.sut,
                               "sut_params": dict(self.sut_params),
                               "space": self.space if isinstance(self.space, Mapping)
                               else self.space})


def seed_stats(seed: int, r: campaign.Result, gmax: float) -> dict:
    b = analysis.best(r.fields)
    best = float(analysis.ranked_reward(r.fields)[b])
    return {"seed": seed, "first_collision": analysis.first_collision(r.fields),
            "best": best, "reached_global_max": bool(best >= gmax - TOL),
            "distinct": len(analysis.distinct_critical(r.indices, r.fields))}


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
            "seeds_reaching_global_max": int(sum(s["reached_global_max"] for s in stats)),
            "distinct_critical_median": float(np.median(distinct)),
            "all_critical": int(truth["n_collisions"]),
            "wall_seconds": wall, "per_seed": stats}


def truth_summary(sp, b) -> dict:
    from jaxfalsify.sweep import ground_truth

    t = ground_truth(sp, b.sut, b.sut_params)
    r = np.where(np.isnan(t["reward"]), -np.inf, t["reward"]).astype(np.float64)
    gmax = float(r.max())
    return {"n_scenarios": int(len(r)), "n_collisions": int(np.sum(t["collision"])),
            "global_max_reward": gmax, "global_max_ties": int(np.sum(r == gmax))}


def execute(config: CompareConfig, out: Path | str, *, force: bool = False,
            progress: Progress | None = None, stop=None, process_id: int = 0,
            num_processes: int = 1, startup_seconds: float = 0.0) -> dict:
    """Run every strategy on seeds 0..seeds-1 and write ``compare.json``/``compare.md`` to
    ``out``. With several processes (``jax.distributed``), process i runs its contiguous share
    of the seeds and writes a part; process 0 merges. Returns the result."""

    clock = Clock(startup_seconds)
    progress = progress or Progress()
    out = Path(out)
    config.check()
    base = config.run_config(config.strategies[0]).build()
    lk = store.open_folder(out, "compare", force=force,
                           name=".lock" if process_id == 0 else f".lock-part-{process_id:05d}")
    try:
        lk.claim("compare")
        return _execute(config, out, base, progress, process_id, num_processes, clock, stop)
    finally:
        lk.release()


def _execute(config: CompareConfig, out: Path, base, progress: Progress, process_id: int,
             num_processes: int, clock: Clock, stop) -> dict:
    from jaxfalsify.distributed import barrier, share

    sp = base.space
    progress.phase(f"ground truth: every scenario of {sp.name} ({sp.size:,}) x {config.sut}")
    with clock("ground_truth"):
        truth = truth_summary(sp, base) if process_id == 0 else None
        barrier("jaxfalsify-compare-truth")
        if truth is None:
            truth = truth_summary(sp, base)  # cached by process 0: a load
    lo, hi = share(config.seeds, process_id, num_processes)
    mine = list(range(lo, hi))
    parts: dict[str, dict] = {}
    for k, entry in enumerate(config.strategies):
        b = config.run_config(entry).build()
        label = search.canonical(entry)
        t0 = time.perf_counter()
        progress.phase(f"[{k + 1}/{len(config.strategies)}] {label}: compiling "
                       f"{len(mine)} seeds x {config.evaluations} evaluations")
        started = {}

        def chunk_done(done, records, label=label):
            if not started:
                progress.start(b.plan.budget, done, "eval", f"{label} ({len(mine)} seeds)")
                started["yes"] = True
            progress.update(done)

        try:
            results = campaign.run_seeds(sp, b.sut, b.sut_params, b.strategy,
                                         b.strategy_params, b.plan, mine, progress=chunk_done,
                                         stop=stop) if mine else []
        except (campaign.Stopped, KeyboardInterrupt):
            progress.close()
            from jaxfalsify.runs import Interrupted

            raise Interrupted("compare", out, k, len(config.strategies), "strategies (nothing "
                              "written; rerun the comparison)") from None
        progress.close()
        wall = time.perf_counter() - t0
        stats = [seed_stats(s, r, truth["global_max_reward"]) for s, r in zip(mine, results)]
        parts[label] = {"stats": stats, "wall": wall,
                        "compile": results[0].compile_seconds if results else 0.0}
        clock.add("compile", parts[label]["compile"])
        clock.add("search", wall - parts[label]["compile"])
    if num_processes > 1:
        out.mkdir(parents=True, exist_ok=True)
        store.write_json(out / f".compare.part-{process_id:05d}.json", parts)
        barrier("jaxfalsify-compare-parts")
        all_parts = [json.loads((out / f".compare.part-{i:05d}.json").read_text())
                     for i in range(num_processes)]
        merged = {k: {"stats": sum((p[k]["stats"] for p in all_parts), []),
                      "wall": max(p[k]["wall"] for p in all_parts)} for k in parts}
    else:
        merged = parts
    rows = [strategy_row(k, v["stats"], truth, v["wall"]) for k, v in merged.items()]
    result = {"space": sp.name, "space_seed": config.space_seed, "sut": config.sut,
              "evaluations": config.evaluations, "seeds": config.seeds,
              "processes": num_processes, **truth, "rows": rows, "versions": cfg.versions()}
    if process_id == 0:
        with clock("writing"):
            out.mkdir(parents=True, exist_ok=True)
            store.write_atomic(out / "config.toml", config.to_toml())
            store.write_json(out / "compare.json", result, indent=2)
            store.write_atomic(out / "compare.md", table_markdown(result) + "\n")
            store.write_json(out / "timing.json", clock.summary(), indent=2)
        for i in range(num_processes if num_processes > 1 else 0):
            (out / f".compare.part-{i:05d}.json").unlink(missing_ok=True)
    result["timing"] = clock.summary()
    return result


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
