"""Search strategies side by side at the same batch: wall time and evaluations to the first
collision, distinct collisions found, in one process.

    python experiments/bench_search.py [--spaces aeb-9e6 ...] [--seeds 10] [--batch 4096]
                                       [--strategies reinforce/default random cmaes cem]
                                       [--evaluations 2048000] [--json out.json]

Each strategy x seed is one campaign (``jaxfalsify.engine.campaign.run``, compiled once per strategy
and reused for every seed), timed per chunk of updates on the host; the search time to the first
collision is the chunks' measured seconds up to the end of the update that held it
(``Result.search_seconds_at``), compilation excluded and reported apart. A seed that finds no
collision within the budget counts as the budget's full search time (a lower bound: the median
is then reported with ``>``). Ratios are against ``random`` at the same batch, same process.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from jaxfalsify.base.config import parse_assignments
from jaxfalsify.engine import campaign
from jaxfalsify.jobs import runs
from jaxfalsify.outputs import analysis

SUITE = Path(__file__).parent / "suite"
SPACES_DIR = Path(__file__).parent / "spaces"
SPACES = {
    # name: (space file, SUT, SUT parameters)
    "aeb-9e6": (SUITE / "aeb-9e6.toml", "sensor-aeb", {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "aeb-6e5": (SUITE / "aeb-6e5.toml", "sensor-aeb", {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "aeb-2e4": (SUITE / "aeb-2e4.toml", "sensor-aeb", {"ttc_full": 2.0, "ttc_partial": 3.0}),
    "island-dash": (SUITE / "island-dash.toml", "carla-tm", {"walker_time": 2.5}),
    "huge-aeb": (SUITE / "huge-aeb.toml", "sensor-aeb", {}),
    "paper": ("paper", "carla-tm", {}),
    "strong-aeb": (SPACES_DIR / "strong-aeb.toml", "sensor-aeb",
                   {"ttc_full": 2.4, "ttc_partial": 3.4, "fov": 90.0, "range": 60.0}),
    "fast-walkers": (SPACES_DIR / "fast-walkers.toml", "sensor-aeb",
                     {"ttc_full": 2.4, "ttc_partial": 3.4, "fov": 90.0, "range": 60.0}),
    "calibrated-aeb": (SPACES_DIR / "calibrated-aeb.toml", "sensor-aeb", {}),
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


def truth_clusters(b, sut, sut_params):
    """``(labels (N,), count)``: the exhaustive sweep's failure clusters (value-grid
    neighbours, :func:`jaxfalsify.outputs.analysis.chebyshev_components`) over every scenario number
    of a sweepable space (label -1: no collision)."""
    from jaxfalsify.engine import truth

    gt = truth.ground_truth(b.space, sut, sut_params)
    hit = np.asarray(gt["collision"], bool) & ~np.asarray(gt["nonfinite"], bool)
    labels = np.full(hit.size, -1, np.int64)
    where = np.nonzero(hit)[0]
    comp = analysis.chebyshev_components(b.space.unravel(where))
    labels[where] = comp
    return labels, int(comp.max()) + 1 if comp.size else 0


def one(space_name, strategy, seeds, batch, evaluations, every, options=None):
    space, sut, sut_params = SPACES[space_name]
    rc = runs.RunConfig(space=str(space), sut=sut, sut_params=sut_params, strategy=strategy,
                        strategy_params=options or {}, evaluations=evaluations, batch=batch,
                        checkpoint_every=every)
    b = rc.build()
    truth = truth_clusters(b, sut, sut_params) if b.space.size <= 20_000_000 else None
    rows = []
    for seed in seeds:
        res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                           seed)
        first = analysis.first_collision(res.fields)
        t_first = res.search_seconds_at(first) if first else None
        hit = analysis.collided(res.fields)
        distinct = len(np.unique(res.indices[hit], axis=0)) if hit.any() else 0
        clusters = None
        if truth is not None:  # ground-truth failure clusters with a member found
            found = truth[0][b.space.ravel(res.indices[hit])] if hit.any() else []
            clusters = f"{len(set(np.asarray(found).tolist()) - {-1})}/{truth[1]}"
        rows.append({"seed": seed, "truth_clusters_found": clusters,
                     "first_collision": first, "seconds_to_first": t_first,
                     "search_seconds": res.search_seconds, "compile_seconds":
                     res.compile_seconds, "collisions": int(hit.sum()),
                     "distinct_collisions": distinct})
    return rows


WIDE = {"name": "wide", "parameters": {  # 4 parameters x 4000 values, 1 x 3000 (the cost row;
    # 4000 on all five would pass the 1e18 scenarios a space may hold)
    "ego_offset": {"distribution": "uniform", "low": 1.0, "high": 10.0, "samples": 4000},
    "ped_accel": {"distribution": "uniform", "low": 0.0, "high": 0.1, "samples": 4000},
    "ped_speed": {"distribution": "uniform", "low": 0.5, "high": 2.5, "samples": 4000},
    "ped_offset": {"distribution": "uniform", "low": 2.0, "high": 6.0, "samples": 4000},
    "ped_speed_change": {"distribution": "uniform", "low": -0.3, "high": 0.3, "samples": 3000}}}


def controller_cost(space, sut, sut_params, batch, updates=20, repeats=3):
    """``(controller s, simulator s)`` per update at ``batch``: the default's ask + tell alone
    (sampling, log-probabilities, gradients, the optax steps; a synthetic reward), jitted as
    one scan of ``updates``, best of ``repeats``; and a ``random`` campaign's search seconds
    per update (the simulator's cost for the same batch: uniform sampling costs ~0)."""
    import jax
    import jax.numpy as jnp

    b = runs.RunConfig(space=space, sut=sut, sut_params=sut_params, batch=batch,
                       evaluations=batch * updates, checkpoint_every=updates).build()
    strat, p = b.strategy, b.strategy_params

    def step(state, key):
        k1, k2 = jax.random.split(key)
        idx, state = strat.ask(k1, state, p)
        r = -jnp.sum(idx.astype(jnp.float32), axis=1)
        return strat.tell_outcome(k2, state, idx, r, -r, r > 1e30, p), None

    f = jax.jit(lambda st, keys: jax.lax.scan(step, st, keys)[0])
    st = strat.init(jax.random.key(0), p)
    keys = jax.random.split(jax.random.key(1), updates)
    jax.block_until_ready(f(st, keys))
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(f(st, keys))
        best = min(best, time.perf_counter() - t)
    rb = runs.RunConfig(space=space, sut=sut, sut_params=sut_params, strategy="random",
                        batch=batch, evaluations=batch * updates,
                        checkpoint_every=updates).build()
    sim_s = min(campaign.run(rb.space, rb.sut, rb.sut_params, rb.strategy, rb.strategy_params,
                             rb.plan, seed).search_seconds for seed in range(repeats))
    return best / updates, sim_s / updates


def first_update(space_name, rows, batch, calls=30):
    """``{label: (first ms, later ms, first / random's)}`` for ``rows`` ``(label, strategy,
    options)``: medians over ``calls`` of the campaign's compiled chunk called for one update,
    from a fresh start (the strategy's start, its first ask, the batch's rollout, no tell) and
    from the state after that update (tell, ask, rollout), each call timed until its records
    are on the host, as :func:`campaign.drive` times a chunk. The rows' programs are called in
    turn (round robin, the order reversed every other round), so a slow spell of the shared
    machine falls on all of them; the ratio is the median over rounds of each first update's
    time over the same round's first update of ``random`` (None without a ``random`` row)."""
    import jax

    from jaxfalsify.core import sim

    space, sut, sut_params = SPACES[space_name]
    dev = jax.local_devices()[0]
    fresh, later = (jax.device_put(np.bool_(f), dev) for f in (True, False))
    one_update = jax.device_put(np.int32(1), dev)
    key_data = jax.device_put(np.stack([sim.seed_key_data(0)]), dev)

    def program(strategy, options):
        b = runs.RunConfig(space=str(space), sut=sut, sut_params=sut_params,
                           strategy=strategy, strategy_params=options or {}, batch=batch,
                           evaluations=batch * 10, checkpoint_every=5).build()
        args = campaign.args_for(b.space, b.sut_params, b.strategy_params, sim.WORLD,
                                 b.plan.evaluations)
        prog = campaign.program(campaign.Campaign(b.space.layout, b.sut, b.strategy,
                                                  b.plan.updates_per_chunk), args, 1)
        leaves = jax.device_put(jax.tree.leaves(args), dev)
        carry = jax.device_put([np.zeros(a.shape, a.dtype) for a in prog.in_avals[0]], dev)
        after = prog(carry, key_data, leaves, fresh, one_update)[0]  # compiled here

        def call(c, flag):
            t = time.perf_counter()
            jax.tree.map(np.asarray, prog(c, key_data, leaves, flag, one_update)[1])
            return time.perf_counter() - t

        call(carry, fresh), call(after, later)  # warmed
        return lambda: call(carry, fresh), lambda: call(after, later)

    calls_of = [(label, *program(strategy, options)) for label, strategy, options in rows]
    firsts = {label: [] for label, _, _ in calls_of}
    laters = {label: [] for label, _, _ in calls_of}
    for r in range(calls):
        for label, f, g in (calls_of if r % 2 == 0 else calls_of[::-1]):
            firsts[label].append(f())
            laters[label].append(g())
    base = np.asarray(firsts["random"]) if "random" in firsts else None
    return {label: (float(np.median(firsts[label])) * 1e3,
                    float(np.median(laters[label])) * 1e3,
                    None if base is None else float(np.median(np.asarray(firsts[label]) / base)))
            for label in firsts}


def learning(seeds: int, batch: int, evaluations: int | None):
    """The paper space's learning target: per seed, the last update's mean reward over the
    global maximum (the exhaustive sweep's, cached per machine). With ``evaluations`` given,
    ``novelty_until`` is half of it (as the default is half the default budget)."""
    from jaxfalsify.engine import truth

    options = {} if evaluations is None else {"novelty_until": float(evaluations // 2)}
    b = runs.RunConfig(batch=batch, evaluations=evaluations, strategy_params=options).build()
    gmax = float(np.max(truth.ground_truth(b.space, "carla-tm")["reward"]))
    out = []
    for seed in range(seeds):
        res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan,
                           seed)
        last = np.asarray(res.fields["reward"][-b.strategy.batch:], np.float64)
        out.append(float(np.nanmean(last)) / gmax)
    return gmax, out


def poisson_interval(k: int) -> tuple[float, float]:
    """Approximate 95 % interval of a Poisson mean given ``k`` events: Garwood's exact bounds
    through the Wilson-Hilferty cube-root approximation (within 1 % of the exact bounds from
    k = 1 on; no SciPy)."""
    z = 1.959964
    if k == 0:
        return 0.0, 3.689
    lo = k * (1 - 1 / (9 * k) - z / (3 * np.sqrt(k))) ** 3
    k1 = k + 1
    hi = k1 * (1 - 1 / (9 * k1) + z / (3 * np.sqrt(k1))) ** 3
    return float(lo), float(hi)


def median_time(rows):
    t = [r["seconds_to_first"] if r["seconds_to_first"] is not None else r["search_seconds"]
         for r in rows]
    censored = sum(r["seconds_to_first"] is None for r in rows)
    return float(np.median(t)), censored


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spaces", nargs="*", default=["aeb-9e6", "huge-aeb", "strong-aeb",
                                                     "paper"])
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
    ap.add_argument("--cost", action="store_true",
                    help="first the controller's cost per update against the simulator's, "
                    "on the paper space and on 5 parameters x 4000 values")
    ap.add_argument("--first-update", type=int, default=0, metavar="CALLS",
                    help="first each strategy's first update on each space, timed alone "
                    "(median of this many calls of the compiled chunk from a fresh start, "
                    "the strategies in turn, and its ratio to random's), and a later update")
    ap.add_argument("--learning", type=int, default=0, metavar="SEEDS",
                    help="first the paper space's learning target over this many seeds (the "
                    "main job's budget)")
    ap.add_argument("--learning-updates", type=int, nargs="*", default=[], metavar="UPDATES",
                    help="with --learning, also these budgets (in updates of the batch)")
    ap.add_argument("--default-param", action="append", default=[], metavar="NAME=VALUE",
                    help="an option of reinforce/default (e.g. novelty_until=614400)")
    ap.add_argument("--variant", action="append", default=[], metavar="NAME=VALUE,...",
                    help="one more row: reinforce/default with these options on top of "
                    "--default-param (e.g. steps=4,lr=0.06); repeatable")
    a = ap.parse_args(argv)
    default_options = parse_assignments(a.default_param, "--default-param")
    rows_of = [(st, st, default_options if st == "reinforce/default" else None)
               for st in a.strategies]  # (label, strategy, options)
    for v in a.variant:
        extra = parse_assignments([x for x in v.split(",") if x], "--variant")
        rows_of.append((f"default[{v}]", "reinforce/default", {**default_options, **extra}))
    out = {}
    if a.learning:
        for u in [None, *a.learning_updates]:  # None: the main job's budget
            gmax, ratios = learning(a.learning, a.batch, u and u * a.batch)
            budget = f"{u} updates" if u else "the main job's budget"
            print(f"paper space, {budget}: last update's mean reward / global maximum "
                  f"({gmax:.4f}) per seed: {', '.join(f'{r:.3f}' for r in ratios)}; >= 0.9 in "
                  f"{sum(r >= 0.9 for r in ratios)}/{len(ratios)}", flush=True)
            out[f"learning_{u}_updates" if u else "learning"] = {
                "global_max": gmax, "last_update_over_max": ratios}
    if a.cost:
        print(f"controller cost per update at batch {a.batch} (ask + tell of reinforce/default "
              f"alone) against the simulator's (a random campaign's search time per update):")
        for label, space in (("paper (carla-tm)", "paper"), ("4000^4 x 3000 values", WIDE)):
            c, sim_s = controller_cost(space, "carla-tm", {}, a.batch)
            print(f"  {label:28s} controller {c * 1e3:6.2f} ms, simulator {sim_s * 1e3:6.2f} ms: "
                  f"{c / sim_s:.1%}", flush=True)
            out.setdefault("cost", {})[label] = {"controller_s": c, "simulator_s": sim_s}
    for sp in a.spaces if a.first_update else ():
        print(f"{sp}: one update at batch {a.batch}, timed alone (medians of {a.first_update} "
              f"calls of each chunk program, the strategies in turn):")
        for st, (f, later, ratio) in first_update(sp, rows_of, a.batch,
                                                  a.first_update).items():
            x = "" if ratio is None else f" ({ratio:.3f} x random's in the same rounds)"
            print(f"  {st:20s} first update {f:6.2f} ms{x}, a later one {later:6.2f} ms",
                  flush=True)
            out.setdefault("first_update", {}).setdefault(sp, {})[st] = {
                "first_ms": f, "later_ms": later, "first_over_random": ratio}
    for sp in a.spaces if a.estimate else ():
        hits, n = estimate_share(sp, a.estimate)
        lo, hi = poisson_interval(hits)
        print(f"{sp}: {hits} collisions in {n} uniform draws: share {hits / n:.2e} "
              f"(95 % interval {lo / n:.1e}-{hi / n:.1e})", flush=True)
        out.setdefault("shares", {})[sp] = {"collisions": hits, "draws": n}
    for sp in a.spaces if a.seeds else ():  # --seeds 0: the first sections only
        print(f"\n== {sp}: batch {a.batch}, budget {a.evaluations}, {a.seeds} seeds")
        print(f"{'strategy':20s} {'found':>6s} {'median first (eval)':>20s} "
              f"{'median s to first':>18s} {'x random':>9s} {'distinct':>9s} "
              f"{'s/update':>9s} {'compile s':>9s}")
        base = None
        for st, strategy, options in rows_of:
            t0 = time.perf_counter()
            rows = one(sp, strategy, list(range(a.seeds)), a.batch, a.evaluations, a.every,
                       options)
            med, cens = median_time(rows)
            firsts = [r["first_collision"] or a.evaluations for r in rows]
            if st == "random":
                base = med
            n_up = -(-a.evaluations // a.batch)
            per_up = np.median([r["search_seconds"] for r in rows]) / n_up
            ratio = f"{med / base:.3f}" if base else "-"
            print(f"{st:20s} {len(rows) - cens:>3d}/{len(rows):<2d} "
                  f"{np.median(firsts):>20.0f} "
                  f"{('>' if cens * 2 >= len(rows) else '') + f'{med:.3f}':>18s} "
                  f"{ratio:>9s} {np.median([r['distinct_collisions'] for r in rows]):>9.0f} "
                  f"{per_up * 1e3:>7.1f}ms {rows[0]['compile_seconds']:>9.1f}"
                  + (f"  truth clusters found: "
                     f"{' '.join(r['truth_clusters_found'] for r in rows)}"
                     if rows[0]["truth_clusters_found"] else ""), flush=True)
            out.setdefault(sp, {})[st] = {"rows": rows, "median_seconds_to_first": med,
                                          "censored": cens,
                                          "wall_seconds": time.perf_counter() - t0}
    if a.json:
        a.json.write_text(json.dumps({"args": {k: str(v) for k, v in vars(a).items()},
                                      "xla_cpu_threads": os.environ.get("NPROC"),
                                      "results": out}, indent=1))


if __name__ == "__main__":
    main()
