"""Throughput of the host evaluator path: the worker pool against the ideal of its workers,
and the search's own cost per evaluation, side by side in one process.

    python experiments/bench_evaluators.py [--workers 2] [--batch 256] [--batches 8]

The evaluator (``experiments/external/busy_evaluator.py``) does about 1 ms of CPU work per
scenario, so ``workers`` processes can at best evaluate ``workers / 1 ms`` scenarios per
second. Rows: the pool alone on ``batches`` batches of ``batch`` scenarios (a warm pool: its
processes started before timing); the whole job (``jaxfalsify.jobs.evaluators.run``: the search
asking, the pool evaluating, a checkpoint per update) for ``random`` and the sample-efficient
``reinforce/screened``: evaluations per second of its loop (search + evaluation + checkpoint,
from the run's own clock) and the search's and the checkpoint's seconds per evaluation;
compiling the search and starting the workers are reported apart.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "external"))
from busy_evaluator import SECONDS_EACH  # noqa: E402

from jaxfalsify.jobs import evaluators, runs  # noqa: E402

SPEC = f"{HERE / 'external' / 'busy_evaluator.py'}:evaluate"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--json", type=Path)
    a = ap.parse_args(argv)
    ideal = a.workers / SECONDS_EACH
    out = {"workers": a.workers, "ideal_per_s": ideal}
    rng = np.random.default_rng(0)
    with evaluators.Pool(SPEC, workers=a.workers) as pool:
        pool.evaluate({"ped_speed": rng.uniform(1, 2, a.batch)})  # warm
        t = time.perf_counter()
        for _ in range(a.batches):
            pool.evaluate({"ped_speed": rng.uniform(1, 2, a.batch)})
        per_s = a.batch * a.batches / (time.perf_counter() - t)
    print(f"ideal ({a.workers} workers x 1 ms): {ideal:8.0f} evaluations/s")
    print(f"pool alone, batch {a.batch}:        {per_s:8.0f} evaluations/s "
          f"({per_s / ideal:.0%} of ideal)")
    out["pool_per_s"] = per_s
    for strategy, batch, n in (("random", a.batch, a.batch * a.batches),
                               ("reinforce/screened", 32, 32 * 16)):
        rc = runs.RunConfig(strategy=strategy, batch=batch, evaluations=n, evaluator=SPEC)
        with tempfile.TemporaryDirectory() as d:
            o = evaluators.run(rc, Path(d) / "run", workers=a.workers, figures=False)
        t = o.timing
        loop = t["search_seconds"] + t["evaluation_seconds"] + t["checkpoint_seconds"]
        print(f"job, {strategy:18s} batch {batch:4d}: {n / loop:8.0f} evaluations/s "
              f"({n / loop / ideal:.0%} of ideal) in the loop; per evaluation: search "
              f"{t['search_seconds'] / n * 1e3:.3f} ms, checkpoint "
              f"{t['checkpoint_seconds'] / n * 1e3:.3f} ms; start: compile "
              f"{t['compile_seconds']:.2f} s, workers {t['workers_start_seconds']:.2f} s")
        out[strategy] = {"batch": batch, "evaluations": n, "timing": t}
    if a.json:
        a.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
