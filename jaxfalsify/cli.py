"""Command line: ``jaxfalsify run`` (the main job: a falsification campaign), ``compare``,
``sweep`` (exhaustive ground truth) and ``simulate`` (one concrete scenario).

Bad input prints one line ``jaxfalsify: error: ...`` naming the offending flag or key and exits
with code 2, before anything is written.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2
        raise UsageError(message)


class UsageError(Exception):
    pass


def _positive_int(name):
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be an integer (got {text!r})")
        if v <= 0:
            raise argparse.ArgumentTypeError(f"{name} must be positive (got {v})")
        return v
    return parse


def _seed(text):
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--seed must be a non-negative integer (got {text!r})")
    if v < 0:
        raise argparse.ArgumentTypeError(f"--seed must be a non-negative integer (got {v})")
    return v


def _distributed_flags(p) -> None:
    g = p.add_argument_group("multi-process (jax.distributed)")
    g.add_argument("--distributed", action="store_true",
                   help="one of several processes; each evaluates its share and writes a part")
    g.add_argument("--coordinator", help="HOST:PORT of process 0 (or JAX_COORDINATOR_ADDRESS)")
    g.add_argument("--num-processes", type=_positive_int("--num-processes"),
                   dest="num_processes", help="(or JAX_NUM_PROCESSES)")
    g.add_argument("--process-id", type=_seed, dest="process_id", help="(or JAX_PROCESS_ID)")


def _start_distributed(args) -> tuple[int, int]:
    if not args.distributed:
        if args.coordinator or args.num_processes or args.process_id is not None:
            raise UsageError("--coordinator/--num-processes/--process-id need --distributed")
        return 0, 1
    from jaxfalsify.distributed import initialize

    try:
        return initialize(args.coordinator, args.num_processes, args.process_id)
    except ValueError as e:
        raise UsageError(str(e)) from None


def build_parser() -> argparse.ArgumentParser:
    from jaxfalsify.sut import SUTS

    p = _Parser(prog="jaxfalsify", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="falsification campaign (the main job); no arguments: the "
                       "paper space, carla-tm, reinforce/default, seed 0, 4000 evaluations")
    r.add_argument("--config", type=Path, help="a run's config.toml to repeat; flags override it")
    r.add_argument("--space", help="built-in name or TOML file (default paper)")
    r.add_argument("--space-seed", type=_seed, dest="space_seed",
                   help="discretisation seed of the space (default 0)")
    r.add_argument("--sut", help=f"system under test: {', '.join(SUTS)} (default carla-tm)")
    r.add_argument("--strategy", help="random, grid, cem, anneal, cmaes, reinforce "
                   "(default reinforce)")
    r.add_argument("--preset", help="reinforce preset: paper or default (default default)")
    r.add_argument("--episodes", type=_positive_int("--episodes"),
                   help="budget in evaluated scenarios (default 4000, the paper's)")
    r.add_argument("--batch", type=_positive_int("--batch"), help="scenarios per update")
    r.add_argument("--seed", type=_seed, help="search seed (default 0)")
    r.add_argument("--out", type=Path, help="run folder (default runs/<timestamp>-<strategy>)")
    r.add_argument("--force", action="store_true", help="overwrite an existing run folder")
    r.add_argument("--quiet", action="store_true", help="no progress bar or report")
    r.add_argument("--no-figures", action="store_true", dest="no_figures",
                   help="skip figures/ and report.md")
    r.add_argument("--rerun", action="store_true", help="also save best.rrd (rerun recording)")
    r.add_argument("--resume", type=Path, metavar="RUN_DIR",
                   help="continue an interrupted run from its last checkpoint (its config.toml "
                   "is used; only --quiet, --no-figures and --rerun may be added)")
    r.add_argument("--checkpoint-every", type=_positive_int("--checkpoint-every"),
                   dest="checkpoint_every", help="updates between checkpoints, rounded down to "
                   "a divisor of the number of updates (default: about 1/20 of the run)")

    c = sub.add_parser("compare", help="all strategies x seeds vs the exhaustive sweep")
    c.add_argument("--strategies", default="reinforce,random,cem,anneal,cmaes",
                   help="comma-separated; reinforce/paper or reinforce/default picks a preset")
    c.add_argument("--seeds", type=_positive_int("--seeds"), default=10)
    c.add_argument("--budget", type=_positive_int("--budget"), default=4000)
    c.add_argument("--space", default="paper")
    c.add_argument("--space-seed", type=_seed, default=0, dest="space_seed")
    c.add_argument("--sut", default="carla-tm")
    c.add_argument("--preset", default="default", help="reinforce preset (default default)")
    c.add_argument("--sweep", type=Path, help="sweep folder to use as ground truth (default "
                   "sweeps/<space>-<sut>-s<space-seed>, run if missing)")
    c.add_argument("--out", type=Path, help="folder for compare.json/.md "
                   "(default runs/compare-<timestamp>)")
    c.add_argument("--force", action="store_true")
    _distributed_flags(c)

    pl = sub.add_parser("replay", help="rerun recording of a run's scenario")
    pl.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    pl.add_argument("--scenario", default="best", help="best, critical:K or eval:N")
    g = pl.add_mutually_exclusive_group()
    g.add_argument("--save", type=Path, help="write FILE.rrd (default RUN_DIR/replay-<scenario>.rrd)")
    g.add_argument("--spawn", action="store_true", help="open a rerun viewer instead")
    pl.add_argument("--scenarios", type=_positive_int("--scenarios"), default=0,
                    help="also overlay the distance of K evaluated scenarios (paper Fig. 10)")

    x = sub.add_parser("export", help="OpenSCENARIO (.xosc) + OpenDRIVE (.xodr) of a run's "
                       "scenarios")
    x.add_argument("run_dir", type=Path, metavar="RUN_DIR")
    x.add_argument("--scenario", default="best", help="best or critical (all distinct ones)")
    x.add_argument("--out", type=Path, required=True, help="output folder")
    x.add_argument("--force", action="store_true", help="overwrite existing files in --out")

    f = sub.add_parser("figures", help="(re)draw a run's figures and report.md")
    f.add_argument("run_dir", type=Path, metavar="RUN_DIR")

    s = sub.add_parser("sweep", help="evaluate every concrete scenario of a space")
    s.add_argument("--space", help="built-in name (paper, paper-extended) or a TOML file "
                   "(default: paper)")
    s.add_argument("--seed", type=_seed, help="discretisation seed (default 0)")
    s.add_argument("--sut", help=f"system under test: {', '.join(SUTS)} (default carla-tm)")
    s.add_argument("--out", type=Path, default=None,
                   help="output folder (default sweeps/<space>-<sut>-s<seed>)")
    s.add_argument("--chunk", type=_positive_int("--chunk"),
                   help=f"most scenarios per compiled batch (default {1 << 17})")
    s.add_argument("--force", action="store_true", help="overwrite an existing sweep in --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.add_argument("--rows", choices=("all", "collisions", "none"),
                   help="scenarios written to Parquet (default all; none: summary only)")
    s.add_argument("--resume", type=Path, metavar="OUT",
                   help="continue an interrupted sweep in OUT (its config.toml is used)")
    _distributed_flags(s)

    m = sub.add_parser("simulate", help="evaluate one concrete scenario and print its outcome")
    m.add_argument("params", nargs="*", metavar="NAME=VALUE",
                   help="scenario parameters, e.g. ego_offset=9 ped_speed=1.237")
    m.add_argument("--sut", default="carla-tm")
    return p


def _check_out(out: Path, marker: str, force: bool) -> None:
    """Refuse an --out that is not a folder, holds finished results (without --force), or
    cannot be written (probed by creating and removing a temporary file)."""
    import tempfile

    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a folder")
    if (out / marker).exists() and not force:
        raise UsageError(f"--out {out} already holds {marker}; pass --force to overwrite")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    if not parent.is_dir():
        raise UsageError(f"--out {out}: {parent} is not a folder")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise UsageError(f"--out {out}: cannot write in {parent} ({e.strerror})") from None


def _check_unfinished(out: Path, force: bool, command: str) -> None:
    if not force and ((out / "checkpoint").exists() or (out / "status.json").exists()
                      or any(out.glob("checkpoint*"))):
        raise UsageError(f"--out {out} holds an unfinished {command}; pass --resume {out} to "
                         "continue it or --force to start over")


SWEEP_FLAGS = ("space", "seed", "sut", "chunk", "rows", "out")


def _sweep_config(args):
    """``(space, sut, out, chunk, rows, processes)`` from --resume OUT's config.toml (processes:
    how many it ran on) or from the flags (processes None)."""
    import tomllib

    from jaxfalsify import sut as sut_lib
    from jaxfalsify.space import space as load_space, space_from_dict

    if args.resume is None:
        sp = load_space(args.space or "paper", seed=args.seed or 0)
        sut = sut_lib.get(args.sut or "carla-tm")
        out = args.out or Path("sweeps") / f"{Path(sp.name).stem}-{sut.name}-s{sp.seed}"
        return sp, sut, out, args.chunk or (1 << 17), args.rows or "all", None
    given = [k for k in SWEEP_FLAGS if getattr(args, k) is not None]
    if given or args.force:
        flag = "--" + (given[0] if given else "force")
        raise UsageError(f"{flag} cannot be combined with --resume (the sweep's own "
                         "config.toml is used)")
    out = args.resume
    path = out / "config.toml"
    if not path.is_file():
        raise UsageError(f"--resume {out}: no config.toml there (not a sweep folder)")
    if (out / "summary.json").exists():
        raise UsageError(f"--resume {out}: the sweep is already complete (summary.json)")
    try:
        doc = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: malformed TOML: {e}") from None
    if doc.get("command") != "sweep":
        raise UsageError(f"--resume {out}: {path} is not a sweep's config")
    try:
        sp = space_from_dict(doc["space"], doc["seed"])
        sut = sut_lib.get(doc["sut"])
        chunk, rows = int(doc["chunk"]), doc["rows"]
    except KeyError as e:
        raise UsageError(f"{path}: missing key {e}") from None
    except (TypeError, ValueError) as e:
        raise UsageError(f"{path}: {e}") from None
    return sp, sut, out, chunk, rows, doc.get("processes", 1)


def cmd_sweep(args) -> int:
    from tqdm import tqdm

    from jaxfalsify.checkpoint import CheckpointError
    from jaxfalsify.sweep import check_resume, run_sweep

    try:
        sp, sut, out, chunk, rows, procs = _sweep_config(args)
    except ValueError as e:
        raise UsageError(str(e)) from None
    if args.resume is None:
        _check_out(out, "summary.json", args.force)
        _check_unfinished(out, args.force, "sweep")
    pid, n_proc = _start_distributed(args)
    from jaxfalsify.distributed import share
    begin, end = share(sp.size, pid, n_proc)
    if args.resume is not None:
        if procs != n_proc:
            raise UsageError(f"--resume {out}: the sweep ran on {procs} process(es), this is "
                             f"{n_proc}; resume it with the same number")
        try:
            check_resume(sp, sut.name, out, chunk, rows, pid, n_proc)
        except CheckpointError as e:
            raise UsageError(f"{e}; start over with --force --out {out}") from None
    bar = tqdm(total=end - begin, unit="scn", unit_scale=True, disable=args.quiet,
               desc=f"sweep {sp.name} / {sut.name}"
               + (f" [process {pid}/{n_proc}]" if n_proc > 1 else ""))
    try:
        summary = run_sweep(sp, sut.name, out, chunk=chunk, progress=bar.update,
                            process_id=pid, num_processes=n_proc, rows=rows,
                            resume=args.resume is not None)
    except KeyboardInterrupt:
        bar.close()
        done = check_resume(sp, sut.name, out, chunk, rows, pid, n_proc)
        print(f"jaxfalsify: interrupted after {done} of {end - begin} scenarios; {out} is "
              f"resumable: jaxfalsify sweep --resume {out}", file=sys.stderr)
        return 130
    finally:
        bar.close()
    if pid != 0:
        print(f"process {pid}: done ({out})")
        return 0
    best = summary["global_max_scenario"] or {}
    print(f"{summary['n_scenarios']} scenarios, {summary['n_collisions']} collisions "
          f"({100 * summary['collision_rate']:.2f} %) in {summary['wall_seconds']:.2f} s "
          f"(compile {summary['compile_seconds']:.2f} s)")
    print(f"global maximum reward {summary['global_max_reward']:.4f} at "
          + ", ".join(f"{k}={v:g}" for k, v in best.get("values", {}).items()))
    print(f"wrote {out}/{', '.join(summary['parts'] + ['summary.json', 'timing.json', 'config.toml'])}")
    return 0


RUN_FLAGS = ("space", "space_seed", "sut", "strategy", "preset", "episodes", "batch", "seed",
             "checkpoint_every")


def _run_config(args):
    """The run's config and folder: from --resume RUN_DIR, or from --config and flags."""
    from jaxfalsify.runs import RunConfig, config_from_toml, default_run_dir

    if args.resume is not None:
        given = [k for k in RUN_FLAGS + ("config", "out") if getattr(args, k) is not None]
        if given or args.force:
            flag = "--" + (given[0].replace("_", "-") if given else "force")
            raise UsageError(f"{flag} cannot be combined with --resume (the run's own "
                             "config.toml is used)")
        out = args.resume
        if not (out / "config.toml").is_file():
            raise UsageError(f"--resume {out}: no config.toml there (not a run folder)")
        if (out / "summary.json").exists():
            raise UsageError(f"--resume {out}: the run is already complete (summary.json)")
        return config_from_toml(out / "config.toml"), out
    base = config_from_toml(args.config) if args.config else RunConfig()
    flags = {k: getattr(args, k) for k in RUN_FLAGS if getattr(args, k) is not None}
    if "space" in flags and args.config:
        flags.setdefault("space_seed", base.space_seed)
    rc = dataclasses.replace(base, **flags)
    if rc.strategy != "reinforce" and "preset" in flags:
        raise ValueError(f"--preset applies to strategy 'reinforce', not '{rc.strategy}'")
    return rc, args.out or default_run_dir(rc.resolved().strategy)


def cmd_run(args) -> int:
    from tqdm import tqdm

    from jaxfalsify import campaign
    from jaxfalsify.checkpoint import CheckpointError
    from jaxfalsify.runs import checkpoint_for, closing_report, start_run, write_run, \
        write_status

    try:
        rc, out = _run_config(args)
        sp, sut, strat, plan = rc.build()
    except ValueError as e:
        raise UsageError(str(e)) from None
    rc = rc.resolved()
    ckpt = checkpoint_for(out, rc, plan, sp)
    resumed = None
    if args.resume is not None:
        try:
            resumed = campaign.restore(ckpt, sp, sut, strat, plan, rc.seed)
        except CheckpointError as e:
            raise UsageError(f"{e}; start over with --force --out {out}") from None
    else:
        _check_out(out, "summary.json", args.force)
        _check_unfinished(out, args.force, "run")
    start_from = sum(len(r["reward"].reshape(-1)) for r in resumed[1]) if resumed else 0
    start_from = min(start_from, plan.budget)
    if resumed is None:
        start_run(out, rc, sp, plan.budget, args.force)
    else:
        write_status(out, "running", budget=plan.budget, resumed_from_evaluation=start_from)
        if not args.quiet:
            print(f"resuming {out} at evaluation {start_from} of {plan.budget}")
    bar = tqdm(total=plan.budget, unit="eval", disable=args.quiet,
               desc=f"{rc.strategy}{'/' + rc.preset if rc.preset else ''} on {sp.name}")

    def progress(done, records):
        fresh = records[progress.seen:]
        progress.seen = len(records)
        for rec in fresh:
            r = np.where(np.isnan(rec["reward"]), -np.inf, rec["reward"])
            progress.best = max(progress.best, float(r.max()))
            progress.collisions += int(np.sum(rec["collision"]))
        bar.set_postfix(best=f"{progress.best:.4f}", collisions=progress.collisions)
        bar.update(done - bar.n)

    progress.best, progress.collisions, progress.seen = -np.inf, 0, 0
    try:
        res = campaign.run(sp, sut, strat, plan, rc.seed, progress=progress, checkpoint=ckpt,
                           resumed=resumed)
    except KeyboardInterrupt:
        bar.close()
        done = ckpt.evaluations_done()
        write_status(out, "interrupted", evaluations_done=done, budget=plan.budget)
        print(f"jaxfalsify: interrupted after {done} of {plan.budget} evaluations; "
              f"{out} is resumable: jaxfalsify run --resume {out}", file=sys.stderr)
        return 130
    finally:
        bar.close()
    summary = write_run(out, res, rc, resumed_from=start_from)
    if not args.quiet:
        print(closing_report(res, summary))
    extra = ""
    if not args.no_figures:
        from jaxfalsify.figures import make_figures
        from jaxfalsify.report import write_report
        make_figures(out)
        write_report(out)
        extra = ", figures/, report.md"
    if args.rerun:
        from jaxfalsify.replay import record
        record(out, "best", save=out / "best.rrd", overlay=14)
        extra += ", best.rrd"
    print(f"wrote {out}/ (config.toml, episodes.parquet, summary.json, critical.csv, "
          f"timing.json{extra})")
    return 0


def cmd_replay(args) -> int:
    from jaxfalsify.replay import record

    if args.save is not None and args.save.suffix != ".rrd":
        raise UsageError(f"--save {args.save}: the file name must end in .rrd")
    try:
        path = record(args.run_dir, args.scenario, save=args.save, spawn=args.spawn,
                      overlay=args.scenarios)
    except ValueError as e:
        raise UsageError(str(e)) from None
    print(f"wrote {path}" if path else "sent to the rerun viewer")
    return 0


def cmd_export(args) -> int:
    from jaxfalsify.export import export

    if args.scenario not in ("best", "critical"):
        raise UsageError(f"--scenario {args.scenario!r}: expected best or critical")
    _check_out(args.out, "crossing.xodr", args.force)
    try:
        files = export(args.run_dir, args.out, args.scenario)
    except ValueError as e:
        raise UsageError(str(e)) from None
    print(f"wrote {len(files) - 1} .xosc and crossing.xodr to {args.out}/")
    return 0


def cmd_figures(args) -> int:
    from jaxfalsify.figures import make_figures
    from jaxfalsify.report import write_report

    try:
        files = make_figures(args.run_dir)
    except ValueError as e:
        raise UsageError(str(e)) from None
    report = write_report(args.run_dir)
    print(f"wrote {len(files)} figures to {args.run_dir}/figures/ and {report}")
    return 0


def cmd_compare(args) -> int:
    import time

    from jaxfalsify import compare
    from jaxfalsify.config import jsonable, write_atomic
    from jaxfalsify.runs import RunConfig
    from jaxfalsify.search import STRATEGIES

    names = [s.strip() for s in args.strategies.split(",") if s.strip()]
    bad = [n for n in names if n.split("/")[0] not in STRATEGIES
           or ("/" in n and not n.startswith("reinforce/"))]
    if bad or not names:
        raise UsageError(f"--strategies: unknown strategy '{bad[0] if bad else ''}' "
                         f"(from {', '.join(STRATEGIES)})")
    if args.distributed and not args.out:
        raise UsageError("compare --distributed needs --out (a folder all processes share)")
    pid, n_proc = _start_distributed(args)  # before anything touches the JAX backend
    base = RunConfig(space=args.space, space_seed=args.space_seed, sut=args.sut,
                     preset=args.preset, episodes=args.budget)
    try:
        base.build()
        from jaxfalsify.reinforce import get_preset
        get_preset(args.preset)
    except ValueError as e:
        raise UsageError(str(e)) from None
    out = args.out or Path("runs") / f"compare-{time.strftime('%Y%m%d-%H%M%S')}"
    _check_out(out, "compare.json", args.force)
    result = compare.run_compare(names, args.seeds, args.budget, base, args.sweep,
                                 progress=lambda row: print(f"  {row['strategy']}: done in "
                                                            f"{row['wall_seconds']:.1f} s",
                                                            flush=True),
                                 process_id=pid, num_processes=n_proc, out_dir=out)
    if pid != 0:
        print(f"process {pid}: done")
        return 0
    table = compare.table_markdown(result)
    print(f"{result['space']} space, {result['sut']}, budget {args.budget}, {args.seeds} seeds; "
          f"global max reward {result['global_max_reward']:.4f}, "
          f"{result['all_critical']} critical of {result['n_scenarios']} scenarios")
    print(table)
    out.mkdir(parents=True, exist_ok=True)
    write_atomic(out / "compare.json", json.dumps(jsonable(result), indent=2) + "\n")
    write_atomic(out / "compare.md", table + "\n")
    print(f"wrote {out}/compare.json, compare.md")
    return 0


def cmd_simulate(args) -> int:
    import numpy as np

    import jaxfalsify as jf
    from jaxfalsify.space import KNOWN_PARAMETERS

    scenario = {}
    for item in args.params:
        name, eq, value = item.partition("=")
        if not eq:
            raise UsageError(f"expected NAME=VALUE, got {item!r}")
        if name not in KNOWN_PARAMETERS:
            raise UsageError(f"unknown parameter '{name}' (known: {', '.join(KNOWN_PARAMETERS)})")
        try:
            scenario[name] = float(value)
        except ValueError:
            raise UsageError(f"{name}={value!r} is not a number") from None
        if not np.isfinite(scenario[name]):
            raise UsageError(f"{name}={value} is not finite")
    try:
        out = jf.evaluate(scenario, sut=args.sut)
    except ValueError as e:
        raise UsageError(str(e)) from None
    from jaxfalsify.config import jsonable
    print(json.dumps(jsonable({k: np.asarray(v).item() for k, v in vars(out).items()}), indent=2))
    return 0


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        handler = {"run": cmd_run, "compare": cmd_compare, "figures": cmd_figures,
                   "replay": cmd_replay, "export": cmd_export,
                   "sweep": cmd_sweep, "simulate": cmd_simulate}[args.command]
        return handler(args)
    except UsageError as e:
        print(f"jaxfalsify: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxfalsify: interrupted; nothing was written in place of earlier results",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
