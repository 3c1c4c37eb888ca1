"""Exhaustive sweep of a discrete logical scenario: every concrete scenario, evaluated in chunks.

The result is the ground truth that search strategies are measured against: every concrete
scenario's indices, values and outcome, streamed chunk by chunk to ``sweep.parquet`` (so memory
stays flat as the space grows), plus ``summary.json`` and the resolved ``config.toml``. Files
are written under temporary names and renamed at the end: an interrupted sweep leaves no
half-written result behind.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import time
from functools import partial
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify import sim
from jaxfalsify import sut as sut_lib
from jaxfalsify.space import Space

OUTCOME_FIELDS = tuple(f.name for f in dataclasses.fields(sim.Outcome))


DEFAULT_CHUNK = 1 << 17


def batch_sharding():
    """A ``NamedSharding`` splitting the batch axis over all local devices (None for one)."""
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.local_devices()
    if len(devices) == 1:
        return None
    return NamedSharding(Mesh(np.array(devices), ("batch",)), PartitionSpec("batch"))


def plan_chunks(size: int, chunk: int = DEFAULT_CHUNK) -> int:
    """Balanced chunk size: as few chunks as ``chunk`` allows, equal sizes, a multiple of the
    local device count (so the batch shards evenly)."""
    n_dev = jax.local_device_count()
    n_chunks = max(1, -(-size // chunk))
    per = -(-size // n_chunks)
    return -(-per // n_dev) * n_dev


@partial(jax.jit, static_argnames=("space", "sut", "world", "chunk", "sharding"))
def evaluate_chunk(start, *, space: Space, sut: sut_lib.SUT, world: sim.World = sim.WORLD,
                   chunk: int = DEFAULT_CHUNK, sharding=None):
    """Outcomes of the concrete scenarios numbered ``[start, start + chunk)`` (clamped to the
    space; rows past its end repeat the last scenario and must be dropped by the caller).
    With a ``sharding`` (see :func:`batch_sharding`) the batch is split over devices.

    Returns ``(indices (chunk, P) int32, Outcome with (chunk,) fields)``.
    """
    flat = jnp.minimum(start + jnp.arange(chunk, dtype=jnp.int32), space.size - 1)
    if sharding is not None:
        flat = jax.lax.with_sharding_constraint(flat, sharding)
    idx = space.unravel(flat)
    out, _ = sim.batch_rollout(space.scenario(idx), sut, world, False)
    return idx, out


def chunk_table(space: Space, begin: int, idx: np.ndarray, out) -> dict[str, np.ndarray]:
    """Host-side columns of one chunk: scenario number, indices, values, outcome fields."""
    n = idx.shape[0]
    cols: dict[str, np.ndarray] = {"scenario": np.arange(begin, begin + n, dtype=np.int64)}
    for p, name in enumerate(space.names):
        cols[f"{name}_idx"] = idx[:, p].astype(np.int32)
    for p, name in enumerate(space.names):
        cols[name] = space.values[p][idx[:, p]]
    for f in OUTCOME_FIELDS:
        cols[f] = np.asarray(getattr(out, f))[:n]
    return cols


def iter_sweep(space: Space, sut: sut_lib.SUT, world: sim.World = sim.WORLD,
               chunk: int = DEFAULT_CHUNK, start: int = 0):
    """Yield ``(begin, end, columns)`` for consecutive chunks of the space (host-side loop; each
    chunk is one call of the same compiled function, sharded over the local devices)."""
    chunk = plan_chunks(space.size, chunk)
    sharding = batch_sharding()
    for b, e in space.chunks(chunk, start):
        idx, out = evaluate_chunk(jnp.int32(b), space=space, sut=sut, world=world, chunk=chunk,
                                  sharding=sharding)
        idx = np.asarray(idx)[: e - b]
        yield b, e, chunk_table(space, b, idx, out)


class Reducer:
    """Running totals of a sweep: counts and the global maximum reward (first one on ties)."""

    def __init__(self):
        self.n = 0
        self.collisions = 0
        self.nonfinite = 0
        self.best_reward = -math.inf
        self.best_row: dict | None = None

    def add(self, cols: dict[str, np.ndarray]):
        self.n += len(cols["scenario"])
        self.collisions += int(np.sum(cols["collision"]))
        self.nonfinite += int(np.sum(cols["nonfinite"]))
        r = np.where(np.isnan(cols["reward"]), -np.inf, cols["reward"])
        i = int(np.argmax(r))
        if r[i] > self.best_reward:
            self.best_reward = float(r[i])
            self.best_row = {k: v[i].item() for k, v in cols.items()}


def run_sweep(space: Space, sut_name: str, out_dir: Path, *, world: sim.World = sim.WORLD,
              chunk: int = DEFAULT_CHUNK, progress: Callable[[int], None] | None = None,
              extra_config: dict | None = None) -> dict:
    """Sweep the whole space, stream rows to ``out_dir/sweep.parquet``; returns the summary."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from jaxfalsify import config as cfg

    sut = sut_lib.get(sut_name)
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp_parquet = out_dir / ".sweep.parquet.partial"
    writer = None
    red = Reducer()
    t0 = time.perf_counter()
    compile_s = 0.0
    try:
        for b, e, cols in iter_sweep(space, sut, world, chunk):
            if b == 0:
                compile_s = time.perf_counter() - t0
            table = pa.table(cols)
            if writer is None:
                writer = pq.ParquetWriter(tmp_parquet, table.schema)
            writer.write_table(table)
            red.add(cols)
            if progress:
                progress(e - b)
        wall = time.perf_counter() - t0
    finally:
        if writer is not None:
            writer.close()
    summary = {
        "space": space.name, "seed": space.seed, "sut": sut.name,
        "n_scenarios": red.n, "n_collisions": red.collisions,
        "collision_rate": red.collisions / max(red.n, 1),
        "n_nonfinite": red.nonfinite,
        "global_max_reward": red.best_reward,
        "global_max_scenario": _scenario_of(space, red.best_row),
        "wall_seconds": wall, "compile_seconds": compile_s,
        "chunk": plan_chunks(space.size, chunk), "devices": jax.local_device_count(),
        "versions": cfg.versions(),
    }
    config = {"command": "sweep", "space": space.describe(), "seed": space.seed,
              "sut": sut.name, "chunk": chunk, **(extra_config or {})}
    cfg.write_atomic(out_dir / "config.toml", cfg.dumps_toml(config))
    cfg.write_atomic(out_dir / "summary.json", json.dumps(cfg.jsonable(summary), indent=2) + "\n")
    os.replace(tmp_parquet, out_dir / "sweep.parquet")
    return summary


def _scenario_of(space: Space, row: dict | None) -> dict | None:
    if row is None:
        return None
    return {"scenario": row["scenario"],
            "indices": {n: row[f"{n}_idx"] for n in space.names},
            "values": {n: row[n] for n in space.names},
            **{f: row[f] for f in OUTCOME_FIELDS}}


def sweep_arrays(space: Space, sut="carla-tm", world: sim.World = sim.WORLD,
                 chunk: int = DEFAULT_CHUNK) -> dict[str, np.ndarray]:
    """The whole sweep in memory (small spaces, tests, ground truth for comparisons)."""
    parts = [cols for _, _, cols in iter_sweep(space, sut_lib.get(sut), world, chunk)]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
