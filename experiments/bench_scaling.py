"""How the simulator and a campaign scale: throughput vs batch size, horizon, number of
parameters and device count, and the wall time of the paper's training campaign.

    python experiments/bench_scaling.py [--quick]

All figures in one run, side by side; ratios matter more than absolute times on a shared
machine. Device counts above 1 are forced host devices (``XLA_FLAGS=
--xla_force_host_platform_device_count=N``) measured in subprocesses, so on a CPU they show the
sharding overhead, not new hardware. Writes ``experiments/results/bench_scaling.json`` and
``bench_scaling.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp

import jaxfalsify as jf
from jaxfalsify.core import sim
from jaxfalsify.engine import campaign
from jaxfalsify.engine.sweep_chunks import plan_chunks
from jaxfalsify.jobs.runs import RunConfig
from jaxfalsify.suts import registry as sut_lib

SPACE = jf.load_space("paper-extended")
STRIDE = 997
SUT, PARAMS = sut_lib.make("carla-tm")


@partial(jax.jit, static_argnames=("chunk", "n_params", "sharding"))
def _chunk(start, world, chunk, n_params=7, sharding=None):
    flat = (((start + jnp.arange(chunk, dtype=jnp.int32)) % SPACE.size) * STRIDE) % SPACE.size
    if sharding is not None:
        flat = jax.lax.with_sharding_constraint(flat, sharding)
    sc = SPACE.layout.scenario(SPACE.layout.unravel(flat), SPACE.table_array)
    # fewer parameters: the rest fixed at their first value (same simulator, smaller space)
    for name in list(SPACE.names)[n_params:]:
        sc[name] = jnp.full_like(sc[name], SPACE.values[SPACE.names.index(name)][0])
    out, _ = sim.batch_rollout(sc, flat, jax.random.key(0), SUT, PARAMS, world)
    return out.steps.sum()


def throughput(n: int, world=jf.WORLD, n_params: int = 7, repeats: int = 3) -> float:
    """Scenarios per second (best of repeats, after compilation)."""
    chunk = plan_chunks(n, 1 << 17)
    run = partial(_chunk, world=world, chunk=chunk, n_params=n_params,
                  sharding=sim.local_batch_sharding())
    jax.block_until_ready(run(jnp.int32(0)))
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready([run(jnp.int32(b)) for b in range(0, n, chunk)])
        best = min(best, time.perf_counter() - t0)
    return n / best


def campaign_seconds(seeds: int) -> dict:
    b = RunConfig(strategy="reinforce/paper", evaluations=4000).build()
    t0 = time.perf_counter()
    res = campaign.run_seeds(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params,
                             b.plan, list(range(seeds)))
    return {"seeds": seeds, "episodes": 4000, "wall_seconds": time.perf_counter() - t0,
            "compile_seconds": res[0].compile_seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--devices-child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = ap.parse_args()
    n = 20_000 if args.quick else 100_000
    if args.devices_child:
        print(json.dumps({"devices": jax.local_device_count(), "scn_per_s": throughput(n)}))
        return

    res: dict = {"device": jax.devices()[0].device_kind, "cpu_count": os.cpu_count(),
                 "jax": jax.__version__}
    print(f"device: {res['device']}, {os.cpu_count()} cores, jax {jax.__version__}")
    sizes = [1_000, 10_000, 100_000] + ([] if args.quick else [1_000_000])
    res["batch"] = [{"batch": b, "scn_per_s": throughput(b)} for b in sizes]
    base = res["batch"][0]["scn_per_s"]
    print("batch size   scenarios/s   x(batch 1e3)")
    for r in res["batch"]:
        print(f"{r['batch']:>10} {r['scn_per_s']:>13.3e} {r['scn_per_s'] / base:>12.1f}")

    res["horizon"] = []
    for h in (50, 100, 200, 300):
        w = jf.World(horizon=h)
        res["horizon"].append({"horizon": h, "scn_per_s": throughput(n, world=w)})
    print("horizon [steps]   scenarios/s   scenario-steps/s")
    for r in res["horizon"]:
        print(f"{r['horizon']:>15} {r['scn_per_s']:>13.3e} {r['scn_per_s'] * r['horizon']:>16.3e}")

    res["params"] = [{"params": p, "scn_per_s": throughput(n, n_params=p)} for p in (3, 5, 7)]
    print("parameters   scenarios/s")
    for r in res["params"]:
        print(f"{r['params']:>10} {r['scn_per_s']:>13.3e}")

    res["devices"] = []
    for d in (1, 2, 4):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={d}")
        cmd = [sys.executable, __file__, "--devices-child", str(d)] + \
            (["--quick"] if args.quick else [])
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
        res["devices"].append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("host devices   scenarios/s")
    for r in res["devices"]:
        print(f"{r['devices']:>12} {r['scn_per_s']:>13.3e}")

    res["campaign"] = [campaign_seconds(s) for s in ((1, 10) if not args.quick else (1, 2))]
    print("paper preset, 4000 episodes: " + "; ".join(
        f"{c['seeds']} seed(s) in {c['wall_seconds']:.1f} s (compile {c['compile_seconds']:.1f} s)"
        for c in res["campaign"]))

    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "bench_scaling.json").write_text(json.dumps(res, indent=2) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(16, 3.8))
    ax[0].loglog([r["batch"] for r in res["batch"]], [r["scn_per_s"] for r in res["batch"]], "o-")
    ax[0].set_xlabel("batch size")
    ax[1].plot([r["horizon"] for r in res["horizon"]], [r["scn_per_s"] for r in res["horizon"]],
               "o-")
    ax[1].set_xlabel("horizon [steps]")
    ax[2].plot([r["params"] for r in res["params"]], [r["scn_per_s"] for r in res["params"]], "o-")
    ax[2].set_xlabel("varied parameters")
    ax[3].plot([r["devices"] for r in res["devices"]], [r["scn_per_s"] for r in res["devices"]],
               "o-")
    ax[3].set_xlabel("forced host devices")
    for a in ax:
        a.set_ylabel("scenarios / s")
        a.set_ylim(bottom=0) if a is not ax[0] else None
    fig.suptitle(f"jaxfalsify throughput ({res['device']}, {os.cpu_count()} cores)")
    fig.tight_layout()
    fig.savefig(args.out / "bench_scaling.png", dpi=90)
    print(f"wrote {args.out}/bench_scaling.json, bench_scaling.png")


if __name__ == "__main__":
    main()
