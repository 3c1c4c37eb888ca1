"""Where a simulator step's time goes, and how the simulator compares with a minimal model.

    python experiments/bench_step.py              # all 100,000 scenarios of the paper space
    python experiments/bench_step.py --n 20000    # a strided sample (quicker)
    python experiments/bench_step.py --check      # first: every outcome of 2.1e6 scenarios
                                                  # bit-identical to the stored hashes (all
                                                  # but the centre distance: UNHASHED)

Every figure is measured in this one process, side by side (best of ``--repeats`` warm calls
of the compiled program; compilation excluded), on the same scenarios:

* **minimal**: a JAX crossing model written here, the floor for this shape of work: a point-mass
  car that starts at rest, speeds up at 2.75 m/s^2 to the autopilot's target speed and keeps
  it, and brakes at a fixed 6 m/s^2 while the pedestrian is in its lane within 15 m ahead;
  the pedestrian's speed profile and kinematics, the box gaps and a contact check, the same
  start positions, end of episode, horizon, batch, blocks of 32 steps and early exit.
* **zero**: :func:`jaxfalsify.evaluate` with a SUT that commands 0 m/s^2 and has no state: the
  simulator core alone (kinematics, swept contact, box distance, RSS, TTC, reward bookkeeping).
* **none**, **carla-tm**, **sensor-aeb**: the built-in SUTs (``none``: the autopilot's PID).
* ``1/lane``: the same SUTs with every scenario of the batch on its own lane until the batch's
  longest episode ends (``sim.LANES_PER = 1``), instead of lanes refilled as episodes end;
* ablations of the core (timing only, outcomes change): ``-ttc`` (the TTC metric replaced by a
  constant), ``-rss`` (the RSS safe distance replaced by 0).

A *scenario-step* is one scenario advanced by one 0.1 s step inside its episode (the sum of
``Outcome.steps``). The table's ``ns/step`` is the time per scenario-step; ``x minimal`` is
scenario-steps/s relative to the minimal model's. Results also go to
``experiments/results/bench_step.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

os.environ["JAXFALSIFY_NO_CACHE"] = "1"  # the ablations must be traced, not loaded from cache

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxfalsify as jf  # noqa: E402
from jaxfalsify.base.config import versions  # noqa: E402
from jaxfalsify.core import sim
from jaxfalsify.scenario import metrics  # noqa: E402
from jaxfalsify.suts import registry as sut_lib  # noqa: E402

W = jf.WORLD


def minimal_model(n_blocks: int = -(-W.horizon // sim.BLOCK)):
    """A jitted ``(scenario dict of (N,) arrays) -> (steps, collision)`` of the minimal model."""
    half_x = (W.ego_length + W.ped_length) / 2
    half_y = (W.ego_width + W.ped_width) / 2
    speed = float(sut_lib.target_speed(sut_lib.AutopilotParams()))
    dt = jnp.float32(W.dt)

    def one(sc):
        start_x, ped_y0 = sim.start_positions(sc["ego_offset"], sc["ped_offset"], W)
        p_start, p_grow = sim.ped_profile_constants(sc["ped_speed"], sc["ped_accel"])

        def step(c, k):
            x, v, y, alive, n, hit = c
            vp = sim._profile_at(k.astype(jnp.float32), p_start, p_grow, sc["ped_accel"],
                                 sc["ped_speed_change"], sc["ped_change_step"])
            ahead = W.crosswalk_x - x
            in_lane = jnp.abs(y - W.ego_y) < half_y
            a = jnp.where((ahead > 0) & (ahead < 15.0) & in_lane, -6.0, 2.75)
            v1 = jnp.clip(v + a * dt, 0.0, speed)
            x1 = x + (v + v1) / 2 * dt
            y1 = y + vp * dt
            gx, gy = metrics.box_gaps(W.crosswalk_x - x1, y1 - W.ego_y, half_x, half_y)
            contact = (gx <= 0) & (gy <= 0)
            move = alive & (k < W.horizon)
            done = contact | (x1 > W.end_x)
            return (jnp.where(move, x1, x), jnp.where(move, v1, v), jnp.where(move, y1, y),
                    move & ~done, n + move.astype(jnp.int32), hit | (move & contact)), None

        def block(cb):
            c, b = cb
            c, _ = jax.lax.scan(step, c, b * sim.BLOCK + jnp.arange(sim.BLOCK, dtype=jnp.int32))
            return c, b + 1

        init = (start_x, jnp.float32(0.0), jnp.float32(ped_y0), jnp.bool_(True),
                jnp.int32(0), jnp.bool_(False))
        c, _ = jax.lax.while_loop(lambda cb: cb[0][3] & (cb[1] < n_blocks), block,
                                  (init, jnp.int32(0)))
        return c[4], c[5]

    return jax.jit(jax.vmap(one))


def zero_sut() -> sut_lib.SUT:
    return sut_lib.SUT("zero", lambda obs, state, params, key: (jnp.float32(0.0), state),
                       lambda key, params: jnp.float32(0.0), None, stochastic=False)


HASHES = Path(__file__).parent / "results" / "outcome_hashes.json"
# not in the hashes: min_rss_margin (added after they were stored) and final_distance (the
# centre distance, whose last bits depend on how XLA fuses the step: a sample of it is checked
# within 2 ulp by tests/core/test_stored_outcomes.py; docs/performance.md)
UNHASHED = ("min_rss_margin", "final_distance")


def outcome_hash(space_name: str, sut: str, chunk: int = 250_000) -> str:
    """SHA-256 of every outcome field of every scenario of a space (in scenario order)."""
    import hashlib

    sp = jf.load_space(space_name)
    h = hashlib.sha256()
    for b in range(0, sp.size, chunk):
        flat = np.arange(b, min(b + chunk, sp.size))
        idx = np.stack(np.unravel_index(flat, sp.shape), -1)
        out = jf.evaluate({k: np.asarray(v, np.float32) for k, v in sp.scenario(idx).items()},
                          sut=sut, chunk_size=chunk)
        for k in sorted(vars(out)):
            if k in UNHASHED:
                continue
            h.update(k.encode())
            h.update(np.ascontiguousarray(getattr(out, k)).tobytes())
    return h.hexdigest()


def check_outcomes() -> bool:
    """Every outcome of the paper space (each SUT) and of paper-extended (carla-tm, 2,000,000
    scenarios) against the hashes stored from the simulator before its speed-ups (all fields
    but ``UNHASHED``)."""
    want = json.loads(HASHES.read_text())
    ok = True
    for key, digest in want.items():
        space_name, sut = key.split("/")
        same = outcome_hash(space_name, sut) == digest
        ok &= same
        print(f"{key}: {'identical' if same else 'DIFFERENT'}", flush=True)
    return ok


def best_of(fn, repeats: int) -> float:
    fn()  # compile and warm
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=100_000, help="scenarios (default: the whole "
                    "paper space, 100,000)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results"
                    / "bench_step.json")
    ap.add_argument("--check", action="store_true", help="also check every outcome of the "
                    "paper space and of paper-extended against the stored hashes")
    args = ap.parse_args()
    if args.check and not check_outcomes():
        raise SystemExit("outcomes differ from the stored ones")

    space = jf.load_space("paper")
    flat = (np.arange(args.n, dtype=np.int64) * 7919) % space.size if args.n < space.size \
        else np.arange(space.size)
    idx = np.stack(np.unravel_index(flat, space.shape), -1)
    sc = {k: np.asarray(v, np.float32) for k, v in space.scenario(idx).items()}
    full = sim._check_scenario(sc)
    n = len(flat)
    rows = []

    mini = minimal_model()
    args_mini = {k: jnp.asarray(v) for k, v in full.items()}
    steps_mini = int(jax.block_until_ready(mini(args_mini))[0].sum())
    t = best_of(lambda: jax.block_until_ready(mini(args_mini)), args.repeats)
    rows.append(("minimal", t, steps_mini))

    def sim_row(name, sut):
        out = jf.evaluate(sc, sut=sut, chunk_size=n)
        steps = int(np.asarray(out.steps).sum())
        t = best_of(lambda: jf.evaluate(sc, sut=sut, chunk_size=n), args.repeats)
        rows.append((name, t, steps))

    sim_row("zero", zero_sut())
    for name in ("none", "carla-tm", "sensor-aeb"):
        sim_row(name, name)
    per = sim.LANES_PER
    try:  # the same batch run one scenario per lane (no refilling): outcomes identical
        sim.LANES_PER = 1
        sim._batch_program.cache_clear()
        for name in ("none", "carla-tm", "sensor-aeb"):
            sim_row(f"{name} 1/lane", name)
    finally:
        sim.LANES_PER = per
        sim._batch_program.cache_clear()
    ttc, rss = metrics.time_to_collision, metrics.rss_safe_distance
    try:  # ablations: the same program without one metric (outcomes change; timing only)
        metrics.time_to_collision = lambda *a, **k: jnp.float32(jnp.inf)
        sim_row("zero -ttc", zero_sut())
        metrics.time_to_collision = ttc
        metrics.rss_safe_distance = lambda *a, **k: jnp.float32(0.0)
        sim_row("zero -rss", zero_sut())
    finally:
        metrics.time_to_collision, metrics.rss_safe_distance = ttc, rss

    base = steps_mini / rows[0][1]
    print(f"{n:,} scenarios of the paper space; {jax.devices()[0].device_kind}, "
          f"{jax.device_count()} device(s), XLA CPU threads "
          f"{os.environ.get('NPROC', 'XLA default')}; best of {args.repeats}")
    print(f"{'model':<20}{'seconds':>9}{'steps':>12}{'M steps/s':>11}{'ns/step':>9}"
          f"{'x minimal':>11}")
    table = []
    for name, t, steps in rows:
        rate = steps / t
        print(f"{name:<20}{t:>9.3f}{steps:>12,}{rate / 1e6:>11.1f}{t / steps * 1e9:>9.2f}"
              f"{rate / base:>11.2f}")
        table.append({"model": name, "seconds": t, "episode_steps": steps,
                      "steps_per_second": rate, "ratio_to_minimal": rate / base})
    by = {r["model"]: r["seconds"] / r["episode_steps"] * 1e9 for r in table}
    print("per scenario-step [ns]: core (zero - minimal) "
          f"{by['zero'] - by['minimal']:.2f}; TTC {by['zero'] - by['zero -ttc']:.2f}; "
          f"RSS {by['zero'] - by['zero -rss']:.2f}; PID (none - zero) "
          f"{by['none'] - by['zero']:.2f}; Traffic Manager (carla-tm - none) "
          f"{by['carla-tm'] - by['none']:.2f}; sensor model (sensor-aeb - none) "
          f"{by['sensor-aeb'] - by['none']:.2f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"n": n, "repeats": args.repeats, "rows": table,
                                    "versions": versions(),
                                    "device": jax.devices()[0].device_kind,
                                    "xla_cpu_threads": os.environ.get("NPROC")}, indent=1)
                        + "\n")


if __name__ == "__main__":
    main()
