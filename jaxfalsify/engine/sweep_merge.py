"""A sweep's pieces put together: its chunks' rows files into one Parquet file, and the summary
parts of its processes (each sweeps a contiguous share of the scenario numbers) into
``summary.json``'s figures, per calibration."""

from __future__ import annotations

import math
from pathlib import Path

from jaxfalsify.base import config as cfg
from jaxfalsify.base.distributed import share
from jaxfalsify.engine.problem import fixed_sut_params
from jaxfalsify.engine.sweep_config import Calibrations, SweepConfig
from jaxfalsify.io import checkpoints
from jaxfalsify.io.files import atomic_path
from jaxfalsify.scenario.space import Space
from jaxfalsify.suts import registry as sut_lib

__all__ = ["read_part", "merge_summary", "merge_rows"]


def read_part(path: Path, i: int, sweep_id: str) -> dict:
    """Another process's summary part, its seal and identity verified."""
    doc = checkpoints.read_json(path)
    if doc.get("sweep") != sweep_id or doc.get("process_id") != i:
        raise checkpoints.CheckpointError(f"{path} belongs to another sweep or process")
    return doc


def merge_summary(space: Space, config: SweepConfig, calib: Calibrations, parts: list,
                   num_processes: int) -> dict:
    def merged(c):
        ts = [(q["totals"][c], q["process_id"]) for q in parts]
        rewards = [t["best_reward"] if t["best_reward"] is not None else -math.inf
                   for t, _ in ts]
        top = max(rewards)
        best = next(t for (t, _), r in zip(ts, rewards) if r == top)  # lowest process first
        n = sum(t["n"] for t, _ in ts)
        col = sum(t["collisions"] for t, _ in ts)
        viol = ({} if config.requirement == "collision" else
                {"n_violations": sum(t.get("violations", 0) for t, _ in ts),
                 "violation_rate": sum(t.get("violations", 0) for t, _ in ts) / max(n, 1)})
        return {"n_scenarios": n, "n_collisions": col, "collision_rate": col / max(n, 1),
                **viol,
                "n_nonfinite": sum(t["nonfinite"] for t, _ in ts),
                "global_max_reward": best["best_reward"],
                "global_max_ties": sum(t["best_ties"] for (t, _), r in zip(ts, rewards)
                                       if r == top),
                "global_max_scenario": best["best"]}

    def params(c):  # a parameter the space sets per scenario has no one value here
        return fixed_sut_params(sut_lib.params_dict(calib.instances[c]), space)

    rows = [merged(c) for c in range(calib.count)]
    summary = {"space": space.name, "space_seed": config.space_seed, "sut": config.sut,
               "seed": config.seed,
               **({"requirement": config.requirement,
                   "requirement_params": sut_lib.params_dict(config.requirement_of()[1])}
                  if config.requirement != "collision" else {})}
    if calib.count == 1:
        summary.update(rows[0])
        summary["sut_params"] = params(0)
    else:
        summary["calibrations"] = [{"calibration": c, **calib.describe(c), **r,
                                    "sut_params": params(c)} for c, r in enumerate(rows)]
        summary["n_calibrations"] = calib.count
        summary["n_scenarios"] = space.size
    summary.update({
        "processes": num_processes, "rows": config.rows,
        "parts": [] if config.rows == "none" else
        ([f"sweep.part-{i:05d}-of-{num_processes:05d}.parquet" for i in range(num_processes)
          if _nonempty_share(space.size, i, num_processes)]  # none for an empty share
         if num_processes > 1 else ["sweep.parquet"]),
        "versions": cfg.versions()})
    return summary


def _nonempty_share(n: int, process_id: int, num_processes: int) -> bool:
    begin, end = share(n, process_id, num_processes)
    return end > begin


def merge_rows(files: list[tuple[Path, dict | None]], final: Path) -> None:
    """Concatenate the chunks' Parquet files (each verified against its commit-record entry)
    into one, under a temporary name, then rename."""
    import io

    import pyarrow.parquet as pq

    with atomic_path(final) as part:
        writer = None
        try:
            for f, entry in files:
                table = pq.read_table(io.BytesIO(checkpoints.read_verified(f, entry)))
                if writer is None:
                    writer = pq.ParquetWriter(part, table.schema)
                writer.write_table(table)
        finally:
            if writer is not None:
                writer.close()
