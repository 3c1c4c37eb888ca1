"""Exhaustive sweep of a discrete logical scenario: every concrete scenario, evaluated in chunks.

The result is the ground truth that search strategies are measured against: every concrete
scenario's indices, values and outcome in ``sweep.parquet``, plus ``summary.json`` (bit-identical
for the same space, seed and SUT whatever the chunk size), ``timing.json`` and the resolved
``config.toml`` (written first).

Each chunk is committed to ``checkpoint/`` as it finishes (its rows as ``rows-<c>.parquet``, then
the running totals in ``state.json``; see :mod:`jaxfalsify.checkpoint`), so memory stays flat and
an interrupted sweep — Ctrl-C, SIGKILL, a lost machine — resumes where it stopped
(``jaxfalsify sweep --resume OUT``). At the end the chunk files are merged into ``sweep.parquet``
under a temporary name and renamed, and the checkpoint is removed: no half-written result is
ever left under a final name.
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
    """Sharding of a sweep chunk over the local devices (see ``sim.local_batch_sharding``)."""
    return sim.local_batch_sharding()


def plan_chunks(size: int, chunk: int = DEFAULT_CHUNK) -> int:
    """Balanced chunk size: as few chunks as ``chunk`` allows, about equal sizes, rounded up
    to a multiple of 256 x the local device count — the batch shards evenly, and XLA's CPU
    loops vectorise fully (an odd batch such as 129,871 ran 4x slower than 130,048)."""
    align = 256 * jax.local_device_count()
    n_chunks = max(1, -(-size // chunk))
    per = -(-size // n_chunks)
    return -(-per // align) * align


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
               chunk: int = DEFAULT_CHUNK, start: int = 0, stop: int | None = None,
               planned: int | None = None):
    """Yield ``(begin, end, columns)`` for consecutive chunks of scenarios ``[start, stop)``
    (host-side loop; each chunk is one call of the same compiled function, sharded over the
    local devices). ``planned`` fixes the compiled chunk size (default: planned from
    ``chunk`` and the range)."""
    stop = space.size if stop is None else stop
    chunk = planned or plan_chunks(max(stop - start, 1), chunk)
    sharding = batch_sharding()
    for b in range(start, stop, chunk):
        e = min(b + chunk, stop)
        idx, out = evaluate_chunk(jnp.int32(b), space=space, sut=sut, world=world, chunk=chunk,
                                  sharding=sharding)
        idx = np.asarray(idx)[: e - b]
        yield b, e, chunk_table(space, b, idx, out)


class Reducer:
    """Running totals of a sweep: counts and the global maximum reward (first one on ties)."""

    FIELDS = ("n", "collisions", "nonfinite", "best_reward", "best_row")

    def __init__(self, **state):
        self.n = 0
        self.collisions = 0
        self.nonfinite = 0
        self.best_reward = -math.inf
        self.best_row: dict | None = None
        for k, v in state.items():
            setattr(self, k, v)

    def state(self) -> dict:
        return {k: getattr(self, k) for k in self.FIELDS}

    def add(self, cols: dict[str, np.ndarray]):
        self.n += len(cols["scenario"])
        self.collisions += int(np.sum(cols["collision"]))
        self.nonfinite += int(np.sum(cols["nonfinite"]))
        r = np.where(np.isnan(cols["reward"]), -np.inf, cols["reward"])
        i = int(np.argmax(r))
        if r[i] > self.best_reward:
            self.best_reward = float(r[i])
            self.best_row = {k: v[i].item() for k, v in cols.items()}


def checkpoint_name(process_id: int = 0, num_processes: int = 1) -> str:
    return ("checkpoint" if num_processes == 1 else
            f"checkpoint-part-{process_id:05d}-of-{num_processes:05d}")


def sweep_config(space: Space, sut_name: str, chunk: int, rows: str, num_processes: int,
                 extra: dict | None = None) -> dict:
    """What ``config.toml`` of a sweep holds (and ``--resume`` reads back)."""
    return {"command": "sweep", "space": space.describe(), "seed": space.seed,
            "sut": sut_name, "chunk": chunk, "processes": num_processes, "rows": rows,
            **(extra or {})}


def _layout(space: Space, sut_name: str, out_dir: Path, chunk: int, rows: str,
            process_id: int, num_processes: int, world: sim.World):
    """This process's range, compiled chunk size, checkpoint folder and its fingerprint."""
    from jaxfalsify.distributed import share

    begin, end = share(space.size, process_id, num_processes)
    planned = plan_chunks(max(end - begin, 1), chunk)
    fingerprint = json.loads(json.dumps(
        {"space": space.describe(), "seed": space.seed, "sut": sut_name, "chunk": planned,
         "rows": rows, "range": [begin, end], "world": repr(world)}))
    return begin, end, planned, out_dir / checkpoint_name(process_id, num_processes), fingerprint


def check_resume(space: Space, sut_name: str, out_dir: Path, chunk: int, rows: str,
                 process_id: int = 0, num_processes: int = 1,
                 world: sim.World = sim.WORLD) -> int:
    """Scenarios this process has committed in ``out_dir``'s checkpoint (0 if none); raises
    :class:`~jaxfalsify.checkpoint.CheckpointError` if the checkpoint is unusable."""
    begin, end, planned, ck, fp = _layout(space, sut_lib.get(sut_name).name, out_dir, chunk,
                                          rows, process_id, num_processes, world)
    if not (ck / "state.json").exists():
        return 0
    done, _ = _load_progress(ck, fp)
    return min(done * planned, end - begin)


def _load_progress(ck: Path, fingerprint: dict) -> tuple[int, Reducer]:
    from jaxfalsify.checkpoint import CheckpointError, read_json

    st = read_json(ck / "state.json")
    if st.get("fingerprint") != fingerprint:
        raise CheckpointError(f"checkpoint {ck / 'state.json'} was written by another sweep "
                              "configuration")
    try:
        done = int(st["chunks_done"])
        red = Reducer(**{k: st["totals"][k] for k in Reducer.FIELDS})
    except (KeyError, TypeError, ValueError):
        raise CheckpointError(f"checkpoint {ck / 'state.json'} is corrupt (fields)") from None
    return done, red


def run_sweep(space: Space, sut_name: str, out_dir: Path, *, world: sim.World = sim.WORLD,
              chunk: int = DEFAULT_CHUNK, progress: Callable[[int], None] | None = None,
              extra_config: dict | None = None, process_id: int = 0,
              num_processes: int = 1, rows: str = "all", resume: bool = False) -> dict:
    """Sweep the whole space into ``out_dir``; returns the summary (plus timing).

    ``rows`` selects what goes to Parquet: ``all`` scenarios, only ``collisions``, or ``none``
    (summary only, for huge spaces). With ``resume``, the chunks already committed to the
    checkpoint are skipped (a missing checkpoint starts from the beginning); without it, an
    existing checkpoint is discarded.

    With several processes (``jax.distributed`` initialised), process i sweeps its contiguous
    share of the scenario numbers into ``sweep.part-<i>-of-<n>.parquet`` with its own
    checkpoint; after a barrier, process 0 merges the parts' summaries into ``summary.json``.
    """
    if rows not in ("all", "collisions", "none"):
        raise ValueError(f"rows must be all, collisions or none (got {rows!r})")
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    from jaxfalsify import config as cfg
    from jaxfalsify.checkpoint import write_json, FORMAT
    from jaxfalsify.distributed import barrier

    sut = sut_lib.get(sut_name)
    out_dir.mkdir(parents=True, exist_ok=True)
    multi = num_processes > 1
    name = (f"sweep.part-{process_id:05d}-of-{num_processes:05d}.parquet" if multi
            else "sweep.parquet")
    begin, end, planned, ck, fingerprint = _layout(space, sut.name, out_dir, chunk, rows,
                                                   process_id, num_processes, world)
    if process_id == 0 and not resume:
        cfg.write_atomic(out_dir / "config.toml", cfg.dumps_toml(
            sweep_config(space, sut.name, chunk, rows, num_processes, extra_config)))
    done, red = 0, Reducer()
    if resume and (ck / "state.json").exists():
        done, red = _load_progress(ck, fingerprint)
    elif ck.exists():
        shutil.rmtree(ck)
    ck.mkdir(parents=True, exist_ok=True)
    resumed_from = min(begin + done * planned, end)
    if progress and resumed_from > begin:
        progress(resumed_from - begin)
    t0 = time.perf_counter()
    compile_s = 0.0
    for c, (b, e, cols) in enumerate(iter_sweep(space, sut, world, chunk, resumed_from, end,
                                                planned=planned), start=done):
        if not compile_s:
            compile_s = time.perf_counter() - t0
        red.add(cols)
        if rows != "none":
            if rows == "collisions":
                keep = cols["collision"]
                cols = {k: v[keep] for k, v in cols.items()}
            tmp = ck / f".rows-{c:06d}.parquet.partial"
            pq.write_table(pa.table(cols), tmp)
            os.replace(tmp, ck / f"rows-{c:06d}.parquet")
        write_json(ck / "state.json", {"format": FORMAT, "chunks_done": c + 1,
                                       "scenarios_done": e - begin,
                                       "fingerprint": fingerprint, "totals": red.state()})
        if progress:
            progress(e - b)
    wall = time.perf_counter() - t0
    n_chunks = -(-(end - begin) // planned)
    if rows != "none":
        _merge_rows([ck / f"rows-{c:06d}.parquet" for c in range(n_chunks)],
                    out_dir / f".{name}.partial", out_dir / name)
    part = {"process_id": process_id, "n": red.n, "collisions": red.collisions,
            "nonfinite": red.nonfinite, "best_reward": red.best_reward,
            "best": _scenario_of(space, red.best_row), "wall": wall, "compile": compile_s}
    if multi:
        cfg.write_atomic(out_dir / f".summary.part-{process_id:05d}.json",
                         json.dumps(cfg.jsonable(part)) + "\n")
        barrier("jaxfalsify-sweep-parts-written")
        parts = [json.loads((out_dir / f".summary.part-{i:05d}.json").read_text())
                 for i in range(num_processes)]
    else:
        parts = [cfg.jsonable(part)]
    best = max(parts, key=lambda q: (q["best_reward"] if q["best_reward"] is not None
                                     else -math.inf, -q["process_id"]))
    n = sum(q["n"] for q in parts)
    collisions = sum(q["collisions"] for q in parts)
    summary = {
        "space": space.name, "seed": space.seed, "sut": sut.name,
        "n_scenarios": n, "n_collisions": collisions,
        "collision_rate": collisions / max(n, 1),
        "n_nonfinite": sum(q["nonfinite"] for q in parts),
        "global_max_reward": best["best_reward"],
        "global_max_scenario": best["best"],
        "processes": num_processes,
        "rows": rows,
        "parts": [] if rows == "none" else
        ([f"sweep.part-{i:05d}-of-{num_processes:05d}.parquet" for i in range(num_processes)]
         if multi else ["sweep.parquet"]),
        "versions": cfg.versions(),
    }
    timing = {"wall_seconds": max(q["wall"] for q in parts),
              "compile_seconds": max(q["compile"] for q in parts),
              "chunk": planned, "devices": jax.local_device_count(),
              "resumed_from_scenario": resumed_from - begin if process_id == 0 else None}
    if process_id == 0:
        cfg.write_atomic(out_dir / "timing.json", json.dumps(cfg.jsonable(timing), indent=2)
                         + "\n")
        cfg.write_atomic(out_dir / "summary.json",
                         json.dumps(cfg.jsonable(summary), indent=2) + "\n")
    if multi:
        barrier("jaxfalsify-sweep-summary-written")
    shutil.rmtree(ck, ignore_errors=True)
    return {**summary, **timing}


def _merge_rows(files: list[Path], tmp: Path, final: Path) -> None:
    """Concatenate the chunks' Parquet files into one, under a temporary name, then rename."""
    import pyarrow.parquet as pq

    from jaxfalsify.checkpoint import CheckpointError

    writer = None
    try:
        for f in files:
            if not f.exists():
                raise CheckpointError(f"checkpoint file {f} is missing")
            table = pq.read_table(f)
            if writer is None:
                writer = pq.ParquetWriter(tmp, table.schema)
            writer.write_table(table)
    except BaseException:
        if writer is not None:
            writer.close()
        tmp.unlink(missing_ok=True)
        raise
    writer.close()
    os.replace(tmp, final)


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
