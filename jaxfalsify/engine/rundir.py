"""Reading a finished run folder: its space, resolved configuration, summary and evaluated
scenarios (:func:`load_run`, every file checked against the others), and the trajectories of
any evaluated scenario simulated again as the run simulated it (:func:`resimulate`). Used by
the figures, the report, replay and export."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxfalsify.core import sim
from jaxfalsify.engine.campaign import RECORD_FIELDS, evaluation_key
from jaxfalsify.engine.problem import RunConfig
from jaxfalsify.scenario.space import Space, is_sut_parameter
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "RunFolder", "load_run", "check_config_matches", "check_simulated", "indices_of",
    "resimulate"
]


class RunFolder(NamedTuple):
    """A finished run folder, read and checked (:func:`load_run`); unpacks as ``space,
    config, summary, evaluations``."""

    space: Space  # the run's discretised logical scenario
    config: RunConfig  # config.toml, resolved
    summary: dict  # summary.json
    evaluations: dict  # evaluations.parquet: column name -> (N,) NumPy array


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


SUMMARY_TYPES = {  # summary.json's fields the outputs read: (test, what it must be)
    "evaluations": (_is_int, "an integer"), "batch": (_is_int, "an integer"),
    "space_seed": (_is_int, "an integer"), "seed": (_is_int, "an integer"),
    "n_collisions": (_is_int, "an integer"), "n_distinct_critical": (_is_int, "an integer"),
    "first_collision_evaluation": (lambda v: v is None or _is_int(v), "an integer or null"),
    "best_reached_evaluation": (lambda v: v is None or _is_int(v), "an integer or null"),
    "strategy": (lambda v: isinstance(v, str), "a string"),
    "space": (lambda v: isinstance(v, str), "a string"),
    "sut": (lambda v: isinstance(v, str), "a string"),
    "best": (lambda v: isinstance(v, dict) and _is_int(v.get("evaluation"))
             and (v.get("reward") is None or _is_number(v.get("reward"))),
             "an object with an integer 'evaluation' and a numeric 'reward'"),
}


def check_summary_types(where: Path, summary: dict) -> None:
    """One-line ValueError naming the first of ``summary``'s fields (those present) whose
    type is not what the outputs read (a hand-edited or damaged summary.json), before anything
    is drawn or written from it."""
    for key, (ok, what) in SUMMARY_TYPES.items():
        if key in summary and not ok(summary[key]):
            shown = json.dumps(summary[key])
            shown = shown if len(shown) <= 60 else shown[:57] + "..."
            raise ValueError(f"{where} is damaged ('{key}' is {shown}, expected {what})")


FLAG_COLUMNS = ("collision", "nonfinite", "violated", "failed")  # true/false columns


def check_column_types(where: Path, ep: dict, sp: Space) -> None:
    """One-line ValueError naming the first column of ``evaluations.parquet`` whose type is
    not what a run writes (a hand-edited or damaged file): the evaluation and update numbers
    and the value indices integers, the flags true/false, every other column a number."""
    integer = ("evaluation", "update", *(f"{n}_idx" for n in sp.names))
    for name, col in ep.items():
        kind = col.dtype
        if name in integer:
            ok, what = np.issubdtype(kind, np.integer), "integers"
        elif name in FLAG_COLUMNS:
            ok, what = kind == np.bool_, "true/false"
        else:
            ok, what = np.issubdtype(kind, np.number) and kind != np.bool_, "numbers"
        if not ok:
            raise ValueError(f"{where} is damaged: column '{name}' holds {kind} values, "
                             f"expected {what}")


def load_run(run_dir: Path) -> RunFolder:
    """A finished run folder: its space, resolved config, summary and evaluations columns,
    every file checked against the others (one-line ValueError naming the damaged file)."""
    import pyarrow.parquet as pq

    run_dir = Path(run_dir)
    missing = [f for f in ("config.toml", "summary.json", "evaluations.parquet")
               if not (run_dir / f).exists()]
    if missing:
        raise ValueError(f"{run_dir} is not a finished run folder (missing "
                         f"{', '.join(missing)})")
    rc = RunConfig.from_toml(run_dir / "config.toml")
    sp = rc.build().space
    where = run_dir / "summary.json"
    try:
        summary = json.loads(where.read_text())
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{where} is damaged ({e})") from None
    need = ("first_collision_evaluation", "n_collisions", "n_distinct_critical", "best",
            "evaluations", "batch", "strategy", "space", "space_seed", "sut", "seed")
    gone = [k for k in need if not isinstance(summary, dict) or k not in summary]
    if gone:
        raise ValueError(f"{where} is damaged (no '{gone[0]}')")
    check_summary_types(where, summary)
    where = run_dir / "evaluations.parquet"
    try:
        table = pq.read_table(where)
        ep = {k: table.column(k).to_numpy() for k in table.column_names}
    except Exception as e:  # pyarrow raises several kinds for a damaged file
        why = " ".join(str(e).split())
        why = why if len(why) <= 120 else why[:120].rsplit(" ", 1)[0] + " ..."
        raise ValueError(f"{where} is damaged ({type(e).__name__}: {why})") from None
    cols = ["evaluation", *RECORD_FIELDS,
            *(c for n in sp.names for c in (f"{n}_idx", n))]
    gone = [c for c in cols if c not in ep]
    if gone:
        raise ValueError(f"{where} is damaged (no column '{gone[0]}')")
    if len(ep["evaluation"]) == 0:
        raise ValueError(f"{where} holds no evaluation")
    check_column_types(where, ep, sp)
    n_rows = len(ep["evaluation"])
    if n_rows != summary["evaluations"] or not np.array_equal(
            ep["evaluation"], np.arange(1, n_rows + 1)):
        raise ValueError(f"{where} is damaged: its 'evaluation' column is not 1..{n_rows} in "
                         f"order, or its {n_rows} rows are not the {summary['evaluations']} "
                         "evaluations summary.json counts")
    update = ep.get("update")
    if update is not None and (update[0] < 0 or np.any(np.diff(update) < 0)):
        raise ValueError(f"{where} is damaged: its 'update' column is not non-negative and "
                         "non-decreasing")
    for key, v in (("best.evaluation", summary["best"]["evaluation"]),
                   ("first_collision_evaluation", summary["first_collision_evaluation"]),
                   ("best_reached_evaluation", summary.get("best_reached_evaluation"))):
        if v is not None and not 1 <= v <= n_rows:
            raise ValueError(f"{run_dir / 'summary.json'} is damaged ('{key}' is {v}, not one "
                             f"of the run's evaluations 1..{n_rows})")
    for n, size in zip(sp.names, sp.shape):
        i = ep[f"{n}_idx"]
        if i.min() < 0 or i.max() >= size:
            raise ValueError(f"{where} is damaged: column '{n}_idx' outside 0..{size - 1}")
    check_counts(run_dir, summary, ep)
    check_config_matches(run_dir, sp, rc, summary, ep)
    return RunFolder(sp, rc, summary, ep)


def check_counts(run_dir: Path, summary: dict, ep: dict) -> None:
    """ValueError (one line) where ``summary.json``'s counts, first evaluations and best
    reward are not those of ``evaluations.parquet`` (a hand-edited summary): the collisions
    and violations counted over finite rollouts, the first of each, the best evaluation (the
    first reaching the highest reward) and the reward recorded there (the same float32); and
    where a rollout recorded as finite has a non-finite reward (a hand-edited parquet)."""
    ok = ~np.asarray(ep["nonfinite"], bool)
    reward = np.asarray(ep["reward"], np.float64)
    bad = np.flatnonzero(ok & ~np.isfinite(reward))
    if bad.size:
        raise ValueError(f"{run_dir / 'evaluations.parquet'} is damaged: evaluation "
                         f"{bad[0] + 1}'s reward is {reward[bad[0]]} while its rollout is "
                         "recorded as finite")
    want = {}
    for name, col in (("collisions", "collision"), ("violations", "violated")):
        if col in ep:
            hit = np.asarray(ep[col], bool) & ok
            want[f"n_{name}"] = int(hit.sum())
            first = np.flatnonzero(hit)
            want[f"first_{name[:-1]}_evaluation"] = int(first[0]) + 1 if first.size else None
    want["n_nonfinite"] = int((~ok).sum())
    # the best: the first evaluation reaching the highest reward (analysis.best)
    want["best.evaluation"] = int(np.argmax(np.where(np.isnan(reward), -np.inf, reward))) + 1
    got_best = summary["best"].get("reward")
    if got_best is not None:
        at = np.float32(ep["reward"][summary["best"]["evaluation"] - 1])
        want["best.reward"] = float(str(at)) if np.isfinite(at) else None
    recorded = {"best.reward": got_best, "best.evaluation": summary["best"]["evaluation"]}
    for key, v in want.items():
        have = recorded[key] if key in recorded else summary.get(key, v)
        if have != v:
            raise ValueError(f"{run_dir / 'summary.json'} does not match evaluations.parquet "
                             f"('{key}' is {json.dumps(have)}; the evaluations give "
                             f"{json.dumps(v)})")


def check_config_matches(run_dir: Path, sp, rc, summary: dict, ep: dict) -> None:
    """ValueError (one line) where the folder's ``config.toml`` no longer describes its
    results (edited after the run): the seeds, strategy, SUT, SUT parameters and requirement
    (with its parameters) that ``summary.json`` records, and every evaluated scenario's values in
    ``evaluations.parquet`` against the space the config builds at their recorded indices."""
    for key in ("space_seed", "seed", "strategy", "sut", "sut_params", "requirement",
                "requirement_params"):
        here, there = getattr(rc, key), summary.get(key, getattr(rc, key))
        if isinstance(here, dict) and isinstance(there, dict) and here != there:
            name = sorted(k for k in set(here) | set(there) if here.get(k) != there.get(k))[0]
            key, here, there = f"{key}.{name}", here.get(name), there.get(name)
        if here != there:
            raise ValueError(f"{run_dir}/config.toml does not match the run's results: {key} "
                             f"= {here!r} there, {there!r} in summary.json "
                             "(edited after the run?)")
    for p, n in enumerate(sp.names):
        want = np.asarray(sp.values[p], np.float64)[ep[f"{n}_idx"]]
        got = np.asarray(ep[n], np.float64)
        bad = ~np.isclose(got, want, rtol=1e-5, atol=1e-6)
        if bad.any():
            j = int(np.argmax(bad))
            raise ValueError(f"{run_dir}/config.toml does not match the run's results: {n} of "
                             f"evaluation {int(ep['evaluation'][j])} is {got[j]:g} in "
                             f"evaluations.parquet but {want[j]:g} in the space config.toml "
                             "builds (edited after the run?)")


def check_simulated(run_dir: Path, rc, what: str) -> None:
    """ValueError (one line) for a run whose scenarios an external evaluator evaluated: there
    is no JAX SUT to simulate them again for ``what`` (replay, export)."""
    if rc.evaluator:
        raise ValueError(f"{run_dir} was evaluated by {rc.evaluator!r} outside JAX: {what} "
                         "needs the run's JAX SUT to simulate its scenarios again")


def indices_of(ep: dict, space, rows) -> np.ndarray:
    return np.stack([ep[f"{n}_idx"][rows] for n in space.names], -1)


def resimulate(sp, rc, ep: dict, rows, world=None):
    """Trajectories ``(len(rows), T)`` of a run's evaluated ``rows`` as the run simulated
    them: its space, SUT and SUT parameters, and for a stochastic SUT each evaluation's own
    draw (the campaign's key, offset by the evaluation number)."""
    rows = np.asarray(rows)
    key = 0
    if sut_lib.resolve(rc.sut).stochastic:
        key = evaluation_key(rc.seed)
    scen = sp.scenario(indices_of(ep, sp, rows))
    offsets = np.asarray(ep["evaluation"])[rows] - 1

    def run(sel):
        return sim.simulate({k: np.asarray(v)[sel] for k, v in scen.items()}, sut=rc.sut,
                           sut_params=dict(rc.sut_params), world=world or sim.WORLD, key=key,
                           offsets=offsets[sel])

    calib = [k for k in scen if is_sut_parameter(k)]  # a space's sut.NAME dimensions
    if not calib or rows.size == 0:
        return run(np.arange(rows.size))
    # one call per calibration (simulate takes one value of each SUT parameter), each padded
    # to the full size so every call reuses one compiled program
    values = np.stack([np.asarray(scen[k], np.float64) for k in calib], -1)
    _, group = np.unique(values, axis=0, return_inverse=True)
    group = group.reshape(-1)
    out = None
    for g in range(int(group.max()) + 1):
        sel = np.nonzero(group == g)[0]
        traj = run(np.concatenate([sel, np.full(rows.size - sel.size, sel[0])]))
        if out is None:
            out = {f.name: np.array(getattr(traj, f.name)) for f in dataclasses.fields(traj)}
        for name, arr in out.items():
            arr[sel] = np.asarray(getattr(traj, name))[:sel.size]
    return sim.Trajectory(**out)
