"""What resumability costs: checkpointed vs plain, measured side by side in one process.

* sweep: ``run_sweep`` (every chunk committed to the checkpoint as its own Parquet file plus the
  running totals, merged into ``sweep.parquet`` at the end) against a plain streaming loop over
  the same compiled chunks into one ``ParquetWriter`` (what a non-resumable sweep would do);
* campaign: ``campaign.run`` with a checkpoint after every update (records, carry, state) against
  the same run without a checkpoint.

Each variant runs after a warm-up (compiled once), best of ``--repeats``; the ratios are the
figures to read, absolute times drift on shared machines.

    python experiments/bench_checkpoint.py [--space paper-extended] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

import jaxfalsify as jf
from jaxfalsify.base.config import versions
from jaxfalsify.engine import campaign, sweep_chunks, sweep_config
from jaxfalsify.io.checkpoints import CampaignCheckpoint
from jaxfalsify.jobs import runs, sweep
from jaxfalsify.suts import registry as sut_lib


def plain_sweep(sp, out: Path) -> None:
    writer = None
    calib = sweep_config.calibrations(sut_lib.resolve("carla-tm"), {})
    for _, _, cols in sweep_chunks.iter_sweep(sp, calib):
        table = pa.table(cols)
        if writer is None:
            writer = pq.ParquetWriter(out / "sweep.parquet", table.schema)
        writer.write_table(table)
    writer.close()


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--space", default="paper-extended")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results"
                    / "bench_checkpoint.json")
    args = ap.parse_args()
    sp = jf.load_space(args.space)
    tmp = Path(tempfile.mkdtemp())

    def fresh(name):
        d = tmp / name
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir()
        return d

    plain_sweep(sp, fresh("warm"))  # compile once
    t_plain = best_of(lambda: plain_sweep(sp, fresh("plain")), args.repeats)
    cfg = sweep_config.SweepConfig(space=args.space)
    t_ckpt = best_of(lambda: sweep.execute(cfg, fresh("ckpt"), force=True), args.repeats)

    b = runs.RunConfig(evaluations=20_000, batch=250, checkpoint_every=1).build()
    plan = b.plan  # 80 updates, a checkpoint after each
    go = lambda **kw: campaign.run(b.space, b.sut, b.sut_params, b.strategy,  # noqa: E731
                                   b.strategy_params, plan, 0, **kw)
    go()  # compile once

    def with_ckpt():
        go(checkpoint=CampaignCheckpoint(fresh("run") / "checkpoint", {"bench": 1}))

    r_plain = best_of(go, args.repeats)
    r_ckpt = best_of(with_ckpt, args.repeats)
    shutil.rmtree(tmp, ignore_errors=True)

    result = {
        "space": sp.name, "n_scenarios": sp.size, "repeats": args.repeats,
        "sweep_plain_seconds": t_plain, "sweep_checkpointed_seconds": t_ckpt,
        "sweep_ratio": t_ckpt / t_plain,
        "campaign": "reinforce/default, batch 250, 80 updates, checkpoint every update",
        "campaign_plain_seconds": r_plain, "campaign_checkpointed_seconds": r_ckpt,
        "campaign_ratio": r_ckpt / r_plain,
        "milliseconds_per_checkpoint": (r_ckpt - r_plain) / plan.n_chunks * 1e3,
        "versions": versions(),
    }
    print(f"sweep {sp.name} ({sp.size} scenarios, rows to Parquet): plain {t_plain:.2f} s, "
          f"checkpointed + merged {t_ckpt:.2f} s -> x{t_ckpt / t_plain:.2f}")
    print(f"campaign (80 updates x 250): plain {r_plain:.2f} s, checkpoint every update "
          f"{r_ckpt:.2f} s -> x{r_ckpt / r_plain:.2f}, "
          f"{(r_ckpt - r_plain) / plan.n_chunks * 1e3:.1f} ms per checkpoint")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
