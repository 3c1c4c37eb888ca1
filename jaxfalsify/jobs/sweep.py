"""Exhaustive sweep of a discrete logical scenario: every concrete scenario, evaluated in chunks.

One concern: the exhaustive-sweep job; its configuration, chunks, totals
and merging are in the ``sweep_*`` modules.

The result is the ground truth that search strategies are measured against: every concrete
scenario's indices, values and outcome in ``sweep.parquet``, plus ``summary.json`` (bit-identical
for the same space, seed and SUT whatever the chunk size), ``timing.json`` and the resolved
``config.toml`` (written first).

A *calibration sweep* gives SUT parameters several values (``sut_params={"ttc_full": [0.8,
1.0, 1.2]}``): every combination of values is a calibration, and each chunk evaluates all
calibrations x its scenarios in one compiled call (``vmap`` over the parameter pytree). Rows
then carry a ``calibration`` number and a column per swept parameter, and ``summary.json`` a
row per calibration.

Each chunk is committed to ``checkpoint/`` as it finishes (its rows as ``rows-<c>.parquet``, then
the running totals in ``state.json``), so memory stays flat and an interrupted sweep — Ctrl-C,
SIGKILL, a lost machine — resumes where it stopped. At the end the chunk files are merged into
``sweep.parquet`` under a temporary name and renamed, and the checkpoint is removed.

This module runs a sweep into its folder (:func:`execute`: the checkpoint, resume and closing
lines) from its parts: :mod:`jaxfalsify.engine.sweep_config` (the configuration and its
calibrations), :mod:`jaxfalsify.engine.sweep_chunks` (the compiled chunks),
:mod:`jaxfalsify.engine.sweep_totals` (the running totals) and
:mod:`jaxfalsify.engine.sweep_merge` (rows files and processes' parts put together).
:mod:`jaxfalsify.engine.truth` sweeps a space in memory instead, and keeps its ground truth in the
per-user cache.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from jaxfalsify.base import config as cfg
from jaxfalsify.base.distributed import agree, barrier, share
from jaxfalsify.base.progress import Clock, Progress, timing_line
from jaxfalsify.core import sim
from jaxfalsify.engine.lifecycle import Status, sut_raised
from jaxfalsify.engine.problem import check_space_sut
from jaxfalsify.engine.sweep_chunks import (
    OUTCOME_FIELDS,
    check_columns,
    check_sweepable,
    iter_sweep,
    plan_chunks,
    violated_fn,
)
from jaxfalsify.engine.sweep_config import Calibrations, SweepConfig, default_out
from jaxfalsify.engine.sweep_merge import merge_rows, merge_summary, read_part
from jaxfalsify.engine.sweep_totals import Reducer, fold
from jaxfalsify.io import cache, checkpoints, store
from jaxfalsify.io.files import sha256, write_atomic, write_json, write_parquet
from jaxfalsify.scenario.space import Space
from jaxfalsify.suts import registry as sut_lib


def summary_lines(s: dict) -> list[str]:
    """What a finished sweep found, in words (``jaxfalsify sweep``'s closing lines), from
    :func:`execute`'s result ``s``: per calibration the collisions and the global maximum
    with its first scenario, the wall time and the files written."""

    lines = []
    for r in s.get("calibrations") or [s]:
        label = ("calibration " + ", ".join(f"{k}={r[k]:g}" for k in r  # the swept ones
                                            if k in r.get("sut_params", {})) + ": "
                 if "calibration" in r else "")
        head = (f"{label}{r['n_scenarios']:,} scenarios, {r['n_collisions']:,} collisions "
                f"({r['collision_rate']:.3g}); ")
        if "n_violations" in r:
            head += (f"{r['n_violations']:,} violations of {s.get('requirement')} "
                     f"({r['violation_rate']:.3g}); ")
        if r["global_max_reward"] is None:
            lines.append(head + f"no finite reward: all {r['n_nonfinite']:,} rollouts "
                         "non-finite (the SUT returned NaN or inf)")
            continue
        best = r["global_max_scenario"] or {}
        lines.append(head + f"global maximum reward {r['global_max_reward']:.4f} reached by "
                     f"{r['global_max_ties']} scenario(s), first at "
                     + ", ".join(f"{k}={v:g}" for k, v in best.get("values", {}).items()))
    lines.append(f"wall time {timing_line(s)}")
    lines.append(f"wrote {s['out']}/"
                 f"{', '.join(s['parts'] + ['summary.json', 'timing.json', 'config.toml'])}")
    return lines


def checkpoint_name(process_id: int = 0, num_processes: int = 1) -> str:
    return ("checkpoint" if num_processes == 1 else
            f"checkpoint-part-{process_id:05d}-of-{num_processes:05d}")


def _layout(config: SweepConfig, space: Space, calib: Calibrations, out: Path,
            process_id: int, num_processes: int, world: sim.World):
    """This process's range, compiled chunk size, checkpoint folder and its fingerprint."""

    begin, end = share(space.size, process_id, num_processes)
    planned = plan_chunks(max(end - begin, 1), max(256, config.chunk // calib.count))
    fingerprint = json.loads(json.dumps(
        {"config": config.to_toml(space, num_processes), "chunk": planned,
         "calibrations": cfg.jsonable([sut_lib.params_dict(p) for p in calib.instances]),
         "range": [begin, end], "world": repr(world),
         "code": cache.source_hash(calib.sut.act, calib.sut.init)}))
    return begin, end, planned, out / checkpoint_name(process_id, num_processes), fingerprint


def _chunk_range(c: int, begin: int, end: int, planned: int) -> list[int]:
    return [begin + c * planned, min(begin + (c + 1) * planned, end)]


def _load_progress(ck: Path, fingerprint: dict, n_calib: int, begin: int, end: int,
                   planned: int, rows: str) -> tuple[int, list[Reducer], dict]:
    """``(chunks done, totals, files)`` of a sweep checkpoint, its commit record's seal and
    fingerprint and every rows file's hash and identity verified."""
    where = ck / "state.json"
    st = checkpoints.read_json(where)
    if st.get("fingerprint") != fingerprint:
        raise checkpoints.CheckpointError(f"checkpoint {where} was written by another sweep "
                                          "configuration or code (the SUT's or jaxfalsify's "
                                          "source changed?)")
    try:
        done = int(st["chunks_done"])
        reds = [Reducer(**{k: t[k] for k in Reducer.FIELDS}) for t in st["totals"]]
        files = dict(st["files"])
    except (KeyError, TypeError, ValueError):
        raise checkpoints.CheckpointError(f"checkpoint {where} is corrupt (fields)") from None
    n_chunks = -(-(end - begin) // planned)
    scenarios = min(done * planned, end - begin)
    if (len(reds) != n_calib or not 0 <= done <= n_chunks
            or st.get("scenarios_done") != scenarios
            or any(r.n != scenarios for r in reds)):
        raise checkpoints.CheckpointError(f"checkpoint {where} is inconsistent (chunks or "
                                          "totals)")
    ident = checkpoints.identity(fingerprint)
    for c in range(done if rows != "none" else 0):
        name = f"rows-{c:06d}.parquet"
        entry = files.get(name)
        if entry is not None and (entry.get("chunk") != c or entry.get("run") != ident
                                  or entry.get("range") != _chunk_range(c, begin, end, planned)):
            raise checkpoints.CheckpointError(f"checkpoint file {ck / name}: its record "
                                              "names another chunk or sweep")
        checkpoints.read_verified(ck / name, entry)
    if rows == "all" and done:  # the totals must be what the verified rows add up to
        import pyarrow.parquet as pq

        again = [Reducer() for _ in range(n_calib)]
        for c in range(done):
            cols = {k: np.asarray(v) for k, v in
                    pq.read_table(ck / f"rows-{c:06d}.parquet").to_pydict().items()}
            n = len(cols["scenario"]) // n_calib
            for i, red in enumerate(again):
                red.add({k: v[i * n:(i + 1) * n] for k, v in cols.items()})
        for red, got in zip(again, reds):
            same = (red.n, red.collisions, red.nonfinite, red.best_ties) == \
                (got.n, got.collisions, got.nonfinite, got.best_ties) and \
                red.best_reward == got.best_reward and _same_row(red.best_row, got.best_row)
            if not same:
                raise checkpoints.CheckpointError(f"checkpoint {where}: its totals disagree "
                                                  "with its rows files (edited)")
    return done, reds, files


def _same_row(a: dict | None, b: dict | None) -> bool:
    """Two best rows hold the same values: one recounted from a rows file (float32 columns
    read back as float64), one from the commit record (JSON: NaN as null)."""
    if a is None or b is None:
        return a is b
    if set(a) != set(b):
        return False
    for k in a:
        x, y = a[k], b[k]
        if isinstance(x, (bool, str)) or isinstance(y, (bool, str)):
            if x != y:
                return False
            continue
        x = math.nan if x is None else float(x)
        y = math.nan if y is None else float(y)
        if not (math.isnan(x) and math.isnan(y) or x == y
                or abs(x - y) <= 1e-6 * max(1.0, abs(x))):  # float32 read as float64
            return False
    return True


def _scenario_of(space: Space, row: dict | None) -> dict | None:
    if row is None:
        return None
    return {"scenario": row["scenario"],
            "indices": {n: row[f"{n}_idx"] for n in space.names},
            "values": {n: row[n] for n in space.names},
            **{f: row[f] for f in OUTCOME_FIELDS}}


def execute(config: SweepConfig, out: Path | str | None = None, *, resume: bool = False,
            force: bool = False, progress: Progress | None = None,
            stop: Callable[[], bool] | None = None, process_id: int = 0,
            num_processes: int = 1, world: sim.World = sim.WORLD,
            startup_seconds: float = 0.0) -> dict:
    """Sweep the whole space into ``out``; the library form of ``jaxfalsify sweep``. Returns
    the summary (plus timing).

    ``resume`` continues the unfinished sweep in ``out`` (chunks already committed are
    skipped); ``stop`` is checked between chunks (see :func:`jaxfalsify.jobs.runs.execute`).
    With several processes (``jax.distributed`` initialised), process i sweeps its contiguous
    share of the scenario numbers into ``sweep.part-<i>-of-<n>.parquet`` with its own
    checkpoint; after a barrier, process 0 merges the parts' summaries into ``summary.json``.
    """
    cfg.check_type(config, SweepConfig, "config")

    clock = Clock(startup_seconds)
    progress = progress or Progress()
    space, calib = config.build()
    out = Path(out) if out is not None else default_out(space, config.sut, config.space_seed)
    config = config.resolved()
    check_sweepable(space)

    check_space_sut(space, calib.sut, dict(config.sut_params))
    check_columns(space, calib)
    rows_bytes = 0 if config.rows == "none" else (  # host-side columns of one chunk
        max(256, config.chunk // calib.count) * calib.count
        * (len(space.shape) * 2 + len(OUTCOME_FIELDS) + 4) * 16)
    rollouts = max(config.chunk, 256 * calib.count)  # one call's (iter_sweep's floor of 256)
    work_bytes = rollouts * 2048 if jax.default_backend() == "cpu" else 0  # else on the GPU
    cfg.check_memory(rows_bytes + work_bytes, f"a sweep chunk of {rollouts} rollouts",
                     "lower --chunk")

    agree("sweep configuration", sha256("\n".join(  # the SUT by its code, not its path
        [ln for ln in config.to_toml(space, num_processes).splitlines()
         if not ln.startswith("sut = ")]
        + [cache.source_hash(calib.sut.act, calib.sut.init)]).encode()))
    existed = out.exists()
    lk = store.open_folder(out, "sweep", force=force, resume=resume,
                           name=".lock" if process_id == 0 else f".lock-part-{process_id:05d}")
    try:
        barrier("jaxfalsify-sweep-checked")  # every process checked the folder before writes
        return _execute(config, out, space, calib, lk, resume=resume, force=force,
                        progress=progress, stop=stop, process_id=process_id,
                        num_processes=num_processes, world=world, clock=clock)
    except BaseException as e:
        if num_processes == 1 and not resume and (sut_raised(e) or store.nothing_written(out)):
            store.discard(out, "sweep", lk, existed)  # SUT raised / nothing written
        elif process_id == 0 and (out / "config.toml").exists() and \
                not isinstance(e, (store.Interrupted, ValueError)):
            Status(out, "sweep").failed(e)
        raise
    finally:
        lk.release()


def _execute(config: SweepConfig, out: Path, space: Space, calib: Calibrations,
             lk: store.FolderLock, *, resume: bool, force: bool, progress: Progress, stop,
             process_id: int, num_processes: int, world: sim.World, clock: Clock) -> dict:

    if resume:
        on_disk, procs = SweepConfig.from_toml(out / "config.toml")
        if procs != num_processes:
            raise store.FolderError(f"--resume {out}: the sweep ran on {procs} process(es), "
                                    f"this is {num_processes}; resume it with the same number")
        if on_disk.to_toml(space, procs) != config.to_toml(space, procs):
            raise checkpoints.CheckpointError(f"--resume {out}: config.toml does not match "
                                              "the sweep configuration given")
    multi = num_processes > 1
    name = (f"sweep.part-{process_id:05d}-of-{num_processes:05d}.parquet" if multi
            else "sweep.parquet")
    begin, end, planned, ck, fingerprint = _layout(config, space, calib, out, process_id,
                                                   num_processes, world)
    done, reds, files = 0, [Reducer() for _ in range(calib.count)], {}
    if resume:
        checkpoints.check_checkpoint_folder(ck)
    if resume and (ck / "state.json").exists():
        done, reds, files = _load_progress(ck, fingerprint, calib.count, begin, end, planned,
                                           config.rows)
    ident = checkpoints.identity(fingerprint)
    lk.claim("sweep")
    if process_id == 0 and not resume:
        if force:
            store.set_aside(out, "sweep")
        out.mkdir(parents=True, exist_ok=True)
        write_atomic(out / "config.toml", config.to_toml(space, num_processes))
    barrier("jaxfalsify-sweep-started")
    out.mkdir(parents=True, exist_ok=True)
    if not resume and ck.exists():
        shutil.rmtree(ck)
    ck.mkdir(parents=True, exist_ok=True)
    status = Status(out, "sweep")
    if process_id == 0:
        status.running(scenarios=space.size)
    resumed_from = min(begin + done * planned, end)
    total = (end - begin) * calib.count
    progress.phase(f"compiling the sweep of {space.name} x {config.sut}"
                   + (f" x {calib.count} calibrations" if calib.count > 1 else ""))
    t0 = time.perf_counter()
    compile_s, started = 0.0, False
    req, req_params = config.requirement_of()
    violated = None if req is None else violated_fn(req)
    try:
        # totals computed on the device (a requirement's violations: on the host, from rows)
        reduced = config.rows == "none" and req is None
        for c, (b, e, cols) in enumerate(iter_sweep(space, calib, world, config.chunk,
                                                    resumed_from, end, planned=planned,
                                                    key=sim.seed_key_data(config.seed),
                                                    reduced=reduced),
                                         start=done):
            if not started:
                compile_s = time.perf_counter() - t0
                progress.start(total, (resumed_from - begin) * calib.count, "scn",
                               f"sweep {space.name} / {config.sut}"
                               + (f" [process {process_id}/{num_processes}]" if multi else ""))
                started = True
            if violated is not None:
                cols["violated"] = violated(cols, req_params)
            fold(reds, space, calib, b, e, cols, reduced)
            if config.rows != "none":
                if config.rows == "collisions":  # the critical rows
                    keep = cols["violated"] if violated is not None else cols["collision"]
                    cols = {k: v[keep] for k, v in cols.items()}
                rows_file = f"rows-{c:06d}.parquet"
                files[rows_file] = {"sha256": write_parquet(ck / rows_file, cols),
                                    "chunk": c, "range": [b, e], "run": ident}
            checkpoints.write_commit(ck / "state.json", {"chunks_done": c + 1,
                                                         "scenarios_done": e - begin,
                                                         "fingerprint": fingerprint,
                                                         "totals": [r.state() for r in reds],
                                                         "files": files})
            hits = sum(r.collisions for r in reds)
            progress.update((e - begin) * calib.count, collisions=f"{hits:,}",
                            rate=f"{hits / max(1, sum(r.n for r in reds)):.3g}")
            if stop is not None and stop() and e < end:
                raise KeyboardInterrupt
    except KeyboardInterrupt:
        progress.close()
        st = (checkpoints.read_json(ck / "state.json") if (ck / "state.json").exists()
              else {})
        n_done = int(st.get("scenarios_done", 0))
        if process_id == 0:
            status.interrupted(scenarios_done=n_done, scenarios=space.size)
        raise store.Interrupted("sweep", out, n_done, end - begin, "scenarios") from None
    progress.close()
    search_s = time.perf_counter() - t0 - compile_s
    clock.add("compile", compile_s)
    clock.add("sweep", search_s)
    with clock("writing"):
        n_chunks = -(-(end - begin) // planned)
        if config.rows != "none" and n_chunks:  # an empty share writes no part file
            merge_rows([(ck / f"rows-{c:06d}.parquet", files.get(f"rows-{c:06d}.parquet"))
                         for c in range(n_chunks)], out / name)
        part = {"process_id": process_id,
                "totals": [{"n": r.n, "collisions": r.collisions, "nonfinite": r.nonfinite,
                            "violations": r.violations,
                            "best_reward": r.best_reward, "best_ties": r.best_ties,
                            "best": _scenario_of(space, r.best_row)} for r in reds],
                "clock": clock.summary()}
        if multi:
            checkpoints.write_commit(out / f".summary.part-{process_id:05d}.json",
                                     {**part, "sweep": checkpoints.identity(
                                         config.to_toml(space, num_processes))})
            barrier("jaxfalsify-sweep-parts-written")
            parts = [read_part(out / f".summary.part-{i:05d}.json", i,
                                checkpoints.identity(config.to_toml(space, num_processes)))
                     for i in range(num_processes)]
        else:
            parts = [cfg.jsonable(part)]
        summary = merge_summary(space, config, calib, parts, num_processes)
    timing = {**clock.summary(), "chunk": planned, "devices": jax.local_device_count(),
              "resumed_from_scenario": resumed_from - begin}
    if process_id == 0:
        write_json(out / "timing.json", timing, indent=2)
        write_json(out / "summary.json", summary, indent=2)
        status.complete(scenarios=space.size)
    if multi:
        barrier("jaxfalsify-sweep-summary-written")
        if process_id == 0:  # every process has read the parts (before the barrier)
            for i in range(num_processes):
                (out / f".summary.part-{i:05d}.json").unlink(missing_ok=True)
    shutil.rmtree(ck, ignore_errors=True)
    return {**summary, **timing, "out": str(out)}


def resume_config(out: Path | str) -> tuple[SweepConfig, int]:
    """``(config, processes)`` of the unfinished sweep in ``out``."""
    out = Path(out)
    store.check_out(out, "sweep", resume=True)
    return SweepConfig.from_toml(out / "config.toml")


def committed(config: SweepConfig, out: Path, process_id: int = 0, num_processes: int = 1,
              world: sim.World = sim.WORLD) -> int:
    """Scenarios this process has committed in ``out``'s checkpoint (0 if none); raises
    :class:`~jaxfalsify.io.checkpoints.CheckpointError` if the checkpoint is unusable."""
    space, calib = config.build()
    config = config.resolved()
    begin, end, planned, ck, fp = _layout(config, space, calib, Path(out), process_id,
                                          num_processes, world)
    if not (ck / "state.json").exists():
        return 0
    done, _, _ = _load_progress(ck, fp, calib.count, begin, end, planned, config.rows)
    return min(done * planned, end - begin)


__all__ = ["SweepConfig", "execute", "resume_config", "committed", "summary_lines",
           "checkpoint_name"]
