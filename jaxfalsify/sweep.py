"""Exhaustive sweep of a discrete logical scenario: every concrete scenario, evaluated in chunks.

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

:func:`ground_truth` keeps the outcome of every scenario of a (space, SUT) pair in the per-user
cache, so figures and comparisons sweep a space once per machine.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import json
import math
import shutil
import time
import zipfile
from pathlib import Path
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify import cache, requirements, sim, store
from jaxfalsify import config as cfg
from jaxfalsify import sut as sut_lib
from jaxfalsify.distributed import agree, barrier, share
from jaxfalsify.problem import (
    SEED_LIMIT,
    build_requirement,
    build_space,
    check_int,
    check_mapping,
    check_space_sut,
    fixed_sut_params,
)
from jaxfalsify.progress import Clock, Progress, timing_line
from jaxfalsify.space import MAX_SIZE, Layout, Space

OUTCOME_FIELDS = tuple(f.name for f in dataclasses.fields(sim.Outcome))
DEFAULT_CHUNK = sim.CPU_CHUNK  # library helpers' default; a sweep's: sim.default_chunk()
ROWS = ("all", "collisions", "none")


def plan_chunks(size: int, chunk: int = DEFAULT_CHUNK) -> int:
    """Balanced chunk size, at most ``chunk``: as few chunks as that allows, about equal
    sizes, each a multiple of 256 x the local device count — the batch shards evenly, and XLA's
    CPU loops vectorise fully (an odd batch such as 129,871 ran 4x slower than 130,048). A
    ``chunk`` below that alignment is rounded to a multiple of the device count only (never
    below one row per device)."""
    n_dev = jax.local_device_count()
    unit = 256 * n_dev if chunk >= 256 * n_dev else n_dev
    cap = max(unit, chunk // unit * unit)
    n_chunks = max(1, -(-size // cap))
    per = -(-size // n_chunks)
    return -(-per // unit) * unit


def sweep_chunk(start, table, params, key, world, *, layout: Layout, sut: sut_lib.SUT,
                chunk: int, sharding=None):
    """Outcomes of the concrete scenarios numbered ``[start, start + chunk)`` (clamped to the
    space; rows past its end repeat the last scenario and must be dropped by the caller) under
    every calibration of ``params`` (a parameter pytree with a leading axis ``(C,)``). With a
    ``sharding`` (see :func:`jaxfalsify.sim.local_batch_sharding`) the batch is split over
    devices. Scenario ``n`` draws from ``fold_in(key, n)`` whatever the chunking. Pure; jit it.

    Returns ``(indices (chunk, P) int32, Outcome with (C, chunk) fields)``.
    """
    flat = jnp.minimum(start + jnp.arange(chunk, dtype=jnp.int32), layout.size - 1)
    if sharding is not None:
        flat = jax.lax.with_sharding_constraint(flat, sharding)
    idx = layout.unravel(flat)
    sc = layout.scenario(idx, table)
    out = jax.vmap(lambda p: sim.batch_rollout(sc, flat, key, sut, p, world)[0])(params)
    return idx, out


def reduce_chunk(start, n_valid, table, params, key, world, *, layout: Layout,
                 sut: sut_lib.SUT, chunk: int, sharding=None):
    """:func:`sweep_chunk` reduced on the device, for sweeps that keep no rows (on a GPU,
    moving every outcome to the host and reducing it there cost ~10x the simulation). Only
    the first ``n_valid`` rows count. Per calibration ``(C,)``: ``collisions``, ``nonfinite``
    (int32), ``top`` (the
    largest reward, NaN counted as -inf; float32), ``ties`` (valid rows with reward == top),
    ``best`` (the first row reaching it), and that row's ``idx (C, P)`` and outcome fields
    ``(C,)``. Pure; jit it.
    """
    idx, out = sweep_chunk(start, table, params, key, world, layout=layout, sut=sut,
                           chunk=chunk, sharding=sharding)
    valid = jnp.arange(chunk) < n_valid
    r = jnp.where(jnp.isnan(out.reward) | ~valid, -jnp.inf, out.reward)  # (C, chunk)
    best = jnp.argmax(r, axis=1)  # the first maximum
    top = jnp.max(r, axis=1)
    pick = lambda v: jnp.take_along_axis(v, best[:, None], axis=1)[:, 0]  # noqa: E731
    return {"collisions": jnp.sum(out.collision & valid, axis=1, dtype=jnp.int32),
            "nonfinite": jnp.sum(out.nonfinite & valid, axis=1, dtype=jnp.int32),
            "top": top, "ties": jnp.sum(valid & (r == top[:, None]), axis=1, dtype=jnp.int32),
            "best": best.astype(jnp.int32), "idx": idx[best],
            "out": {k: pick(v) for k, v in vars(out).items()}}


@functools.lru_cache(maxsize=32)
def _chunk_program(layout: Layout, sut: sut_lib.SUT, chunk: int, params_tree,
                   params_avals: tuple, world_tree, reduced: bool = False):
    sharding = sim.local_batch_sharding()

    def fn(start, n_valid, table, params_leaves, key_data, world_leaves):
        args = (start, table, jax.tree.unflatten(params_tree, params_leaves),
                jax.random.wrap_key_data(key_data), jax.tree.unflatten(world_tree, world_leaves))
        kw = {"layout": layout, "sut": sut, "chunk": chunk, "sharding": sharding}
        if reduced:
            return reduce_chunk(args[0], n_valid, *args[1:], **kw)
        idx, out = sweep_chunk(*args, **kw)
        return idx, vars(out)

    table = jax.ShapeDtypeStruct((len(layout.shape), max(layout.shape)), jnp.float32)
    key_args = (table, list(params_avals))

    def example():
        return (np.int32(0), np.int32(chunk), np.zeros(table.shape, np.float32),
                [np.zeros(a.shape, a.dtype) for a in params_avals], sim.seed_key_data(0),
                [np.float32(0)] * world_tree.num_leaves)

    key = sut_lib.cache_key(sut)
    static = None if key is None else {"layout": repr(layout), "sut": key, "chunk": chunk,
                                       "params": str(params_tree), "world": str(world_tree),
                                       "reduced": reduced}
    return cache.exported_jit(fn, "sweep", static, key_args, example)


def _program(params, world, layout: Layout, sut: sut_lib.SUT, chunk: int, reduced: bool):
    p_leaves, p_tree = jax.tree.flatten(sim._f32(params))
    w_leaves, w_tree = jax.tree.flatten(sim._f32(world))
    avals = tuple(jax.ShapeDtypeStruct(x.shape, x.dtype) for x in p_leaves)
    prog = _chunk_program(layout, sut, chunk, p_tree, avals, w_tree, reduced)
    return prog, p_leaves, w_leaves


def evaluate_chunk(start: int, table, params, key_data, world, *, layout: Layout,
                   sut: sut_lib.SUT, chunk: int):
    """:func:`sweep_chunk`, compiled (cached per machine): NumPy ``(indices, outcome dict)``."""
    prog, p_leaves, w_leaves = _program(params, world, layout, sut, chunk, False)
    idx, out = prog(np.int32(start), np.int32(chunk), table, p_leaves, key_data, w_leaves)
    return np.asarray(idx), {k: np.asarray(v) for k, v in out.items()}


def evaluate_reduced(start: int, n_valid: int, table, params, key_data, world, *,
                     layout: Layout, sut: sut_lib.SUT, chunk: int) -> dict:
    """:func:`reduce_chunk`, compiled (cached per machine), as NumPy."""
    prog, p_leaves, w_leaves = _program(params, world, layout, sut, chunk, True)
    res = prog(np.int32(start), np.int32(n_valid), table, p_leaves, key_data, w_leaves)
    return jax.tree.map(np.asarray, res)


def chunk_table(space: Space, begin: int, idx: np.ndarray, out, calib: "Calibrations"
                ) -> dict[str, np.ndarray]:
    """Host-side columns of one chunk (calibration-major): [calibration, swept parameters],
    scenario number, indices, values, outcome fields."""
    n, C = idx.shape[0], calib.count
    cols: dict[str, np.ndarray] = {}
    if C > 1:
        cols["calibration"] = np.repeat(np.arange(C, dtype=np.int32), n)
        for name, vals in calib.columns().items():
            cols[name] = np.repeat(vals, n)
    cols["scenario"] = np.tile(np.arange(begin, begin + n, dtype=np.int64), C)
    for p, name in enumerate(space.names):
        cols[f"{name}_idx"] = np.tile(idx[:, p].astype(np.int32), C)
    for p, name in enumerate(space.names):
        cols[name] = np.tile(space.exact_values[p][idx[:, p]], C)
    for f in OUTCOME_FIELDS:
        cols[f] = out[f][:, :n].reshape(-1)
    return cols


@dataclasses.dataclass(frozen=True)
class Calibrations:
    """The SUT parameter sets of a sweep: every combination of the swept values."""

    sut: sut_lib.SUT
    instances: tuple  # parameter pytrees, one per calibration
    swept: tuple[tuple[str, tuple[float, ...]], ...]  # (name, values) with several values

    @property
    def count(self) -> int:
        return len(self.instances)

    def stacked(self):
        if self.instances[0] is None:
            return np.zeros((self.count,), np.float32)  # no parameters: vmap over a dummy
        return jax.tree.map(lambda *xs: np.asarray(xs, np.float32), *self.instances)

    def columns(self) -> dict[str, np.ndarray]:
        """The swept parameters' value per calibration as given, ``{name: (C,) float64}``
        (the simulator computes with their float32 roundings)."""
        return {name: np.asarray([sut_lib.params_dict(p)[name] for p in self.instances],
                                 np.float64) for name, _ in self.swept}

    def describe(self, c: int) -> dict[str, float]:
        return {name: float(v[c]) for name, v in self.columns().items()}


def calibrations(sut: sut_lib.SUT, sut_params: Mapping[str, Any]) -> Calibrations:
    """Expand ``{name: value or [values]}`` into the calibrations: C order over the swept
    parameters in the SUT's declared order (the last declared parameter fastest), whatever
    order they are given in, so a sweep and its resume (whose ``config.toml`` lists them in
    declared order) number the calibrations alike. One-line ValueError naming a bad name or
    value, or values a swept parameter repeats in float32 (the simulator's precision)."""
    order = {n: i for i, n in enumerate(sut_lib.param_names(sut))}
    items = sorted(dict(sut_params).items(), key=lambda kv: order.get(kv[0], len(order)))
    fixed, swept = {}, []
    for name, v in items:  # sorted is stable: unknown names keep their order, at the end
        if isinstance(v, np.ndarray) and v.ndim == 1:  # an array of values, like a list
            v = v.tolist()
        if isinstance(v, (list, tuple)):
            v = [cfg.plain(x) if isinstance(x, np.generic) else x for x in v]
            if len(v) == 0:
                raise ValueError(f"sut_params.{name}: an empty list of values")
            if len(v) == 1:
                fixed[name] = v[0]
            else:
                swept.append((name, tuple(v)))
        else:  # a NumPy scalar as the Python number it is (np.float32 1.2 as 1.2)
            fixed[name] = cfg.plain(v) if isinstance(v, (np.generic, np.ndarray)) \
                and np.ndim(v) == 0 else v
    count = math.prod(len(vals) for _, vals in swept)
    if count > 4096:  # before building them
        raise ValueError(f"sut_params: {count} calibrations; at most 4096 per sweep")
    for name, vals in swept:  # each value checked (a bad one named) before the float32 test
        for x in vals:
            sut_lib.with_params(sut, {**fixed, name: x}, where="sut_params")
        as32 = np.asarray(vals, np.float64).astype(np.float32)
        if len(set(as32.tolist())) != len(vals):
            raise ValueError(f"sut_params.{name}: values {list(vals)} repeat in float32 (the "
                             "simulator's precision): the calibrations would be identical")
    instances = []
    for combo in itertools.product(*(vals for _, vals in swept)):
        over = {**fixed, **{n: c for (n, _), c in zip(swept, combo)}}
        instances.append(sut_lib.with_params(sut, over, where="sut_params"))
    sut_lib.check_traceable(sut, instances[0])
    return Calibrations(sut, tuple(instances),
                        tuple((n, tuple(float(x) for x in vals)) for n, vals in swept))


def check_columns(space: Space, calib: Calibrations) -> None:
    """ValueError for a swept SUT parameter named like another column of ``sweep.parquet``
    (it would be overwritten)."""
    taken = {"calibration", "scenario", *space.names, *(f"{n}_idx" for n in space.names),
             *OUTCOME_FIELDS}
    for name, _ in calib.swept:
        if name in taken:
            raise ValueError(f"--sut-param {name}: sweep.parquet has a column '{name}' already; "
                             "sweep that SUT parameter as a space parameter sut.NAME instead")


def check_sweepable(space: Space) -> None:
    """ValueError for a space too large to enumerate (int32 scenario numbers)."""

    if space.size > MAX_SIZE:
        raise ValueError(f"space '{space.name}' has {space.size:.3g} scenarios: too many to "
                         f"sweep (at most {MAX_SIZE:,}); search it (jaxfalsify run, or compare, "
                         "which then estimates the collision share from a uniform sample)")


def iter_sweep(space: Space, calib: Calibrations, world: sim.World = sim.WORLD,
               chunk: int = DEFAULT_CHUNK, start: int = 0, stop: int | None = None,
               planned: int | None = None, key=None, reduced: bool = False):
    """Yield ``(begin, end, columns)`` for consecutive chunks of scenarios ``[start, stop)``
    (host-side loop; each chunk is one call of the same compiled function, sharded over the
    local devices). ``planned`` fixes the compiled chunk size. With ``reduced`` the chunk is
    reduced on the device and ``columns`` is :func:`reduce_chunk`'s dict (no rows)."""
    check_sweepable(space)
    stop = space.size if stop is None else stop
    chunk = planned or plan_chunks(max(stop - start, 1), max(256, chunk // calib.count))
    table, params = space.table_array, calib.stacked()
    key_data = sim.seed_key_data(0) if key is None else key
    for b in range(start, stop, chunk):
        e = min(b + chunk, stop)
        kw = {"layout": space.layout, "sut": calib.sut, "chunk": chunk}
        if reduced:
            yield b, e, evaluate_reduced(b, e - b, table, params, key_data, world, **kw)
            continue
        idx, out = evaluate_chunk(b, table, params, key_data, world, **kw)
        idx = idx[: e - b]
        yield b, e, chunk_table(space, b, idx, out, calib)


class Reducer:
    """Running totals of a sweep per calibration: counts and the global maximum reward (the
    first scenario on ties) and how many scenarios reach it."""

    FIELDS = ("n", "collisions", "nonfinite", "best_reward", "best_row", "best_ties",
              "violations")

    def __init__(self, **state):
        self.n = 0
        self.collisions = 0
        self.violations = 0  # of the sweep's requirement (rows with a "violated" column)
        self.nonfinite = 0
        self.best_reward = -math.inf
        self.best_row: dict | None = None
        self.best_ties = 0
        for k, v in state.items():
            setattr(self, k, -math.inf if k == "best_reward" and v is None else v)

    def state(self) -> dict:
        return {k: getattr(self, k) for k in self.FIELDS}

    def add(self, cols: dict[str, np.ndarray]):
        self.n += len(cols["scenario"])
        self.collisions += int(np.sum(cols["collision"]))
        if "violated" in cols:
            self.violations += int(np.sum(cols["violated"]))
        self.nonfinite += int(np.sum(cols["nonfinite"]))
        r = np.where(np.isnan(cols["reward"]), -np.inf, cols["reward"]).astype(np.float64)
        i = int(np.argmax(r))
        if r[i] > self.best_reward:
            self.best_reward = float(r[i])
            self.best_row = {k: cfg.plain(v[i]) for k, v in cols.items()}
            self.best_ties = int(np.sum(r == r[i]))
        elif r[i] == self.best_reward and math.isfinite(r[i]):
            self.best_ties += int(np.sum(r == r[i]))


def _add_reduced(reds: list[Reducer], space: Space, calib: Calibrations, b: int, e: int,
                 res: dict) -> None:
    """Fold one chunk's device-side totals (:func:`reduce_chunk`) into the reducers: the
    same state :meth:`Reducer.add` reaches from the chunk's rows."""
    for c, red in enumerate(reds):
        red.n += e - b
        red.collisions += int(res["collisions"][c])
        red.nonfinite += int(res["nonfinite"][c])
        top = float(res["top"][c])
        if top > red.best_reward:
            i = int(res["best"][c])
            out = {k: np.repeat(v[c:c + 1, None], calib.count, axis=0)
                   for k, v in res["out"].items()}
            row = chunk_table(space, b + i, res["idx"][c:c + 1], out, calib)
            red.best_reward = top
            red.best_row = {k: cfg.plain(v[c]) for k, v in row.items()}
            red.best_ties = int(res["ties"][c])
        elif top == red.best_reward and math.isfinite(top):
            red.best_ties += int(res["ties"][c])


def _split_cols(cols: dict, calib: Calibrations) -> list[dict]:
    """A chunk's columns per calibration (calibration-major rows)."""
    if calib.count == 1:
        return [cols]
    n = len(cols["scenario"]) // calib.count
    return [{k: v[c * n:(c + 1) * n] for k, v in cols.items()} for c in range(calib.count)]


def fold(reds: list[Reducer], space: Space, calib: Calibrations, b: int, e: int, cols: dict,
         reduced: bool) -> None:
    """Add one chunk of :func:`iter_sweep` (rows, or with ``reduced`` device-side totals) to
    the per-calibration reducers."""
    if reduced:
        _add_reduced(reds, space, calib, b, e, cols)
        return
    for red, part in zip(reds, _split_cols(cols, calib)):
        red.add(part)


@dataclasses.dataclass(frozen=True)
class SweepConfig:
    """What a sweep needs."""

    space: Any = "paper"  # built-in name, TOML path, or a space description table
    space_seed: int = 0  # discretisation seed
    sut: str = "carla-tm"
    sut_params: Mapping[str, Any] = dataclasses.field(default_factory=dict)  # value or list
    seed: int = 0  # the SUT's randomness (sensor noise); deterministic SUTs ignore it
    chunk: int | None = None  # most scenarios (x calibrations) per compiled call; None:
    # the backend's default (sim.default_chunk), resolved by execute once any distributed
    # runtime is up (choosing it starts JAX's backend); config.toml records the value
    rows: str = "all"  # all, collisions or none (summary only)
    requirement: str = "collision"  # also count its violations (a "violated" column; rows =
    # "collisions" then keeps the violations)
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)

    def requirement_of(self):
        """``(Requirement, its parameters)``, or ``(None, None)`` for collisions; one-line
        ValueError for a bad name or parameter."""
        req, params = build_requirement(self.requirement, self.requirement_params)
        return (None, None) if req is None else (req, params)

    def build(self) -> tuple[Space, Calibrations]:
        check_int("space_seed", self.space_seed, 0, SEED_LIMIT - 1)
        check_int("seed", self.seed, 0, SEED_LIMIT - 1)
        if self.chunk is not None:
            check_int("chunk", self.chunk, 1, 1 << 24)
        if self.rows not in ROWS:
            raise ValueError(f"rows must be one of {', '.join(ROWS)} (got {self.rows!r})")
        if not isinstance(self.sut, str):
            raise ValueError(f"sut must be a name (got {self.sut!r})")
        sp = build_space(self.space, self.space_seed)
        sut = sut_lib.resolve(self.sut)
        self.requirement_of()
        return sp, calibrations(sut, check_mapping("sut_params", self.sut_params))

    def resolved(self) -> "SweepConfig":
        """This config with the default chunk chosen for JAX's backend and a SUT file path
        made absolute (:func:`jaxfalsify.sut.recorded_spec`)."""
        return dataclasses.replace(self, chunk=self.chunk or sim.default_chunk(),
                                   sut=sut_lib.recorded_spec(self.sut),
                                   requirement=sut_lib.recorded_spec(self.requirement))

    def full_sut_params(self, space: Space) -> dict[str, Any]:
        """Every SUT parameter: its default, or the value (list of values) given; without
        those ``space`` varies (its ``sut.NAME`` dimensions)."""

        defaults = sut_lib.params_dict(sut_lib.resolve(self.sut).default_params)
        return fixed_sut_params({**defaults, **dict(self.sut_params)}, space)

    def to_toml(self, space: Space, processes: int = 1) -> str:
        doc = {"kind": "sweep", "sut": self.sut, "space_seed": self.space_seed,
               "seed": self.seed, "chunk": self.chunk, "rows": self.rows,
               "processes": processes, "sut_params": self.full_sut_params(space),
               **({"requirement": self.requirement,
                   "requirement_params": dict(self.requirement_params)}
                  if self.requirement != "collision" else {}),
               "space": space.describe()}
        return cfg.dumps_toml(doc)

    @classmethod
    def from_toml(cls, path: Path) -> tuple["SweepConfig", int]:
        """``(config, processes)`` from a sweep's ``config.toml``."""
        doc = cfg.read_toml(path)
        if doc.pop("kind", None) != "sweep":
            raise ValueError(f"{path} is not a sweep's config")
        processes = doc.pop("processes", 1)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(doc) - known
        if unknown:
            raise ValueError(f"{path}: unknown key '{sorted(unknown)[0]}'")
        try:
            return cls(**doc), int(processes)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: {e}") from None


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


def default_out(space: Space, sut_name: str, space_seed: int) -> Path:
    sut = sut_lib.folder_name(sut_name)
    return Path("sweeps") / f"{space.name}-{sut}-s{space_seed}"  # names hold no / (check_name)


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
    st = store.read_json(where)
    if st.get("fingerprint") != fingerprint:
        raise store.CheckpointError(f"checkpoint {where} was written by another sweep "
                                    "configuration or code (the SUT's or jaxfalsify's source "
                                    "changed?)")
    try:
        done = int(st["chunks_done"])
        reds = [Reducer(**{k: t[k] for k in Reducer.FIELDS}) for t in st["totals"]]
        files = dict(st["files"])
    except (KeyError, TypeError, ValueError):
        raise store.CheckpointError(f"checkpoint {where} is corrupt (fields)") from None
    n_chunks = -(-(end - begin) // planned)
    scenarios = min(done * planned, end - begin)
    if (len(reds) != n_calib or not 0 <= done <= n_chunks
            or st.get("scenarios_done") != scenarios
            or any(r.n != scenarios for r in reds)):
        raise store.CheckpointError(f"checkpoint {where} is inconsistent (chunks or totals)")
    ident = store.identity(fingerprint)
    for c in range(done if rows != "none" else 0):
        name = f"rows-{c:06d}.parquet"
        entry = files.get(name)
        if entry is not None and (entry.get("chunk") != c or entry.get("run") != ident
                                  or entry.get("range") != _chunk_range(c, begin, end, planned)):
            raise store.CheckpointError(f"checkpoint file {ck / name}: its record names "
                                        "another chunk or sweep")
        store.read_verified(ck / name, entry)
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
                raise store.CheckpointError(f"checkpoint {where}: its totals disagree with "
                                            "its rows files (edited)")
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
    skipped); ``stop`` is checked between chunks (see :func:`jaxfalsify.runs.execute`).
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

    agree("sweep configuration", store.sha256("\n".join(  # the SUT by its code, not its path
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
    except (store.Interrupted, ValueError):
        raise
    except BaseException as e:
        if num_processes == 1 and not resume and sut_lib.callback_error(e) is not None:
            store.discard(out, "sweep", lk, existed)  # the SUT raised: nothing worth keeping
        elif process_id == 0 and (out / "config.toml").exists():
            try:  # status.json tells the truth
                store.write_status(out, "sweep", "failed", error=(
                    sut_lib.callback_error(e) or f"{type(e).__name__}: {e}")[:300])
            except OSError:
                pass
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
            raise store.CheckpointError(f"--resume {out}: config.toml does not match the "
                                        "sweep configuration given")
    multi = num_processes > 1
    name = (f"sweep.part-{process_id:05d}-of-{num_processes:05d}.parquet" if multi
            else "sweep.parquet")
    begin, end, planned, ck, fingerprint = _layout(config, space, calib, out, process_id,
                                                   num_processes, world)
    done, reds, files = 0, [Reducer() for _ in range(calib.count)], {}
    if resume:
        store.check_checkpoint_folder(ck)
    if resume and (ck / "state.json").exists():
        done, reds, files = _load_progress(ck, fingerprint, calib.count, begin, end, planned,
                                           config.rows)
    ident = store.identity(fingerprint)
    lk.claim("sweep")
    if process_id == 0 and not resume:
        if force:
            store.clear(out, "sweep")
        out.mkdir(parents=True, exist_ok=True)
        store.write_atomic(out / "config.toml", config.to_toml(space, num_processes))
    barrier("jaxfalsify-sweep-started")
    out.mkdir(parents=True, exist_ok=True)
    if not resume and ck.exists():
        shutil.rmtree(ck)
    ck.mkdir(parents=True, exist_ok=True)
    if process_id == 0:
        store.write_status(out, "sweep", "running", scenarios=space.size)
    resumed_from = min(begin + done * planned, end)
    total = (end - begin) * calib.count
    progress.phase(f"compiling the sweep of {space.name} x {config.sut}"
                   + (f" x {calib.count} calibrations" if calib.count > 1 else ""))
    t0 = time.perf_counter()
    compile_s, started = 0.0, False
    req, req_params = config.requirement_of()
    violated = None if req is None else _violated_fn(req)
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
                files[rows_file] = {"sha256": store.write_parquet(ck / rows_file, cols),
                                    "chunk": c, "range": [b, e], "run": ident}
            store.write_commit(ck / "state.json", {"chunks_done": c + 1,
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
        st = store.read_json(ck / "state.json") if (ck / "state.json").exists() else {}
        n_done = int(st.get("scenarios_done", 0))
        if process_id == 0:
            store.write_status(out, "sweep", "interrupted", scenarios_done=n_done,
                               scenarios=space.size)
        raise store.Interrupted("sweep", out, n_done, end - begin, "scenarios") from None
    progress.close()
    search_s = time.perf_counter() - t0 - compile_s
    clock.add("compile", compile_s)
    clock.add("sweep", search_s)
    with clock("writing"):
        n_chunks = -(-(end - begin) // planned)
        if config.rows != "none" and n_chunks:  # an empty share writes no part file
            _merge_rows([(ck / f"rows-{c:06d}.parquet", files.get(f"rows-{c:06d}.parquet"))
                         for c in range(n_chunks)], out / name)
        part = {"process_id": process_id,
                "totals": [{"n": r.n, "collisions": r.collisions, "nonfinite": r.nonfinite,
                            "violations": r.violations,
                            "best_reward": r.best_reward, "best_ties": r.best_ties,
                            "best": _scenario_of(space, r.best_row)} for r in reds],
                "clock": clock.summary()}
        if multi:
            store.write_commit(out / f".summary.part-{process_id:05d}.json",
                               {**part, "sweep": store.identity(config.to_toml(space,
                                                                               num_processes))})
            barrier("jaxfalsify-sweep-parts-written")
            parts = [_read_part(out / f".summary.part-{i:05d}.json", i,
                                store.identity(config.to_toml(space, num_processes)))
                     for i in range(num_processes)]
        else:
            parts = [cfg.jsonable(part)]
        summary = _merge_summary(space, config, calib, parts, num_processes)
    timing = {**clock.summary(), "chunk": planned, "devices": jax.local_device_count(),
              "resumed_from_scenario": resumed_from - begin}
    if process_id == 0:
        store.write_json(out / "timing.json", timing, indent=2)
        store.write_json(out / "summary.json", summary, indent=2)
        store.write_status(out, "sweep", "complete", scenarios=space.size)
    if multi:
        barrier("jaxfalsify-sweep-summary-written")
        if process_id == 0:  # every process has read the parts (before the barrier)
            for i in range(num_processes):
                (out / f".summary.part-{i:05d}.json").unlink(missing_ok=True)
    shutil.rmtree(ck, ignore_errors=True)
    return {**summary, **timing, "out": str(out)}


def _read_part(path: Path, i: int, sweep_id: str) -> dict:
    """Another process's summary part, its seal and identity verified."""
    doc = store.read_json(path)
    if doc.get("sweep") != sweep_id or doc.get("process_id") != i:
        raise store.CheckpointError(f"{path} belongs to another sweep or process")
    return doc


def _merge_summary(space: Space, config: SweepConfig, calib: Calibrations, parts: list,
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


def _merge_rows(files: list[tuple[Path, dict | None]], final: Path) -> None:
    """Concatenate the chunks' Parquet files (each verified against its commit-record entry)
    into one, under a temporary name, then rename."""
    import io

    import pyarrow.parquet as pq

    with store.atomic_path(final) as part:
        writer = None
        try:
            for f, entry in files:
                table = pq.read_table(io.BytesIO(store.read_verified(f, entry)))
                if writer is None:
                    writer = pq.ParquetWriter(part, table.schema)
                writer.write_table(table)
        finally:
            if writer is not None:
                writer.close()


def resume_config(out: Path | str) -> tuple[SweepConfig, int]:
    """``(config, processes)`` of the unfinished sweep in ``out``."""
    out = Path(out)
    store.check_out(out, "sweep", resume=True)
    return SweepConfig.from_toml(out / "config.toml")


def committed(config: SweepConfig, out: Path, process_id: int = 0, num_processes: int = 1,
              world: sim.World = sim.WORLD) -> int:
    """Scenarios this process has committed in ``out``'s checkpoint (0 if none); raises
    :class:`~jaxfalsify.store.CheckpointError` if the checkpoint is unusable."""
    space, calib = config.build()
    config = config.resolved()
    begin, end, planned, ck, fp = _layout(config, space, calib, Path(out), process_id,
                                          num_processes, world)
    if not (ck / "state.json").exists():
        return 0
    done, _, _ = _load_progress(ck, fp, calib.count, begin, end, planned, config.rows)
    return min(done * planned, end - begin)


# ----------------------------------------------------------------------------- in memory
def sweep_arrays(space: Space, sut="carla-tm", sut_params=None, world: sim.World = sim.WORLD,
                 chunk: int = DEFAULT_CHUNK, fields=None) -> dict[str, np.ndarray]:
    """The whole sweep in memory (small spaces, tests, ground truth): ``fields`` (default
    all columns) ``(N,)`` in scenario order. ``sut_params`` as in :func:`calibrations`."""
    s = sut_lib.resolve(sut)
    calib = calibrations(s, sut_params or {})
    parts = []
    for _, _, cols in iter_sweep(space, calib, world, chunk):
        parts.append({k: v for k, v in cols.items() if fields is None or k in fields})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


TRUTH_FIELDS = ("collision", "reward", "nonfinite")


def _violated_fn(req):
    """``(columns, params) -> (n,) bool``: a chunk's violations of ``req`` (robustness < 0 on
    a finite rollout), from its outcome columns; one compiled function per requirement."""
    rob = jax.jit(lambda o, p: requirements.robustness(req, o, p))

    def violated(cols: dict, params) -> np.ndarray:
        out = sim.Outcome(**{f: np.asarray(cols[f]) for f in OUTCOME_FIELDS})
        nonfinite = np.asarray(cols["nonfinite"], bool)
        return (np.asarray(rob(out, params)) < 0) & ~nonfinite

    return violated


def _violation_truth(space: Space, s, sut_params, world, req, req_params) -> dict:
    """:func:`ground_truth`'s arrays with ``collision`` the requirement's violations, chunk by
    chunk (only the three arrays are kept)."""
    calib = calibrations(s, sut_params or {})
    violated = _violated_fn(req)
    parts: dict[str, list] = {k: [] for k in TRUTH_FIELDS}
    for _, _, cols in iter_sweep(space, calib, world, DEFAULT_CHUNK):
        parts["collision"].append(violated(cols, req_params))
        parts["reward"].append(np.asarray(cols["reward"]))
        parts["nonfinite"].append(np.asarray(cols["nonfinite"], bool))
    return {k: np.concatenate(v) for k, v in parts.items()}


def ground_truth(space: Space, sut="carla-tm", sut_params=None,
                 world: sim.World = sim.WORLD, requirement=None,
                 requirement_params=None) -> dict[str, np.ndarray]:
    """``{collision, reward, nonfinite}`` ``(N,)`` of every scenario, from the per-user cache
    (keyed by the space's values, the SUT, its parameters, the world and the simulator's
    source) or swept once and stored there. With a ``requirement`` (a name, an import path
    or a :class:`jaxfalsify.requirements.Requirement`; ``requirement_params`` a table of its
    parameters or their pytree), ``collision`` holds its violations instead (robustness < 0 on
    a finite rollout), what a run with that requirement calls critical."""
    import hashlib

    s = sut_lib.resolve(sut)
    params = sut_lib.with_params(s, sut_params)
    code = sut_lib.cache_key(s)  # None (a closure, no source file): never cached
    if requirement is not None:  # a name, an import path or a Requirement; its parameters
        requirement = requirements.resolve(requirement)  # as a table or a pytree
        requirement_params = requirements.with_params(requirement, requirement_params)
        if requirement is requirements.REGISTRY["collision"]:
            requirement = None  # the plain ground truth
    # the space by its parameters in their order (which numbers the scenarios) and the exact
    # float32 values; the code by jaxfalsify's whole source, the SUT's (its module and every
    # user module loaded: helpers), the jax version and the backend (float32 results differ)
    values = hashlib.sha256(b"".join(v.tobytes() for v in space.values)).hexdigest()
    key = cache.key_of({"names": list(space.names), "shape": list(space.shape),
                        "values": values, "sut": code,
                        "params": sut_lib.params_dict(params), "world": repr(world),
                        "code": cache.code_hash(), "jax": jax.__version__,
                        "backend": jax.default_backend(),
                        "prng": str(jax.config.jax_default_prng_impl),
                        **({} if requirement is None else {
                            "requirement": requirements.cache_key(requirement),
                            "requirement_params": sut_lib.params_dict(requirement_params)})})
    path = cache.folder() / "truth" / f"{key}.npz"
    use = cache.enabled() and code is not None and (
        requirement is None or requirements.cache_key(requirement) is not None)
    if use and path.is_file():
        try:
            with np.load(path) as z:
                got = {k: z[k] for k in TRUTH_FIELDS}
                mine = "key" in z.files and str(z["key"]) == key  # an entry of another space
                # or SUT put under this name (each file intact) is swept again, never used
            if mine and all(len(v) == space.size for v in got.values()):
                return got
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            pass  # a damaged entry (a flipped bit fails the zip's CRC) is swept again
        cache.stale(path)
    given = None if params is None else dict(sut_lib.params_dict(params))
    got = (sweep_arrays(space, s, given, world, fields=TRUTH_FIELDS) if requirement is None
           else _violation_truth(space, s, given, world, requirement, requirement_params))
    if use:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            store.save_npz(path, {**got, "key": np.array(key)})
        except OSError:
            pass
    return got
