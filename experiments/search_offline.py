"""Strategies against a precomputed sweep (a lookup table instead of the simulator): fast
iteration on search hyperparameters. The table is an ``.npz`` with ``collision``, ``reward``,
``robustness`` per scenario in space order (``--table PATH`` sweeps the space and writes it
there when the file does not exist yet).

    python experiments/search_offline.py --space experiments/suite/aeb-2e4.toml \\
        --sut-param ttc_full=2.0 --sut-param ttc_partial=3.0 --table /tmp/aeb-2e4.npz \\
        --strategies reinforce/default,cmaes --opt reinforce/default:lr=0.05

(a development tool: ``jaxfalsify compare --suite`` is the benchmark, on the simulator)
"""
from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxfalsify as jf
from jaxfalsify import search
from jaxfalsify.jobs import compare_stats


def load_table(space, sut, sut_params, path):
    if path and os.path.exists(path):
        return dict(np.load(path))
    from jaxfalsify.engine.truth import sweep_arrays
    g = sweep_arrays(space, sut, sut_params,
                     fields=("collision", "reward", "robustness", "min_ttc"))
    if path:
        np.savez(path, **g)
    return g


def run(strat, params, table, shape, budget, seeds):
    B = strat.batch
    n_upd = -(-budget // B)
    coll = jnp.asarray(table["collision"])
    rew = jnp.asarray(np.where(np.isnan(table["reward"]), -np.inf, table["reward"]), jnp.float32)
    rob = jnp.asarray(table["robustness"], jnp.float32)
    # an older table without min_ttc: every TTC unknown (counts as the cap: no tie-break)
    ttc = jnp.asarray(table.get("min_ttc", np.full(rob.shape, np.inf)), jnp.float32)
    radix = np.cumprod((1,) + tuple(shape[::-1]))[:-1][::-1].astype(np.int64)

    def one(key):
        def upd(carry, k):
            state, u = carry
            k1, k2 = jax.random.split(k)
            idx, state = strat.ask(k1, state, params)
            flat = jnp.sum(idx * jnp.asarray(radix, jnp.int32), -1)
            ev = u * B + jnp.arange(B)
            ok = ev < budget
            r = jnp.where(ok, rew[flat], -jnp.inf)
            c = coll[flat] & ok
            state = strat.tell_outcome(k2, state, idx, r, jnp.where(ok, rob[flat], jnp.inf), c,
                                       params, ttc=jnp.where(ok, ttc[flat], jnp.inf))
            return (state, u + 1), (idx, r, c)
        k0, k1 = jax.random.split(key)
        _, (idx, r, c) = jax.lax.scan(upd, (strat.init(k0, params), 0),
                                      jax.random.split(k1, n_upd))
        return idx.reshape(-1, len(shape))[:budget], r.reshape(-1)[:budget], c.reshape(-1)[:budget]

    f = jax.jit(lambda ks: jax.lax.map(one, ks))
    keys = jax.vmap(jax.random.key)(jnp.arange(seeds))
    t0 = time.perf_counter()
    out = jax.tree.map(np.asarray, f(keys))
    return out, time.perf_counter() - t0


def _value(v):
    try:
        return int(v)
    except ValueError:
        pass
    try:
        return float(v)
    except ValueError:
        return v


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--space", default="paper")
    ap.add_argument("--sut", default="sensor-aeb")
    ap.add_argument("--sut-param", action="append", default=[])
    ap.add_argument("--table")
    ap.add_argument("--strategies", default="reinforce/default,random,cmaes")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--evaluations", type=int, default=4000)
    ap.add_argument("--opt", action="append", default=[], help="STRATEGY:K=V,K=V[:BATCH]")
    ap.add_argument("--per-seed", action="store_true",
                    help="also print each seed's first collision, best and last-quarter mean")
    a = ap.parse_args(argv)
    sp = jf.load_space(a.space)
    sut_params = {k: float(v) for k, v in (s.split("=") for s in a.sut_param)}
    table = load_table(sp, a.sut, sut_params, a.table)
    r = np.where(np.isnan(table["reward"]), -np.inf, table["reward"])
    gmax = r.max()
    n_c = int(table["collision"].sum())
    u = compare_stats.uniform_first_collision(sp.size, n_c, a.evaluations)
    print(f"{sp.name}: {n_c} collisions of {sp.size} (p={u['p']:.2e}), 1/p={u['expected']:.4g},"
          f" gmax={gmax:.4f}, uniform corners {2.0 ** sum(n > 1 for n in sp.shape) / sp.size:.2e}")
    configs = [(s, {}, None) for s in a.strategies.split(",") if s]
    for o in a.opt:
        parts = o.split(":")
        kv = dict((x.split("=")[0], _value(x.split("=")[1])) for x in parts[1].split(",") if x)
        configs.append((parts[0], kv, int(parts[2]) if len(parts) > 2 else None))
    for name, kv, batch in configs:
        strat, params = search.make(name, sp.shape, batch, **kv)
        (idx, rr, cc), dt = run(strat, params, table, sp.shape, a.evaluations, a.seeds)
        first = np.array([np.argmax(c) + 1 if c.any() else a.evaluations + 1 for c in cc])
        best = rr.max(1)
        reached = np.sum(best >= gmax - 1e-6)
        corners = np.mean(compare_stats.corner_mask(idx.reshape(-1, len(sp.shape)), sp.shape))
        tail = rr[:, -a.evaluations // 4:]
        fm = np.array([np.mean(t[np.isfinite(t)]) for t in tail])
        distinct = np.median([len(np.unique(i[c], axis=0)) for i, c in zip(idx, cc)])
        q = np.percentile(first, [25, 50, 75])
        found = np.sum(first <= a.evaluations)
        print(f"{name:18s} {str(kv):42s} b={strat.batch:4d} found {found}/{a.seeds}"
              f" first {q[1]:g} [{q[0]:g},{q[2]:g}] gmax {reached}/{a.seeds} distinct {distinct:g}"
              f" corners {corners:.1e} last-q {np.median(fm):.4f}"
              f" (>=.9gmax {np.sum(fm >= 0.9 * gmax)})"
              f" {dt:.1f}s", flush=True)
        if a.per_seed:
            for i in range(a.seeds):
                print(f"    seed {i:2d}: first {first[i]:5d}  best/gmax {best[i] / gmax:.4f}"
                      f"  last-q/gmax {fm[i] / gmax:.4f}")


if __name__ == "__main__":
    main()
