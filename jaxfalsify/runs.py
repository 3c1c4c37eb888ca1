"""Run configurations, run directories and the closing report of ``jaxfalsify run``.

A run directory holds:

* ``config.toml`` — everything resolved (the space's full description included), so
  ``jaxfalsify run --config RUN/config.toml`` repeats the run;
* ``episodes.parquet`` — every evaluated concrete scenario;
* ``summary.json`` — the run's outcome (see README, 'The main job');
* ``critical.csv`` — the distinct collision scenarios found, ranked by reward;
* ``timing.json`` — wall and compile seconds (kept out of ``summary.json``, which is
  bit-identical between runs of the same config and seed);
* ``status.json`` — ``running``, ``interrupted`` or ``complete``, and how to resume;
* ``checkpoint/`` — while the run is unfinished: the state to resume from
  (see :mod:`jaxfalsify.checkpoint`); removed once the results are written.

``config.toml`` and ``status.json`` are written when the run starts; the results when it ends.
Files are written under temporary names and renamed, so nothing is left half-written.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from jaxfalsify import campaign, config as cfg, search
from jaxfalsify import sut as sut_lib
from jaxfalsify.space import Space, space as load_space, space_from_dict

PAPER_BUDGET = 4000


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """What a run needs; ``resolved()`` fills defaults that depend on other fields."""

    space: Any = "paper"  # built-in name, TOML path, or a space description table
    space_seed: int = 0
    sut: str = "carla-tm"
    strategy: str = "reinforce"
    preset: str | None = "default"
    episodes: int = PAPER_BUDGET
    batch: int | None = None
    seed: int = 0
    checkpoint_every: int | None = None  # updates between checkpoints (None: ~1/20 of the run)

    def resolved(self) -> "RunConfig":
        preset = self.preset if self.strategy == "reinforce" else None
        if self.strategy == "reinforce" and preset is None:
            preset = "default"
        batch = self.batch or search.default_batch(self.strategy, preset or "default")
        return dataclasses.replace(self, preset=preset, batch=batch)

    def build(self) -> tuple[Space, sut_lib.SUT, search.Strategy, campaign.Plan]:
        """Validate and build everything; ValueError (one line) on bad values."""
        _check_int("seed", self.seed, minimum=0)
        _check_int("space_seed", self.space_seed, minimum=0)
        _check_int("episodes", self.episodes, minimum=1)
        if self.batch is not None:
            _check_int("batch", self.batch, minimum=1)
        if self.checkpoint_every is not None:
            _check_int("checkpoint_every", self.checkpoint_every, minimum=1)
        if isinstance(self.space, dict):
            sp = space_from_dict(self.space, self.space_seed)
        else:
            sp = load_space(self.space, self.space_seed)
        sut = sut_lib.get(self.sut)
        r = self.resolved()
        if r.batch > sp.size and r.strategy == "grid":
            raise ValueError(f"batch={r.batch} exceeds the space's {sp.size} scenarios "
                             "(strategy 'grid' would repeat scenarios within one batch)")
        strat = search.make(r.strategy, sp.shape, r.batch, r.preset or "default")
        return sp, sut, strat, campaign.plan(r.episodes, r.batch, every=r.checkpoint_every)

    def to_toml(self, sp: Space) -> str:
        r = self.resolved()
        doc = {"strategy": r.strategy, "preset": r.preset, "sut": r.sut, "seed": r.seed,
               "episodes": r.episodes, "batch": r.batch, "space_seed": r.space_seed,
               "checkpoint_every": r.checkpoint_every, "space": sp.describe()}
        return cfg.dumps_toml(doc)


def _check_int(key: str, v, minimum: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ValueError(f"{key} must be an integer >= {minimum} (got {v!r})")


CONFIG_KEYS = {f.name for f in dataclasses.fields(RunConfig)}


def config_from_toml(path: Path) -> RunConfig:
    """Read a run's ``config.toml``; unknown keys and wrong types give one-line errors."""
    try:
        doc = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"--config {path}: no such file") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: malformed TOML: {e}") from None
    unknown = set(doc) - CONFIG_KEYS
    if unknown:
        raise ValueError(f"{path}: unknown key '{sorted(unknown)[0]}' "
                         f"(allowed: {', '.join(sorted(CONFIG_KEYS))})")
    for key in ("sut", "strategy", "preset"):
        if key in doc and not isinstance(doc[key], str):
            raise ValueError(f"{path}: {key} must be a string (got {doc[key]!r})")
    if "space" in doc and not isinstance(doc["space"], (str, dict)):
        raise ValueError(f"{path}: space must be a name, a path or a table")
    return RunConfig(**doc)


# ----------------------------------------------------------------------------- outputs
def episodes_table(res: campaign.Result) -> dict[str, np.ndarray]:
    cols: dict[str, np.ndarray] = {"evaluation": res.evaluation, "update": res.update}
    for p, name in enumerate(res.space.names):
        cols[f"{name}_idx"] = res.indices[:, p]
    for p, name in enumerate(res.space.names):
        cols[name] = res.space.values[p][res.indices[:, p]]
    cols.update(res.fields)
    return cols


def summary_dict(res: campaign.Result, rc: RunConfig) -> dict:
    r = rc.resolved()
    b = campaign.best_index(res)
    crit = campaign.distinct_critical(res)
    best = {"params": campaign.scenario_values(res.space, res.indices[b]),
            "indices": [int(i) for i in res.indices[b]], "evaluation": b + 1,
            **{k: res.fields[k][b].item() for k in
               ("reward", "collision", "min_distance", "final_distance",
                "high_risk_share_second_half")}}
    return {"strategy": r.strategy, "preset": r.preset, "space": res.space.name,
            "space_seed": r.space_seed, "sut": r.sut, "seed": r.seed,
            "evaluations": res.n, "batch": r.batch,
            "first_collision_evaluation": campaign.first_collision_evaluation(res),
            "n_collisions": int(np.sum(res.fields["collision"])),
            "n_distinct_critical": len(crit),
            "n_nonfinite": int(np.sum(res.fields["nonfinite"])),
            "best": best, "convergence_evaluation": campaign.convergence_evaluation(res),
            "versions": cfg.versions()}


def critical_csv(res: campaign.Result) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    names = list(res.space.names)
    w.writerow(["rank", *names, "reward", "min_distance", "high_risk_share_second_half",
                "first_evaluation", "times_evaluated"])
    for rank, c in enumerate(campaign.distinct_critical(res), 1):
        vals = campaign.scenario_values(res.space, c["indices"])
        w.writerow([rank, *(f"{vals[n]:g}" for n in names), f"{c['reward']:.6f}",
                    f"{c['min_distance']:.4f}", f"{c['high_risk_share_second_half']:.4f}",
                    c["first_evaluation"], c["times_evaluated"]])
    return buf.getvalue()


RESULT_FILES = ("episodes.parquet", "summary.json", "critical.csv", "timing.json",
                "report.md", "best.rrd")


def checkpoint_for(out: Path, rc: RunConfig, p: campaign.Plan, sp: Space):
    """The run's checkpoint folder, fingerprinted by the resolved config and the plan."""
    from jaxfalsify.checkpoint import CampaignCheckpoint

    fp = {"config": rc.to_toml(sp), "plan": list(p)}
    return CampaignCheckpoint(out / "checkpoint", json.loads(json.dumps(fp)))


def write_status(out: Path, state: str, **extra) -> None:
    doc = {"state": state, **extra}
    if state != "complete":
        doc["resume"] = f"jaxfalsify run --resume {out}"
    cfg.write_atomic(out / "status.json", json.dumps(cfg.jsonable(doc), indent=2) + "\n")


def start_run(out: Path, rc: RunConfig, sp: Space, budget: int, force: bool) -> None:
    """Create the run folder with config.toml and status.json; with ``force``, first remove
    an earlier run's results and checkpoint from it."""
    import shutil

    if force:
        for name in RESULT_FILES + ("status.json", "config.toml"):
            (out / name).unlink(missing_ok=True)
        for name in ("checkpoint", "figures"):
            shutil.rmtree(out / name, ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    cfg.write_atomic(out / "config.toml", rc.to_toml(sp))
    write_status(out, "running", budget=budget)


def write_run(out: Path, res: campaign.Result, rc: RunConfig,
              resumed_from: int = 0) -> dict:
    """Write the run's results (atomically), mark it complete and drop its checkpoint;
    returns the summary."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    out.mkdir(parents=True, exist_ok=True)
    tmp = out / ".episodes.parquet.partial"
    pq.write_table(pa.table(episodes_table(res)), tmp)
    summary = summary_dict(res, rc)
    timing = {"wall_seconds": res.wall_seconds, "compile_seconds": res.compile_seconds,
              "resumed_from_evaluation": resumed_from}
    cfg.write_atomic(out / "config.toml", rc.to_toml(res.space))
    cfg.write_atomic(out / "critical.csv", critical_csv(res))
    tmp.replace(out / "episodes.parquet")
    cfg.write_atomic(out / "timing.json", json.dumps(cfg.jsonable(timing), indent=2) + "\n")
    cfg.write_atomic(out / "summary.json", json.dumps(cfg.jsonable(summary), indent=2) + "\n")
    write_status(out, "complete", evaluations_done=res.n, budget=res.n)
    shutil.rmtree(out / "checkpoint", ignore_errors=True)
    return {**summary, **timing}


def closing_report(res: campaign.Result, summary: dict) -> str:
    """The best critical scenario beside a typical non-critical one (paper Table II layout)."""
    b = campaign.best_index(res)
    t = campaign.typical_non_critical(res)
    names = res.space.names
    units = dict(zip(names, res.space.units))
    best_vals = campaign.scenario_values(res.space, res.indices[b])
    typ_vals = campaign.scenario_values(res.space, res.indices[t]) if t is not None else {}
    head = "Challenging (best)" if res.fields["collision"][b] else "Best (no collision)"
    lines = [f"{'parameter':<28}{head:>20}{'Non-challenging':>20}"]
    for n in names:
        u = f" {units[n]}" if units[n] in ("m", "m/s") else ""
        typ = f"{typ_vals[n]:.3f}{u}" if t is not None else "-"
        lines.append(f"{n:<28}{f'{best_vals[n]:.3f}{u}':>20}{typ:>20}")
    for f, fmt in (("reward", ".4f"), ("collision", ""), ("min_distance", ".2f"),
                   ("high_risk_share_second_half", ".2f")):
        bv = format(res.fields[f][b].item(), fmt)
        tv = format(res.fields[f][t].item(), fmt) if t is not None else "-"
        lines.append(f"{f:<28}{bv:>20}{tv:>20}")
    fc = summary["first_collision_evaluation"]
    lines.append("")
    lines.append(f"{summary['evaluations']} evaluations, {summary['n_collisions']} collisions, "
                 f"{summary['n_distinct_critical']} distinct critical scenarios; first collision "
                 f"at evaluation {fc if fc is not None else '-'}; best reward reached at "
                 f"{summary['best']['evaluation']}, converged at "
                 f"{summary['convergence_evaluation']}; {summary['wall_seconds']:.1f} s "
                 f"({summary['compile_seconds']:.1f} s compile)")
    return "\n".join(lines)


def default_run_dir(strategy: str) -> Path:
    return Path("runs") / f"{time.strftime('%Y%m%d-%H%M%S')}-{strategy}"
