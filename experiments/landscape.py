"""How much local structure leads to a suite space's failures: the evidence behind the search
targets that no strategy meets (README, 'The search benchmark suite').

For one swept space (its exhaustive sweep is the ground truth), two oracle measures that any
search moving by local steps is bound by:

* **Basins.** Steepest descent of the STL robustness (a collision counts below every near
  miss) over the axis neighbourhood of radius r (every parameter moved by up to r value steps,
  one at a time): the share of all scenarios whose descent ends in a collision. A searcher that
  follows the robustness downhill from a uniform start reaches a failure with about this
  probability; when it is near the collision share itself, the signal does not lead there.
* **Flood fill to the global maximum.** Best-first search started *at* a collision (chosen at
  random): expand the best scenario seen so far, evaluating every unseen axis neighbour within
  radius r, ranked like the default's signal (collisions first by reward, then lowest
  robustness). Counts the evaluations until the global maximum is evaluated (censored at
  ``--budget``). A learner that converges on good collisions needs at least this order of
  evaluations after its first collision.

    python experiments/landscape.py --space experiments/suite/aeb-2e4.toml --sut sensor-aeb \\
        --sut-param ttc_full=2.0 --sut-param ttc_partial=3.0

Prints a table and writes ``experiments/results/landscape/<space>.json``.
"""

from __future__ import annotations

import argparse
import heapq
import json
from pathlib import Path

import numpy as np


def axis_offsets(n_params: int, radius: int) -> list[tuple[int, int]]:
    """(parameter, step) pairs of the axis neighbourhood of ``radius``."""
    return [(d, s) for d in range(n_params) for s in range(-radius, radius + 1) if s]


def descent_basin_share(objective: np.ndarray, collision: np.ndarray, radius: int) -> float:
    """Share of scenarios whose steepest descent of ``objective`` (shape = the space's
    shape, lower is better) over the axis neighbourhood ends at a collision."""
    shape = objective.shape
    idx = np.arange(objective.size).reshape(shape)
    best, best_f = idx.copy(), objective.copy()
    for d, s in axis_offsets(len(shape), radius):
        src = [slice(None)] * len(shape)
        dst = [slice(None)] * len(shape)
        src[d] = slice(max(s, 0), shape[d] + min(s, 0))  # neighbour at x + s ...
        dst[d] = slice(max(-s, 0), shape[d] + min(-s, 0))  # ... seen from x
        nf = np.full(shape, np.inf)
        ni = idx.copy()
        nf[tuple(dst)] = objective[tuple(src)]
        ni[tuple(dst)] = idx[tuple(src)]
        better = nf < best_f
        best_f = np.where(better, nf, best_f)
        best = np.where(better, ni, best)
    nxt = best.reshape(-1)
    for _ in range(64):  # pointer doubling: 2^64 steps, past every descent's end
        nxt2 = nxt[nxt]
        if np.array_equal(nxt2, nxt):
            break
        nxt = nxt2
    return float(collision.reshape(-1)[nxt].mean())


def flood_fill_to_max(signal: np.ndarray, is_max: np.ndarray, start: int, radius: int,
                      budget: int) -> int | None:
    """Evaluations after ``start`` until a best-first axis-neighbourhood search (highest
    ``signal`` expanded first) evaluates a scenario with ``is_max``; None beyond ``budget``."""
    shape = signal.shape
    flat_sig, flat_max = signal.reshape(-1), is_max.reshape(-1)
    radix = np.cumprod((1,) + shape[::-1])[:-1][::-1]
    offsets = axis_offsets(len(shape), radius)
    seen, heap, n = {start}, [(-flat_sig[start], start)], 0
    if flat_max[start]:
        return 0
    while heap and n < budget:
        _, x = heapq.heappop(heap)
        ix = np.array(np.unravel_index(x, shape))
        for d, s in offsets:
            v = ix[d] + s
            if v < 0 or v >= shape[d]:
                continue
            y = int(x + s * radix[d])
            if y in seen:
                continue
            seen.add(y)
            n += 1
            if flat_max[y]:
                return n
            heapq.heappush(heap, (-flat_sig[y], y))
    return None


def main(argv=None) -> None:
    import jaxfalsify as jf
    from jaxfalsify.engine.truth import sweep_arrays

    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--space", required=True)
    ap.add_argument("--sut", default="sensor-aeb")
    ap.add_argument("--sut-param", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--radii", default="1,2,3")
    ap.add_argument("--starts", type=int, default=20, help="flood fills (random collisions)")
    ap.add_argument("--budget", type=int, default=4000)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "landscape")
    a = ap.parse_args(argv)
    sp = jf.load_space(a.space)
    sut_params = {k: float(v) for k, v in (s.split("=", 1) for s in a.sut_param)}
    g = sweep_arrays(sp, a.sut, sut_params, fields=("collision", "reward", "robustness"))
    shape = tuple(sp.shape)
    coll = g["collision"].reshape(shape)
    reward = np.nan_to_num(g["reward"], nan=-np.inf).reshape(shape)
    rob = np.nan_to_num(g["robustness"], nan=np.inf).reshape(shape)
    n_coll = int(coll.sum())
    if n_coll == 0:
        raise SystemExit(f"{sp.name}: no collision in the space")
    gmax = reward[coll].max()
    is_max = coll & (reward >= gmax - 1e-6)
    # the default's ranking: collisions first (by reward), then the lowest robustness
    signal = np.where(coll, 1e3 + reward, -rob)
    objective = -signal
    radii = [int(r) for r in a.radii.split(",")]
    rng = np.random.default_rng(0)
    starts = rng.choice(np.flatnonzero(coll.reshape(-1)), size=a.starts)
    result = {"space": sp.name, "sut": a.sut, "sut_params": sut_params,
              "scenarios": int(coll.size), "collisions": n_coll,
              "collision_share": n_coll / coll.size,
              "global_max": float(gmax), "global_max_ties": int(is_max.sum()), "radii": {}}
    print(f"{sp.name} x {a.sut}: {n_coll} collisions of {coll.size:,} (p = "
          f"{n_coll / coll.size:.2e}); global max {gmax:.4f} ({int(is_max.sum())} scenarios)")
    print("| radius | descent basins of the collisions (share of the space) | x p | "
          f"flood fill from a collision to the global max: median [IQR], found within "
          f"{a.budget} |")
    print("|---|---|---|---|")
    for r in radii:
        basin = descent_basin_share(objective, coll, r)
        fills = [flood_fill_to_max(signal, is_max, int(s), r, a.budget) for s in starts]
        cens = np.array([f if f is not None else a.budget + 1 for f in fills], np.float64)
        q = np.percentile(cens, [25, 50, 75])
        found = sum(f is not None for f in fills)
        result["radii"][str(r)] = {"basin_share": basin, "basin_over_p": basin * coll.size / n_coll,
                                   "flood_fill": fills,
                                   "flood_fill_median": float(q[1]),
                                   "flood_fill_found": found}
        print(f"| {r} | {basin:.2e} | {basin * coll.size / n_coll:.1f} | {q[1]:g} "
              f"[{q[0]:g}, {q[2]:g}], {found}/{len(fills)} |", flush=True)
    a.out.mkdir(parents=True, exist_ok=True)
    path = a.out / f"{sp.name}.json"
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
