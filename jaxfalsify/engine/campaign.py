"""A falsification campaign: a search strategy against a SUT over a space, for a budget.

One concern: one compiled campaign and the host loop that drives it.

:func:`make_campaign` builds, PureJaxRL-style, pure functions whose whole loop (tell the
previous batch -> ask -> simulate the batch, a ``lax.fori_loop`` over updates) is one
jit-compiled call. Everything numeric is a traced argument (:class:`Args`: the space's value
table, the SUT's and the strategy's parameters, the world, the budget), so another space seed,
calibration or hyperparameter value reuses the compiled code; only the static configuration
(space layout, SUT, strategy, batch, updates per chunk) compiles anew. The host (:func:`drive`)
calls it once per chunk of updates (the number of updates a traced argument: the first chunk
runs one, so the first batch's failures reach the host after one update) so progress can be
shown, checkpoints committed and a stop request honoured between chunks, and times each chunk
(compilation done ahead and timed apart; :meth:`Result.search_seconds_at`).

A batch's outcomes are returned with the update that simulated it; the strategy learns from
them at the start of the next update (the same asks and tells in the same order as learning at
the end of the update, so the same results; the last batch is never told, as nothing would use
what the strategy learnt from it).

Many seeds run inside one compiled call (``lax.map`` over keys: each seed's batch is already
hundreds of scenarios wide, and vmapping the LSTM controller over seeds has deadlocked
XLA:CPU).

Evaluations are numbered from 1 in the order they were asked. A budget that is not a multiple
of the batch is honoured by giving the overflow of the last batch a reward of -inf (it teaches
nothing and is not recorded).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify.core import requirements, screen, sim
from jaxfalsify.io import cache
from jaxfalsify.scenario.space import Layout, Space
from jaxfalsify.search.base import Strategy
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "RECORD_FIELDS", "Plan", "plan", "args_for", "Campaign", "evaluation_key", "environment",
    "is_key", "static_key", "program", "Result", "Stopped", "run_seeds", "run", "carry_avals",
    "record_shapes", "drive"
]

RECORD_FIELDS = ("reward", "reward_rss", "reward_distance", "reward_collision", "collision",
                 "min_distance", "final_distance", "high_risk_share",
                 "high_risk_share_second_half", "robustness", "nonfinite", "violated")
BOOL_FIELDS = ("collision", "nonfinite", "violated")  # the others float32
# violated: the run's requirement is violated (collision without one named; counted
# evaluations only: a non-finite rollout or one past the budget is never "violated")


class Plan(NamedTuple):
    batch: int  # scenarios per update
    n_updates: int  # updates to spend the budget
    updates_per_chunk: int  # updates per compiled call (progress, checkpoints, stop checks)
    evaluations: int  # the budget, in evaluated scenarios
    first_chunk: int = 1  # updates in the first call: the first batch's outcomes reach the
    # host (its failures, progress, the time to a first failure) after one update

    def start(self, c: int) -> int:
        """The first update (0-based) of chunk ``c``; ``n_updates`` for ``c >= n_chunks``."""
        if c <= 0:
            return 0
        return min(self.n_updates, self.first_chunk + (c - 1) * self.updates_per_chunk)

    def updates_in(self, c: int) -> int:
        """Updates chunk ``c`` runs (the last chunk may run fewer than ``updates_per_chunk``)."""
        return self.start(c + 1) - self.start(c)

    @property
    def n_chunks(self) -> int:
        """Chunks to run: a first one of ``first_chunk`` updates, then ``updates_per_chunk``
        each, the last one the rest."""
        rest = max(0, self.n_updates - self.first_chunk)
        return 1 + -(-rest // self.updates_per_chunk)

    def done_after(self, chunks: int) -> int:
        """Evaluations committed after ``chunks`` chunks."""
        return min(self.start(chunks) * self.batch, self.evaluations)


def plan(evaluations: int, batch: int, chunks_target: int = 20,
         every: int | None = None) -> Plan:
    """Updates needed for the budget, and a chunking of them for progress and checkpoints: a
    first chunk of one update, then chunks of ``every`` updates (about ``chunks_target`` chunks
    when not given), the last one the rest. Results do not depend on the chunking (the same
    update function runs, as many times as the budget needs)."""
    if isinstance(evaluations, bool) or not isinstance(evaluations, int) or evaluations <= 0:
        raise ValueError(f"evaluations must be a positive integer (got {evaluations!r})")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch <= 0:
        raise ValueError(f"batch must be a positive integer (got {batch!r})")
    n_updates = -(-evaluations // batch)
    per = min(every, n_updates) if every else max(1, n_updates // chunks_target)
    return Plan(batch, n_updates, per, evaluations, 1)


class Args(NamedTuple):
    """The traced inputs of a campaign."""

    table: jax.Array  # (P, max_n) float32, the space's values
    sut_params: Any  # the SUT's parameter pytree
    strategy_params: Any  # the strategy's hyperparameter pytree
    world: sim.World
    evaluations: jax.Array  # () int32, the budget
    requirement_params: Any = None  # the requirement's parameter pytree (None: none)


def args_for(space: Space, sut_params, strategy_params, world: sim.World,
             evaluations: int, requirement_params=None) -> Args:
    """The traced inputs, as host arrays (float32 parameters, int32 budget)."""
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return Args(space.table_array, jax.tree.map(f32, sut_params),
                jax.tree.map(f32, strategy_params), jax.tree.map(f32, world),
                np.int32(evaluations), jax.tree.map(f32, requirement_params))


@dataclasses.dataclass(frozen=True)
class Campaign:
    """The static configuration of a campaign (hashable: it keys the compiled functions)."""

    layout: Layout
    sut: sut_lib.SUT
    strategy: Strategy
    updates_per_chunk: int
    requirement: Any = None  # a requirements.Requirement the search looks for violations of
    # (None: collisions, ranked by the shaped signal of the clash robustness)

    @property
    def batch(self) -> int:
        return self.strategy.batch


def evaluation_key(seed: int) -> jax.Array:
    """The typed key a campaign of search seed ``seed`` simulates with: evaluation ``e``
    (1-based) draws its SUT's randomness from ``fold_in(evaluation_key(seed), e - 1)`` (pass
    it with ``offsets=e - 1`` to :func:`jaxfalsify.simulate` to re-simulate that draw)."""
    return jax.random.split(sim.seed_key(seed), 3)[1]  # as init() splits it


def make_campaign(c: Campaign):
    """Returns ``(init(key, args) -> carry, run_chunk(carry, args, count) -> (carry,
    records))``, both pure. ``records`` hold, per update of the chunk, the batch's ``indices
    (U, B, P)`` and each of ``RECORD_FIELDS`` ``(U, B)`` (``U = updates_per_chunk``; the rows
    past ``count``, the updates the call ran, are zeros)."""
    strategy, B = c.strategy, c.batch
    P = len(c.layout.shape)

    def pending_of(key, indices, reward, robustness, violated, ttc):
        """A batch's outcomes as the carry keeps them until the next update tells them."""
        return {"key": key, "indices": indices.astype(jnp.int32),
                "reward": reward.astype(jnp.float32),
                "robustness": robustness.astype(jnp.float32), "violated": violated,
                "ttc": ttc.astype(jnp.float32)}

    def init(key, args: Args):
        k_init, k_eval, k_run = jax.random.split(key, 3)  # k_eval: see evaluation_key
        zeros = jnp.zeros(B, jnp.float32)  # (never told: the first update tells nothing)
        pending = pending_of(k_run, jnp.zeros((B, P), jnp.int32), zeros, zeros,
                             jnp.zeros(B, bool), zeros)
        return {"state": strategy.start(k_init, args.strategy_params), "key": k_run,
                "eval_key": k_eval, "update": jnp.int32(0), "pending": pending}

    sharding = sim.local_batch_sharding() if B % jax.local_device_count() == 0 else None

    def tell(state, pending, args: Args):
        return strategy.tell_outcome(pending["key"], state, pending["indices"],
                                     pending["reward"], pending["robustness"],
                                     pending["violated"], args.strategy_params,
                                     ttc=pending["ttc"])

    def one_update(carry, args: Args):
        key, k_ask, k_tell = jax.random.split(carry["key"], 3)
        # the strategy learns from the previous update's batch first (the first update has
        # none): a batch's outcomes reach the host with the update that simulated it, before
        # the strategy has learnt from them; the order of asks and tells is the same
        state = jax.lax.cond(carry["update"] > 0, lambda s: tell(s, carry["pending"], args),
                             lambda s: s, carry["state"])
        # the kinematic screen (core/screen.py), traced only where the strategy uses it
        screen_of = screen.for_space(c.layout, args.table, c.sut, args.sut_params, args.world)
        idx, state = strategy.ask_screened(k_ask, state, args.strategy_params, screen_of)
        if sharding is not None:  # the proposal batch is simulated on all local devices
            idx = jax.lax.with_sharding_constraint(idx, sharding)
        evaluation = carry["update"] * B + jnp.arange(B, dtype=jnp.int32)
        out, _ = sim.batch_rollout(c.layout.scenario(idx, args.table), evaluation,
                                   carry["eval_key"], c.sut, args.sut_params, args.world)
        in_budget = evaluation < args.evaluations
        r = jnp.where(jnp.isnan(out.reward) | ~in_budget, -jnp.inf, out.reward)
        counted = in_budget & ~out.nonfinite
        if c.requirement is None:
            robustness, violated = out.robustness, out.collision & counted
        else:
            robustness = requirements.robustness(c.requirement, out, args.requirement_params)
            violated = (robustness < 0) & counted
        rob = jnp.where(counted & jnp.isfinite(robustness), robustness, jnp.inf)
        pending = pending_of(k_tell, idx, r, rob, violated,
                             jnp.where(counted, out.min_ttc, jnp.inf))
        rec = {"indices": idx, **{f: getattr(out, f) for f in RECORD_FIELDS
                                  if f != "violated"}, "violated": violated}
        return {**carry, "state": state, "key": key, "update": carry["update"] + 1,
                "pending": pending}, rec

    def run_chunk(carry, args: Args, count):
        """``count`` (traced, at most ``updates_per_chunk``) updates; the records of the
        chunk's remaining rows are zeros (the host keeps the first ``count``)."""
        U = c.updates_per_chunk
        recs = {"indices": jnp.zeros((U, B, P), jnp.int32),
                **{f: jnp.zeros((U, B), bool if f in BOOL_FIELDS else jnp.float32)
                   for f in RECORD_FIELDS}}

        def body(i, both):
            cr, rs = both
            cr, rec = one_update(cr, args)
            return cr, {k: jax.lax.dynamic_update_index_in_dim(rs[k], rec[k].astype(rs[k].dtype),
                                                              i, 0) for k in rs}

        return jax.lax.fori_loop(0, count, body, (carry, recs))

    return init, run_chunk


def environment() -> dict:
    """What a campaign's results depend on besides its configuration and code: JAX's tracing
    settings (:func:`jaxfalsify.io.cache.program_settings`), the backend (float32 results differ
    between CPU and GPU) and the local device count (on several devices the batch is sharded,
    and the partitioned program's float math can differ in the last bits, which a learning
    strategy such as ``reinforce/default`` amplifies into other proposals), and on a CPU
    XLA's thread count (:mod:`jaxfalsify.base.threads`: the simulator's outcomes are the same
    bits on any, a CMA-ES update's linear algebra not always)."""
    env = {**cache.program_settings(), "backend": jax.default_backend(),
           "local_devices": jax.local_device_count()}
    if env["backend"] == "cpu":
        env["xla_cpu_threads"] = os.environ.get("NPROC")
    return env


def is_key(x) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def static_key(c: Campaign) -> dict | None:
    """What identifies a campaign's program besides its argument shapes (None: not cacheable,
    e.g. a SUT built from a closure)."""
    sut = sut_lib.cache_key(c.sut)
    if sut is None:
        return None
    cls = type(c.strategy)
    strategy = f"{cls.__module__}.{cls.__qualname__}"
    if not cls.__module__.startswith("jaxfalsify."):  # a user's strategy: key on its code
        code = cache.user_code_hash(cls)
        if code is None:
            return None
        strategy += f":{code}"
    req = None if c.requirement is None else requirements.cache_key(c.requirement)
    if c.requirement is not None and req is None:
        return None
    return {"layout": repr(c.layout), "sut": sut, "strategy": repr(c.strategy),
            "strategy_code": strategy, "updates_per_chunk": c.updates_per_chunk,
            **({"requirement": req} if req is not None else {})}


@functools.lru_cache(maxsize=64)
def _program(c: Campaign, args_tree, args_avals: tuple, n_seeds: int,
             settings: tuple = ()) -> cache.Program:  # settings: keys the in-process cache
    init, run_chunk = make_campaign(c)

    def fn(carry_leaves, key_data, args_leaves, fresh, count):
        """One chunk for ``n_seeds`` seeds: ``(S, ...)`` carry leaves (PRNG keys as key data),
        key data ``(S, 2)``, the args' leaves, ``fresh`` (start from ``init``) and ``count``
        (int32: the updates to run, at most the chunk's length)."""
        args = jax.tree.unflatten(args_tree, args_leaves)
        template = jax.eval_shape(init, jax.random.key(0), args)
        leaves_t, ctree = jax.tree.flatten(template)
        keys = [is_key(x) for x in leaves_t]

        def one(xs):
            leaves, kd = xs
            carry = jax.lax.cond(
                fresh, lambda: init(jax.random.wrap_key_data(kd), args),
                lambda: jax.tree.unflatten(ctree, [jax.random.wrap_key_data(x) if k else x
                                                   for x, k in zip(leaves, keys)]))
            carry, rec = run_chunk(carry, args, count)
            return [jax.random.key_data(x) if k else x
                    for x, k in zip(jax.tree.leaves(carry), keys)], rec

        return jax.lax.map(one, (carry_leaves, key_data))

    def example():  # host zeros: no eager device ops (each would compile a small program)
        args_leaves = [np.zeros(a.shape, a.dtype) for a in args_avals]
        args = jax.tree.unflatten(args_tree, args_leaves)
        template = jax.eval_shape(lambda a: init(jax.random.key(0), a), args)
        kd = jax.eval_shape(lambda: jax.random.key_data(jax.random.key(0))).shape
        carry = [np.zeros((n_seeds,) + kd, np.uint32) if is_key(x)
                 else np.zeros((n_seeds,) + x.shape, x.dtype) for x in jax.tree.leaves(template)]
        return (carry, np.zeros((n_seeds, 2), np.uint32), args_leaves, np.bool_(True),
                np.int32(1))

    key_args = ([jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args_avals],
                jax.ShapeDtypeStruct((n_seeds,), jnp.uint32))
    return cache.exported_jit(fn, "campaign", static_key(c), key_args, example)


def program(c: Campaign, args: Args, n_seeds: int) -> cache.Program:
    """The compiled chunk function of a campaign for ``n_seeds`` seeds (cached in-process and,
    with :func:`jaxfalsify.io.cache.exported_jit`, per machine)."""
    leaves, tree = jax.tree.flatten(args)
    avals = tuple(jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in leaves)
    return _program(c, tree, avals, n_seeds, tuple(cache.program_settings().items()))


@dataclasses.dataclass
class Result:
    """Every evaluated scenario of a campaign, host-side, in evaluation order (1..budget).

    Timing (see :func:`drive`): ``compile_seconds`` lowering and compiling the chunk program
    (a program already compiled in this process costs milliseconds); ``search_seconds`` the
    host loop over chunks after that; ``chunk_seconds`` ``(n_chunks,)`` float64 seconds of
    each chunk's compiled call until its records were on the host (NaN: a chunk restored from
    a checkpoint, run by an earlier process; None: not timed), shared by the
    ``seeds_per_call`` seeds of that call. :meth:`search_seconds_at` turns them into the
    search time elapsed at an evaluation."""

    space: Space
    batch: int
    indices: np.ndarray  # (N, P) int32
    fields: dict[str, np.ndarray]  # RECORD_FIELDS -> (N,)
    compile_seconds: float = 0.0
    search_seconds: float = 0.0
    chunk_seconds: np.ndarray | None = None  # (n_chunks,) float64 seconds
    updates_per_chunk: int = 0  # updates per compiled call (the plan's)
    seeds_per_call: int = 1  # seeds that shared each compiled call
    chunk_updates: tuple[int, ...] | None = None  # updates each chunk ran (None: all
    # updates_per_chunk)

    @property
    def n(self) -> int:
        return len(self.indices)

    @property
    def evaluation(self) -> np.ndarray:
        return np.arange(1, self.n + 1)

    @property
    def update(self) -> np.ndarray:
        return (self.evaluation - 1) // self.batch

    def search_seconds_at(self, evaluation: int) -> float | None:
        """Search seconds (compilation excluded) this seed had spent at the end of the update
        holding evaluation ``evaluation`` (1-based): the chunks before that update's chunk in
        full, plus its chunk's seconds divided evenly among the updates the chunk ran
        (``chunk_updates``), for the updates up to and including this one; divided by
        ``seeds_per_call`` (seeds sharing a compiled call run one after another with the same
        work, so each is given an even share). Resolution: one update (exact at chunk
        boundaries, so for the first update). None when the campaign was not timed or a chunk
        up to there was restored from a checkpoint."""
        if isinstance(evaluation, bool) or not isinstance(evaluation, (int, np.integer)) \
                or not 1 <= evaluation <= max(self.n, 1):
            raise ValueError(f"evaluation must be an integer in 1..{max(self.n, 1)} "
                             f"(got {evaluation!r})")
        if self.chunk_seconds is None or self.updates_per_chunk <= 0:
            return None
        u = (int(evaluation) - 1) // self.batch  # 0-based update
        t = np.asarray(self.chunk_seconds, np.float64)
        lengths = (np.full(len(t), self.updates_per_chunk) if self.chunk_updates is None
                   else np.asarray(self.chunk_updates))
        ends = np.cumsum(lengths)  # updates done after each chunk
        c = int(np.searchsorted(ends, u, side="right"))  # the chunk holding update u
        if c >= len(t) or not np.all(np.isfinite(t[:c + 1])):
            return None
        j, length = u - (int(ends[c]) - int(lengths[c])), int(lengths[c])
        done = float(np.sum(t[:c])) + float(t[c]) * (j + 1) / length
        return done / self.seeds_per_call


def collect(records: list[dict], space: Space, p: Plan, compile_s: float = 0.0,
            search_s: float = 0.0, chunk_s: np.ndarray | None = None) -> list[Result]:
    """Flatten chunk records ``(S, U, B, ...)`` into one Result per seed (``chunk_s``: the
    ``(n_chunks,)`` seconds per chunk that :func:`drive` measured, shared by the S seeds)."""
    host = [jax.tree.map(np.asarray, r) for r in records]
    cat = {k: np.concatenate([h[k] for h in host], axis=1) for k in host[0]}
    n_seeds = cat["reward"].shape[0]

    def one(c):
        idx = c["indices"].reshape(-1, len(space.shape))[: p.evaluations]
        fields = {f: c[f].reshape(-1)[: p.evaluations] for f in RECORD_FIELDS}
        return Result(space, p.batch, idx.astype(np.int32), fields, compile_s, search_s,
                      None if chunk_s is None else np.array(chunk_s, np.float64),
                      p.updates_per_chunk, n_seeds,
                      tuple(p.updates_in(c) for c in range(p.n_chunks)))

    return [one({k: v[s] for k, v in cat.items()}) for s in range(n_seeds)]


class Stopped(Exception):
    """Raised by :func:`drive` when ``stop()`` asked to stop; the work done is committed."""

    def __init__(self, chunks_done: int):
        super().__init__(f"stopped after {chunks_done} chunks")
        self.chunks_done = chunks_done


def _compile_ahead(prog: cache.Program, carry, key_data, args_leaves, flags, fresh: bool,
                   chunks: int, count) -> None:
    """Compile the chunk program for the calls :func:`drive` will make, before the first one
    (the calls reuse what ``lower(...).compile()`` built). On several local devices the carry
    comes back sharded as the program's outputs are, which later calls see as other input
    shardings: those programs are compiled here too (until the carry's shardings repeat)."""
    compiled = prog.call.lower(carry, key_data, args_leaves, flags[fresh], count).compile()
    if jax.local_device_count() == 1 or chunks < 2:  # inputs committed as the outputs are
        return
    seen = []
    for _ in range(3):
        shardings = list(compiled.output_shardings[0])
        if shardings in seen:
            return
        seen.append(shardings)
        carry = [jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sh)
                 for x, sh in zip(carry, shardings)]
        compiled = prog.call.lower(carry, key_data, args_leaves, flags[False], count).compile()


def drive(prog: cache.Program, seeds: list[int], args: Args, p: Plan, *, progress=None,
          checkpoint=None, resumed=None, stop: Callable[[], bool] | None = None,
          timed: list | None = None):
    """Host loop over chunks of updates: ``(records, compile seconds, search seconds)``.

    ``progress(done, records)`` after each chunk (``done`` in evaluations); with a
    checkpoint (:class:`jaxfalsify.io.checkpoints.CampaignCheckpoint`) each chunk is committed
    to it;
    ``resumed = (carry, records)`` continues after the chunks those records hold;
    ``stop()`` is checked before each chunk: when true, raise :class:`Stopped` (everything
    done so far is committed).

    Timing: compile seconds are the program's lowering and compilation, done ahead of the
    first chunk (``lower(...).compile()``, which the chunk calls then reuse; a program already
    compiled in this process costs milliseconds); search seconds run from there to the end of
    the loop. ``timed``, when given, receives one float per chunk of the plan: the seconds of
    that chunk's compiled call until its records were on the host (a blocking transfer, so
    the chunk's device work is done), NaN for the chunks ``resumed`` holds.
    """
    if not 1 <= p.first_chunk <= p.updates_per_chunk:  # the program holds updates_per_chunk
        raise ValueError(f"first_chunk must be in 1..{p.updates_per_chunk} "
                         f"(got {p.first_chunk!r})")
    t0 = time.perf_counter()
    # every input committed to the device, as the outputs fed back are: the first and later
    # calls then share one compiled executable
    # (host-side NumPy: an eager jnp op would compile a small program of its own; on several
    # devices the batch is sharded inside, so inputs stay uncommitted)
    dev = jax.local_devices()[0] if jax.local_device_count() == 1 else None
    args_leaves = jax.device_put(jax.tree.leaves(args), dev)
    key_data = jax.device_put(np.stack([sim.seed_key_data(s) for s in seeds]), dev)
    if resumed and resumed[0] is not None:
        carry, records, fresh = list(resumed[0]), list(resumed[1]), False
    else:
        carry = [np.zeros(a.shape, a.dtype) for a in prog.in_avals[0]]
        records, fresh = [], True
    carry = jax.device_put(carry, dev)
    flags = [jax.device_put(np.bool_(f), dev) for f in (False, True)]
    counts = {n: jax.device_put(np.int32(n), dev)
              for n in {p.updates_in(c) for c in range(len(records), p.n_chunks)}}
    if timed is not None:
        timed[:] = [float("nan")] * len(records)
    if len(records) < p.n_chunks:  # compiled here, so that no chunk's time includes it
        _compile_ahead(prog, carry, key_data, args_leaves, flags, fresh,
                       p.n_chunks - len(records), counts[p.updates_in(len(records))])
    compile_s = time.perf_counter() - t0
    t_search = time.perf_counter()
    for c in range(len(records), p.n_chunks):
        if stop is not None and stop():
            raise Stopped(len(records))
        t_chunk = time.perf_counter()
        n = p.updates_in(c)
        carry, rec = prog(carry, key_data, args_leaves, flags[fresh], counts[n])
        fresh = False
        records.append(jax.tree.map(lambda x, n=n: np.asarray(x)[:, :n], rec))
        if timed is not None:
            timed.append(time.perf_counter() - t_chunk)
        if checkpoint is not None:
            checkpoint.save(c, [np.asarray(x) for x in carry], records[-1],
                            p.done_after(c + 1))
        if progress:
            progress(p.done_after(c + 1), records)
    search_s = time.perf_counter() - t_search
    return records, compile_s, search_s


def run_seeds(space: Space, sut: sut_lib.SUT, sut_params, strategy: Strategy,
              strategy_params, p: Plan, seeds: list[int], world: sim.World = sim.WORLD,
              requirement=None, requirement_params=None, **drive_kw) -> list[Result]:
    """Campaigns for many seeds in one compiled function (mapped over the seeds), chunk by
    chunk on the host (see :func:`drive` for the keywords). A resumed campaign gives
    bit-identical results to an uninterrupted one: the carry (strategy and optimiser state,
    PRNG keys, update count, the batch not yet told) is restored exactly and the same compiled
    chunk continues. Each Result carries the chunks' measured seconds
    (:meth:`Result.search_seconds_at`); the seeds of one call share them evenly, so a caller
    that wants each seed's own measured time calls this once per seed (the one-seed program is
    compiled once and reused)."""
    args = args_for(space, sut_params, strategy_params, world, p.evaluations,
                    requirement_params)
    prog = program(Campaign(space.layout, sut, strategy, p.updates_per_chunk, requirement),
                   args, len(seeds))
    chunk_s: list[float] = []
    records, compile_s, search_s = drive(prog, list(seeds), args, p, timed=chunk_s, **drive_kw)
    return collect(records, space, p, compile_s, search_s, np.asarray(chunk_s, np.float64))


def run(space: Space, sut: sut_lib.SUT, sut_params, strategy: Strategy, strategy_params,
        p: Plan, seed: int, world: sim.World = sim.WORLD, requirement=None,
        requirement_params=None, **drive_kw) -> Result:
    """One seed (see :func:`run_seeds`)."""
    return run_seeds(space, sut, sut_params, strategy, strategy_params, p, [seed], world,
                     requirement, requirement_params, **drive_kw)[0]


def carry_avals(space: Space, sut: sut_lib.SUT, sut_params, strategy: Strategy,
                strategy_params, p: Plan, world: sim.World = sim.WORLD, n_seeds: int = 1,
                requirement=None, requirement_params=None):
    """Shapes and dtypes of a campaign's carry leaves (what a checkpoint must hold)."""
    args = args_for(space, sut_params, strategy_params, world, p.evaluations,
                    requirement_params)
    return program(Campaign(space.layout, sut, strategy, p.updates_per_chunk, requirement),
                   args, n_seeds).in_avals[0]


def record_shapes(space: Space, p: Plan, chunk: int,
                  n_seeds: int = 1) -> dict[str, tuple[int, ...]]:
    """Shapes of chunk ``chunk``'s records ``(S, U, B, ...)`` (``U``: its updates)."""
    lead = (n_seeds, p.updates_in(chunk), p.batch)
    return {"indices": lead + (len(space.shape),), **{f: lead for f in RECORD_FIELDS}}
