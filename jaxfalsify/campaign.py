"""A falsification campaign: a search strategy against a SUT over a space, for a budget.

``make_campaign`` builds, PureJaxRL-style, pure functions whose whole loop (ask -> simulate the
batch -> tell, ``lax.scan`` over updates) is one jit-compiled call; the host calls it once per
chunk of updates so a progress bar can move, and collects every evaluated scenario.
``run_seeds`` runs many seeds inside one compiled call (``lax.map`` over keys: each seed's
batch is already hundreds of scenarios wide, and vmapping the LSTM controller over seeds
deadlocked XLA:CPU in jax 0.10.2 during development).

Evaluations are numbered from 1 in the order they were asked. A budget that is not a multiple
of the batch is honoured by giving the overflow of the last batch a reward of -inf (it teaches
nothing and is not recorded).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfalsify import search, sim
from jaxfalsify import sut as sut_lib
from jaxfalsify.space import Space

RECORD_FIELDS = ("reward", "reward_rss", "reward_distance", "reward_collision", "collision",
                 "min_distance", "final_distance", "high_risk_share",
                 "high_risk_share_second_half", "robustness", "nonfinite")


class Plan(NamedTuple):
    batch: int
    n_updates: int
    updates_per_chunk: int
    budget: int

    @property
    def n_chunks(self) -> int:
        return self.n_updates // self.updates_per_chunk


def plan(budget: int, batch: int, chunks_target: int = 20, every: int | None = None) -> Plan:
    """Updates needed for the budget, and a chunking of them (a divisor) for progress and
    checkpoints: about ``chunks_target`` chunks, or at most ``every`` updates per chunk.
    Results do not depend on the chunking (the same update function is scanned)."""
    if budget <= 0:
        raise ValueError(f"budget (--episodes) must be positive (got {budget})")
    if batch <= 0:
        raise ValueError(f"batch must be positive (got {batch})")
    n_updates = -(-budget // batch)
    per = min(every, n_updates) if every else max(1, n_updates // chunks_target)
    while n_updates % per:
        per -= 1
    return Plan(batch, n_updates, per, budget)


def make_campaign(space: Space, sut: sut_lib.SUT, strategy: search.Strategy, p: Plan,
                  world: sim.World = sim.WORLD):
    """Returns ``(init(key) -> carry, run_chunk(carry) -> (carry, records))``, both pure.

    ``records`` hold, per update of the chunk, the batch's ``indices (U, B, P)`` and each of
    ``RECORD_FIELDS`` ``(U, B)``.
    """

    def init(key):
        k_init, k_run = jax.random.split(key)
        return {"state": strategy.init(k_init), "key": k_run, "update": jnp.int32(0)}

    sharding = sim.local_batch_sharding() if p.batch % jax.local_device_count() == 0 else None

    def one_update(carry, _):
        key, k_ask = jax.random.split(carry["key"])
        idx, state = strategy.ask(k_ask, carry["state"])
        if sharding is not None:  # the proposal batch is simulated on all local devices
            idx = jax.lax.with_sharding_constraint(idx, sharding)
        out, _ = sim.batch_rollout(space.scenario(idx), sut, world, False)
        evaluation = carry["update"] * p.batch + jnp.arange(p.batch)
        in_budget = evaluation < p.budget
        r = jnp.where(jnp.isnan(out.reward) | ~in_budget, -jnp.inf, out.reward)
        state = strategy.tell(state, idx, r)
        rec = {"indices": idx, **{f: getattr(out, f) for f in RECORD_FIELDS}}
        return {"state": state, "key": key, "update": carry["update"] + 1}, rec

    def run_chunk(carry):
        return jax.lax.scan(one_update, carry, None, length=p.updates_per_chunk)

    return init, run_chunk


@dataclasses.dataclass
class Result:
    """Every evaluated scenario of a campaign, host-side, in evaluation order (1..budget)."""

    space: Space
    batch: int
    indices: np.ndarray  # (N, P) int32
    fields: dict[str, np.ndarray]  # RECORD_FIELDS -> (N,)
    compile_seconds: float
    wall_seconds: float

    @property
    def n(self) -> int:
        return len(self.indices)

    @property
    def evaluation(self) -> np.ndarray:
        return np.arange(1, self.n + 1)

    @property
    def update(self) -> np.ndarray:
        return (self.evaluation - 1) // self.batch

    def ranked_reward(self) -> np.ndarray:
        r = self.fields["reward"].astype(np.float64)
        return np.where(np.isnan(r), -np.inf, r)


def collect(records: list[dict], space: Space, p: Plan, compile_s: float, wall_s: float,
            seed_axis: int | None = None) -> Result | list[Result]:
    """Flatten chunk records ``(U, B, ...)`` (or ``(S, U, B, ...)``) into Result(s)."""
    host = [jax.tree.map(np.asarray, r) for r in records]
    cat = {k: np.concatenate([h[k] for h in host], axis=0 if seed_axis is None else 1)
           for k in host[0]}
    if seed_axis is None:
        return _one(cat, space, p, compile_s, wall_s)
    n_seeds = cat["reward"].shape[0]
    return [_one({k: v[s] for k, v in cat.items()}, space, p, compile_s, wall_s)
            for s in range(n_seeds)]


def _one(cat, space, p, compile_s, wall_s) -> Result:
    P = len(space.shape)
    idx = cat["indices"].reshape(-1, P)[: p.budget]
    fields = {f: cat[f].reshape(-1)[: p.budget] for f in RECORD_FIELDS}
    return Result(space, p.batch, idx.astype(np.int32), fields, compile_s, wall_s)


@functools.lru_cache(maxsize=16)
def _compiled(space: Space, sut: sut_lib.SUT, strategy: search.Strategy, p: Plan,
              world: sim.World, seeds: bool):
    """Jitted (init, run_chunk), mapped over seeds if asked; cached so repeated campaigns of
    the same configuration compile once."""
    init, run_chunk = make_campaign(space, sut, strategy, p, world)
    if seeds:
        return (jax.jit(lambda keys: jax.lax.map(init, keys)),
                jax.jit(lambda carry: jax.lax.map(run_chunk, carry)))
    return jax.jit(init), jax.jit(run_chunk)


def _drive(init, step, keys, p: Plan, progress=None, checkpoint=None, resumed=None):
    """Host loop over chunks of updates: returns (records, compile seconds, wall seconds).

    With a :class:`~jaxfalsify.checkpoint.CampaignCheckpoint`, every chunk is committed to it
    as soon as it is done; ``resumed = (carry, records)`` (from :func:`restore`) continues
    after the chunks those records hold.
    """
    import time

    t0 = time.perf_counter()
    carry, records = resumed if resumed and resumed[0] is not None else (init(keys), [])
    records = list(records)
    compile_s = 0.0
    if progress and records:
        progress(min(len(records) * p.updates_per_chunk * p.batch, p.budget), records)
    for c in range(len(records), p.n_chunks):
        carry, rec = step(carry)
        records.append(jax.tree.map(np.asarray, rec))
        done = min((c + 1) * p.updates_per_chunk * p.batch, p.budget)
        if checkpoint is not None:
            checkpoint.save(c, carry, records[-1], done)
        if not compile_s:
            compile_s = time.perf_counter() - t0
        if progress:
            progress(done, records)
    return records, compile_s, time.perf_counter() - t0


def run(space: Space, sut: sut_lib.SUT, strategy: search.Strategy, p: Plan, seed: int,
        world: sim.World = sim.WORLD, progress: Callable[[int, Result | None], None] | None = None,
        checkpoint=None, resumed=None) -> Result:
    """One seed, chunk by chunk on the host (progress callback after each chunk).

    ``checkpoint``/``resumed``: see :func:`_drive` and :func:`restore`. A resumed run gives
    bit-identical results to an uninterrupted one: the carry (strategy and optimiser state,
    PRNG key, update count) is restored exactly and the same compiled chunk continues.
    """
    init, step = _compiled(space, sut, strategy, p, world, False)
    records, compile_s, wall = _drive(init, step, jax.random.key(seed), p, progress,
                                      checkpoint, resumed)
    return collect(records, space, p, compile_s, wall)


def restore(checkpoint, space: Space, sut: sut_lib.SUT, strategy: search.Strategy, p: Plan,
            seed: int, world: sim.World = sim.WORLD):
    """``(carry, records)`` saved in ``checkpoint`` for this configuration (``(None, [])``
    if none yet); raises :class:`~jaxfalsify.checkpoint.CheckpointError` if unusable."""
    from jaxfalsify.checkpoint import CheckpointError

    init, _ = _compiled(space, sut, strategy, p, world, False)
    carry, records = checkpoint.load(jax.eval_shape(init, jax.random.key(seed)))
    want = {"indices": (p.updates_per_chunk, p.batch, len(space.shape)),
            **{f: (p.updates_per_chunk, p.batch) for f in RECORD_FIELDS}}
    if len(records) > p.n_chunks or any(
            set(r) != set(want) or any(r[k].shape != want[k] for k in want) for r in records):
        raise CheckpointError(f"checkpoint {checkpoint.folder}: its records do not fit this "
                              "run's plan")
    return carry, records


def run_seeds(space: Space, sut: sut_lib.SUT, strategy: search.Strategy, p: Plan,
              seeds: list[int], world: sim.World = sim.WORLD) -> list[Result]:
    """Many seeds in one compiled function (the campaign mapped over keys)."""
    init, step = _compiled(space, sut, strategy, p, world, True)
    keys = jnp.stack([jax.random.key(s) for s in seeds])
    records, compile_s, wall = _drive(init, step, keys, p)
    return collect(records, space, p, compile_s, wall, seed_axis=0)


# ----------------------------------------------------------------------------- summaries
def first_collision_evaluation(res: Result) -> int | None:
    hits = np.nonzero(res.fields["collision"] & ~res.fields["nonfinite"])[0]
    return int(hits[0]) + 1 if hits.size else None


def convergence_evaluation(res: Result) -> int:
    """First evaluation after which the running best stays within 1 % of its final value."""
    best = np.maximum.accumulate(res.ranked_reward())
    final = best[-1]
    if not np.isfinite(final):
        return res.n
    ok = best >= final - 0.01 * abs(final)
    return int(np.argmax(ok)) + 1


def best_index(res: Result) -> int:
    return int(np.argmax(res.ranked_reward()))  # the first evaluation reaching the maximum


def distinct_critical(res: Result) -> list[dict]:
    """Distinct collision scenarios found, ranked by reward (then by first evaluation)."""
    col = res.fields["collision"] & ~res.fields["nonfinite"]
    seen: dict[tuple, dict] = {}
    for i in np.nonzero(col)[0]:
        key = tuple(int(v) for v in res.indices[i])
        if key in seen:
            seen[key]["times_evaluated"] += 1
        else:
            seen[key] = {"indices": key, "first_evaluation": int(i) + 1, "times_evaluated": 1,
                         **{f: res.fields[f][i].item() for f in RECORD_FIELDS}}
    return sorted(seen.values(), key=lambda d: (-d["reward"], d["first_evaluation"]))


def scenario_values(space: Space, indices) -> dict[str, float]:
    return {n: float(space.values[p][int(indices[p])]) for p, n in enumerate(space.names)}


def typical_non_critical(res: Result) -> int | None:
    """The non-colliding evaluation with the median reward (a 'typical' one, paper Table II)."""
    ok = ~res.fields["collision"] & ~res.fields["nonfinite"]
    idx = np.nonzero(ok)[0]
    if idx.size == 0:
        return None
    r = res.fields["reward"][idx]
    return int(idx[np.argsort(r, kind="stable")[len(idx) // 2]])

