"""Throughput of the batched simulator, side by side with the NumPy reference and a per-scenario
Python loop (the original's shape of work), plus sweep times, compile time and peak memory.

    python experiments/bench_throughput.py            # full table (a few minutes on 2 cores)
    python experiments/bench_throughput.py --quick    # small sizes only
    python experiments/bench_throughput.py --chunk 1048576 --sizes 1e3,1e5,1e7,1e8  # a GPU

Scenarios are drawn from the ``paper-extended`` space with a fixed stride, so every size sees
the same mix. A *scenario-step* is one scenario advanced by one 0.1 s step of the fixed 30 s
horizon (300 steps per scenario); the simulator stops a batch early once all its episodes
have ended, so 'horizon steps/s' counts the work the fixed horizon represents and 'episode
steps/s' only the steps inside episodes. Peak memory is measured in a fresh subprocess per
size (resident set size, so it includes JAX and XLA themselves). Results go to stdout and to
``experiments/results/bench_throughput.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxfalsify as jf
from jaxfalsify.base.config import versions
from jaxfalsify.core import sim
from jaxfalsify.core.reference import python_loop_evaluate, reference_evaluate
from jaxfalsify.engine import sweep_chunks, sweep_totals
from jaxfalsify.engine.sweep_chunks import plan_chunks
from jaxfalsify.engine.sweep_config import calibrations
from jaxfalsify.suts import registry as sut_lib

SPACE = jf.load_space("paper-extended")
STRIDE = 997  # prime, coprime with the space size; size * STRIDE < 2**31 (no int32 overflow)
CHUNK = 1 << 17
HORIZON = jf.WORLD.horizon
SUT, PARAMS = sut_lib.make("carla-tm")


@partial(jax.jit, static_argnames=("chunk", "sharding"))
def _bench_chunk(start, table, params, world, chunk, sharding=None):
    """The sweep's work (scenarios, SUT parameters and world traced) on a strided mix."""
    flat = (((start + jnp.arange(chunk, dtype=jnp.int32)) % SPACE.size) * STRIDE) % SPACE.size
    if sharding is not None:
        flat = jax.lax.with_sharding_constraint(flat, sharding)
    sc = SPACE.layout.scenario(SPACE.layout.unravel(flat), table)
    out, _ = sim.batch_rollout(sc, flat, jax.random.key(0), SUT, params, world)
    return out.steps.sum(), out.collision.sum()


def _chunk_fn(chunk):
    """The compiled chunk with everything but the start bound (chunk rounded by plan_chunks)."""
    return partial(_bench_chunk, table=SPACE.table_array, params=PARAMS, world=jf.WORLD,
                   chunk=chunk, sharding=sim.local_batch_sharding())


def scenarios_numpy(n: int) -> dict:
    flat = ((np.arange(n, dtype=np.int64) % SPACE.size) * STRIDE) % SPACE.size
    idx = np.stack(np.unravel_index(flat, SPACE.shape), -1)
    return {k: np.asarray(v) for k, v in SPACE.scenario(idx).items()}


def time_jax(n: int, repeats: int = 3) -> dict:
    chunk = plan_chunks(n, CHUNK)
    run = _chunk_fn(chunk)
    t0 = time.perf_counter()
    jax.block_until_ready(run(jnp.int32(0)))
    compile_s = time.perf_counter() - t0
    best, steps = float("inf"), 0
    for _ in range(repeats):
        t0 = time.perf_counter()
        acc = []
        for b in range(0, n, chunk):  # one chunk at a time, as a sweep consumes them
            acc.append(jax.block_until_ready(run(jnp.int32(b))))
        dt = time.perf_counter() - t0
        best = min(best, dt)
        steps = int(sum(int(a[0]) for a in acc))  # padded rows of a last chunk included
    return {"seconds": best, "compile_seconds": compile_s, "episode_steps": steps}


def time_call(fn, *args) -> float:
    t0 = time.perf_counter()
    fn(*args)
    return time.perf_counter() - t0


def peak_rss_mib(n: int) -> float:
    """Peak resident memory [MiB] of a fresh process evaluating n scenarios."""
    r = subprocess.run([sys.executable, __file__, "--one", str(n)], capture_output=True,
                       text=True, check=True)
    return int(r.stdout.strip().splitlines()[-1]) / 1024  # ru_maxrss is in KiB on Linux


def one(n: int) -> None:
    chunk = plan_chunks(n, CHUNK)
    run = _chunk_fn(chunk)
    for b in range(0, n, chunk):  # results stay small; chunks keep memory flat
        jax.block_until_ready(run(jnp.int32(b)))
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def sweep_seconds(space_name: str) -> dict:
    """An exhaustive sweep's loop, best of 3 after compilation, two ways side by side: totals
    reduced on the device (what ``--rows none`` runs) and every outcome brought to the host
    and reduced there (what a sweep that keeps rows runs, less the writing)."""
    sp = jf.load_space(space_name)
    calib = calibrations(SUT, {})
    res = {"space": space_name, "n": sp.size}
    for name, reduced in (("device", True), ("host", False)):
        def loop():
            reds = [sweep_totals.Reducer()]
            for b, e, cols in sweep_chunks.iter_sweep(sp, calib, chunk=CHUNK, reduced=reduced):
                sweep_totals.fold(reds, sp, calib, b, e, cols, reduced)
            return reds[0]
        t0 = time.perf_counter()
        red = loop()
        res[f"compile_{name}_seconds"] = time.perf_counter() - t0  # first pass, compile incl.
        res[f"{name}_seconds"] = min(time_call(loop) for _ in range(3))
        res[f"{name}_collisions"] = red.collisions
    assert res["device_collisions"] == res["host_collisions"]
    res["seconds"], res["compile_seconds"] = res["device_seconds"], res["compile_device_seconds"]
    return res


def main() -> None:
    global CHUNK
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="sizes up to 1e5 only")
    ap.add_argument("--sizes", default=None,
                    help="comma-separated batch sizes (default 1e3..1e7; --quick: ..1e5)")
    ap.add_argument("--chunk", type=int, default=CHUNK,
                    help=f"scenarios per compiled call (default {CHUNK}; GPUs want ~1e6)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results"
                    / "bench_throughput.json")
    args = ap.parse_args()
    CHUNK = args.chunk
    sizes = [1_000, 10_000, 100_000] + ([] if args.quick else [1_000_000, 10_000_000])
    if args.sizes:
        sizes = [int(float(v)) for v in args.sizes.split(",")]
    rows = []
    print(f"device: {jax.devices()[0].device_kind} x{jax.device_count()}, "
          f"{os.cpu_count()} cores, jax {jax.__version__}, chunk {CHUNK}")
    print(f"{'batch':>10} {'jax s':>9} {'horizon steps/s':>16} {'episode steps/s':>16} "
          f"{'numpy s':>9} {'jax/numpy':>10} {'py-loop s':>10} {'jax/py-loop':>12}")
    for n in sizes:
        j = time_jax(n)
        row = {"batch": n, "jax_seconds": j["seconds"], "compile_seconds": j["compile_seconds"],
               "horizon_steps_per_s": n * HORIZON / j["seconds"],
               "episode_steps_per_s": j["episode_steps"] / j["seconds"]}
        if n <= 10_000:
            sc = scenarios_numpy(n)
            row["numpy_seconds"] = time_call(reference_evaluate, sc)
            row["speedup_vs_numpy"] = row["numpy_seconds"] / j["seconds"]
        if n <= 1_000:
            m = 100  # the per-scenario loop is slow: time 100 and scale to n
            sc = {k: v[:m] for k, v in scenarios_numpy(m).items()}
            row["pyloop_seconds"] = time_call(python_loop_evaluate, sc) * n / m
            row["speedup_vs_pyloop"] = row["pyloop_seconds"] / j["seconds"]
        rows.append(row)
        f = lambda k, fmt: format(row[k], fmt) if k in row else "-"  # noqa: E731
        print(f"{n:>10} {row['jax_seconds']:>9.4f} {row['horizon_steps_per_s']:>16.3e} "
              f"{row['episode_steps_per_s']:>16.3e} {f('numpy_seconds', '9.3f'):>9} "
              f"{f('speedup_vs_numpy', '10.1f'):>10} {f('pyloop_seconds', '10.2f'):>10} "
              f"{f('speedup_vs_pyloop', '12.0f'):>12}", flush=True)
    sweeps = [sweep_seconds("paper")] + ([] if args.quick else [sweep_seconds("paper-extended")])
    for s in sweeps:
        print(f"sweep {s['space']:>15}: {s['n']:>9} scenarios in {s['seconds']:.3f} s "
              f"(first pass with compile {s['compile_seconds']:.2f} s); outcomes to the host "
              f"and reduced there: {s['host_seconds']:.3f} s "
              f"(x{s['host_seconds'] / s['seconds']:.2f})")
    mem = {}
    # each in a fresh process, with the default chunk
    for n in ([100_000] if args.quick else [100_000, 1_000_000, 10_000_000]):
        mem[n] = peak_rss_mib(n)
        print(f"peak memory, {n:>10} scenarios: {mem[n]:8.0f} MiB", flush=True)
    if len(mem) > 1:
        print(f"peak memory ratio 1e7 / 1e5: {mem[10_000_000] / mem[100_000]:.2f}")
    result = {"device": jax.devices()[0].device_kind, "device_count": jax.device_count(),
              "chunk": CHUNK,
              "cpu_count": os.cpu_count(), "xla_cpu_threads": os.environ.get("NPROC"),
              "platform": platform.platform(),
              "versions": versions(), "rows": rows, "sweeps": sweeps,
              "peak_rss_mib": {str(k): v for k, v in mem.items()}}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "--one":
        one(int(sys.argv[2]))
    else:
        main()
