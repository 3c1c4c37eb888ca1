"""A sweep's chunks of scenarios on the device: each chunk evaluates all calibrations x its
scenarios in one compiled call (``vmap`` over the parameter pytree, the batch sharded over the
local devices; compiled programs cached per machine), as rows (:func:`sweep_chunk`, then
host-side columns: :func:`chunk_table`) or reduced on the device (:func:`reduce_chunk`);
:func:`iter_sweep` runs them one after another. Rows carry a ``calibration`` number and a
column per swept parameter when there are several calibrations.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.core import requirements, sim
from jaxfalsify.engine.sweep_config import Calibrations
from jaxfalsify.io import cache
from jaxfalsify.scenario.space import MAX_SIZE, Layout, Space
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "OUTCOME_FIELDS", "DEFAULT_CHUNK", "plan_chunks", "chunk_table", "check_columns",
    "check_sweepable", "iter_sweep", "violated_fn", "sweep_chunk", "reduce_chunk",
    "evaluate_chunk", "evaluate_reduced"
]

OUTCOME_FIELDS = tuple(f.name for f in dataclasses.fields(sim.Outcome))
DEFAULT_CHUNK = sim.CPU_CHUNK  # library helpers' default; a sweep's: sim.default_chunk()


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
    ``sharding`` (see :func:`jaxfalsify.core.sim.local_batch_sharding`) the batch is split over
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
    p_leaves, p_tree = jax.tree.flatten(sim.as_float32(params))
    w_leaves, w_tree = jax.tree.flatten(sim.as_float32(world))
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


def violated_fn(req):
    """``(columns, params) -> (n,) bool``: a chunk's violations of ``req`` (robustness < 0 on
    a finite rollout), from its outcome columns; one compiled function per requirement."""
    rob = jax.jit(lambda o, p: requirements.robustness(req, o, p))

    def violated(cols: dict, params) -> np.ndarray:
        out = sim.Outcome(**{f: np.asarray(cols[f]) for f in OUTCOME_FIELDS})
        nonfinite = np.asarray(cols["nonfinite"], bool)
        return (np.asarray(rob(out, params)) < 0) & ~nonfinite

    return violated
