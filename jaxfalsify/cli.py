"""The ``jaxfalsify`` command: a thin shell over the library.

One concern: turning the command line into library calls (flags, help,
exit codes); no job logic lives here.

Each subcommand maps its flags to a config (``runs.RunConfig``, ``sweep_config.SweepConfig``,
``compare.CompareConfig``) and calls the library's ``execute``; exceptions become one line
``jaxfalsify: error: ...`` and an exit code: 2 for bad input (nothing written), 130 / 143 after
SIGINT / SIGTERM (work committed, resumable), 1 for a failed write (disk full, permissions).
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import signal
import sys
from pathlib import Path

__all__ = ["build_parser", "main", "entry"]

DESCRIPTION = ("JAX-accelerated, batched scenario-based falsification: search a logical "
               "scenario for the concrete scenarios in which a system under test collides.")


class UsageError(Exception):
    pass


class _StoreOnce(argparse.Action):
    """An option that takes one value: given twice (``--seed 1 --seed 2``) it is refused
    instead of the last one silently winning."""

    def __call__(self, parser, namespace, values, option_string=None):
        seen = namespace.__dict__.setdefault("_given_once", set())
        if self.dest in seen:
            parser.error(f"{option_string} given twice")
        seen.add(self.dest)
        setattr(namespace, self.dest, values)


class _Parser(argparse.ArgumentParser):
    def __init__(self, *args, **kwargs):
        # no prefixes of long flags: ``compare --seed 3`` must not mean ``--seeds 3``
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)
        for name in (None, "store"):  # every option of one value, in groups too
            self.register("action", name, _StoreOnce)

    def error(self, message):  # one line, exit 2
        raise UsageError(message)


POSITIONALS = {"params": "NAME=VALUE", "run_dir": "RUN_DIR"}  # named so in errors


def parse(argv=None) -> argparse.Namespace:
    """The command line parsed; ``simulate``'s NAME=VALUE may also follow its options."""
    args, extra = build_parser().parse_known_args(argv)
    if args.command == "simulate":
        values = [a for a in extra if "=" in a and not a.startswith("-")]
        args.params = list(args.params) + values
        extra = [a for a in extra if a not in values]
    if extra:
        raise UsageError(f"unrecognized arguments: {' '.join(extra)}")
    vars(args).pop("_given_once", None)
    for name, value in vars(args).items():
        values = value if isinstance(value, list) else [value]
        for v in (str(x) for x in values if isinstance(x, (str, Path))):
            flag = POSITIONALS.get(name, f"--{name.replace('_', '-')}")
            if isinstance(value, str) and not v.strip():  # names nothing: never a default
                raise UsageError(f"{flag} {v!r}: an empty value")
            if any(c < " " or c == "\x7f" for c in v):  # a name or path never holds one
                raise UsageError(f"{flag} {v!r}: a control character (a newline, a tab, ...) "
                                 "in a value")
    return args


def _int(name, minimum=0, maximum=None):
    def parse(text):
        # digits 0-9 only: Python's int() also reads '1_000' and other scripts' digits
        if not re.fullmatch(r"\s*[+-]?[0-9]+\s*", text):
            raise argparse.ArgumentTypeError(f"{name} must be an integer (got {text!r})")
        v = int(text)
        if v < minimum:
            raise argparse.ArgumentTypeError(f"{name} must be >= {minimum} (got {v})")
        if maximum is not None and v > maximum:
            raise argparse.ArgumentTypeError(f"{name} must be <= {maximum} (got {v})")
        return v
    return parse


def _float_positive(name):
    def parse(text):
        from jaxfalsify.base.config import parse_number

        v = parse_number(text)
        if v is None:
            raise argparse.ArgumentTypeError(f"{name} must be a number (got {text!r})")
        if not 0 < v < float("inf"):
            raise argparse.ArgumentTypeError(f"{name} must be > 0 and finite (got {text})")
        return v
    return parse


class StopFlag:
    """SIGINT / SIGTERM handlers that ask the running work to stop between chunks (a second
    signal interrupts at once)."""

    def __init__(self):
        self.signum = None

    def __call__(self) -> bool:
        return self.signum is not None

    def handler(self, signum, frame):
        if self.signum is not None:
            raise KeyboardInterrupt
        self.signum = signum

    def install(self):
        """Handle SIGINT and SIGTERM, except a signal this process inherited as ignored (a
        script's background job, ``cmd &``, ignores SIGINT: it keeps ignoring it)."""
        self.previous = {}
        for s in (signal.SIGINT, signal.SIGTERM):
            before = signal.getsignal(s)
            if before is signal.SIG_IGN:
                continue
            self.previous[s] = before
            signal.signal(s, self.handler)
        return self

    def restore(self) -> None:
        """The handlers from before :meth:`install`."""
        for s, before in getattr(self, "previous", {}).items():
            signal.signal(s, before if before is not None else signal.SIG_DFL)

    @property
    def exit_code(self) -> int:
        return 128 + (self.signum or signal.SIGINT)


def _path(text: str) -> Path:
    """A file or folder argument: a non-empty path (``Path('')`` is the working folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"an empty path ({text!r})")
    return Path(text)


def _folder(text: str) -> Path:
    """An output folder argument: a non-empty path (``--out ''`` would be the working folder)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty path (name a folder, e.g. runs/mine)")
    return Path(text)


def _add_requirement(p):
    from jaxfalsify.core.requirements import DEFAULT, REGISTRY

    p.add_argument("--requirement", help=f"what counts as a failure: {', '.join(REGISTRY)} or "
                   f"an import path module:attr / file.py:attr (default {DEFAULT})")
    p.add_argument("--requirement-param", action="append", dest="requirement_param",
                   metavar="NAME=VALUE", help="set a requirement parameter (repeatable)")


def _add_sut(p, many=False):
    from jaxfalsify.suts.registry import REGISTRY

    p.add_argument("--sut", help=f"system under test: {', '.join(REGISTRY)} or an import "
                   "path module:attr / file.py:attr (default carla-tm)")
    p.add_argument("--sut-param", action="append", dest="sut_param", metavar="NAME=VALUE",
                   help="set a SUT parameter (repeatable)" + (
                       "; NAME=V1,V2,... sweeps calibrations" if many else ""))


def _distributed_flags(p) -> None:
    g = p.add_argument_group("multi-process (jax.distributed)")
    g.add_argument("--distributed", action="store_true",
                   help="one of several processes; each evaluates its share and writes a part")
    g.add_argument("--coordinator", help="HOST:PORT of process 0 (or JAX_COORDINATOR_ADDRESS)")
    g.add_argument("--num-processes", type=_int("--num-processes", 1), dest="num_processes",
                   help="(or JAX_NUM_PROCESSES)")
    g.add_argument("--process-id", type=_int("--process-id"), dest="process_id",
                   help="(or JAX_PROCESS_ID)")
    g.add_argument("--coordinator-timeout", type=_float_positive("--coordinator-timeout"),
                   dest="coordinator_timeout", metavar="SECONDS",
                   help="how long to wait for the coordinator and the other processes "
                   "(default 120)")


def build_parser() -> argparse.ArgumentParser:
    from jaxfalsify import __version__, search
    from jaxfalsify.jobs.compare import DEFAULT_STRATEGIES

    p = _Parser(prog="jaxfalsify", description=DESCRIPTION)
    p.add_argument("--version", action="version", version=f"jaxfalsify {__version__}")
    p.add_argument("--no-cache", action="store_true", dest="no_cache",
                   help="no compilation or ground-truth cache (also JAXFALSIFY_NO_CACHE=1)")
    sub = p.add_subparsers(dest="command", required=True)
    strategies = ", ".join(search.names())

    r = sub.add_parser("run", help="falsification campaign (the main job); no arguments: the "
                       "paper space, carla-tm, reinforce/default, seed 0, 100 updates of 4096 "
                       "scenarios")
    r.add_argument("--config", type=_path, help="a run's config.toml to repeat; flags override it")
    r.add_argument("--space", help="built-in name (paper, paper-extended) or TOML file")
    r.add_argument("--space-seed", type=_int("--space-seed"), dest="space_seed",
                   help="discretisation seed of the space (default 0)")
    _add_sut(r)
    r.add_argument("--requirement", help="what counts as critical: collision (default), clash, "
                   "ttc, rss or an import path module:attr / file.py:attr; the search looks "
                   "for its violations")
    r.add_argument("--requirement-param", action="append", dest="requirement_param",
                   metavar="NAME=VALUE", help="set a requirement parameter (repeatable)")
    r.add_argument("--strategy", help=f"{strategies} (default reinforce/default)")
    r.add_argument("--strategy-param", action="append", dest="strategy_param",
                   metavar="NAME=VALUE", help="set a strategy option (repeatable)")
    r.add_argument("--evaluations", type=_int("--evaluations", 1),
                   help="budget in evaluated scenarios (default: the strategy's; "
                   "reinforce/default 409,600 = 100 updates of 4096, reinforce/paper and the "
                   "others the paper's 4000)")
    r.add_argument("--batch", type=_int("--batch", 1), help="scenarios per update (default: "
                   "the strategy's; reinforce/default 4096 on a CPU, 65,536 on a GPU)")
    r.add_argument("--seed", type=_int("--seed"), help="search seed (default 0)")
    r.add_argument("--checkpoint-every", type=_int("--checkpoint-every", 1, 10**9),
                   dest="checkpoint_every", help="updates between checkpoints (default: "
                   "about 1/20 of the run)")
    _evaluator_flags(r, "default strategy then reinforce/screened")
    r.add_argument("--out", type=_folder, help="run folder (default runs/<timestamp>-<strategy>)")
    r.add_argument("--force", action="store_true", help="overwrite an existing run folder")
    r.add_argument("--resume", type=_folder, metavar="RUN_DIR",
                   help="continue an interrupted run (its config.toml is used)")
    r.add_argument("--quiet", action="store_true", help="no progress or report")
    r.add_argument("--no-figures", action="store_true", dest="no_figures",
                   help="skip figures/ and report.md")
    r.add_argument("--rerun", action="store_true", help="also save best.rrd (rerun recording)")

    s = sub.add_parser("sweep", help="evaluate every concrete scenario of a space")
    s.add_argument("--space", help="built-in name or TOML file (default paper)")
    s.add_argument("--space-seed", type=_int("--space-seed"), dest="space_seed",
                   help="discretisation seed of the space (default 0)")
    _add_sut(s, many=True)
    s.add_argument("--seed", type=_int("--seed"),
                   help="seed of the SUT's randomness (default 0; built-ins are deterministic)")
    s.add_argument("--chunk", type=_int("--chunk", 1),
                   help="most scenarios per compiled batch (default 131072 on CPUs, "
                   "1048576 on GPUs/TPUs)")
    s.add_argument("--rows", choices=("all", "collisions", "none"),
                   help="scenarios written to Parquet (default all; none: summary only; "
                   "collisions: the critical ones, a requirement's violations with one)")
    s.add_argument("--requirement", help="also count this requirement's violations (clash, "
                   "ttc, rss or an import path): a violated column and n_violations")
    s.add_argument("--requirement-param", action="append", dest="requirement_param",
                   metavar="NAME=VALUE", help="set a requirement parameter (repeatable)")
    s.add_argument("--out", type=_folder, help="output folder (default "
                   "sweeps/<space>-<sut>-s<space-seed>)")
    s.add_argument("--force", action="store_true", help="overwrite an existing sweep in --out")
    s.add_argument("--resume", type=_folder, metavar="OUT",
                   help="continue an interrupted sweep (its config.toml is used)")
    s.add_argument("--quiet", action="store_true", help="no progress")
    _distributed_flags(s)

    c = sub.add_parser("compare", help="strategies x seeds against the exhaustive ground truth")
    c.add_argument("--strategies",
                   help=f"comma-separated (default {','.join(DEFAULT_STRATEGIES)})")
    c.add_argument("--seeds", type=_int("--seeds", 1), help="seeds 0..N-1 (default 10)")
    c.add_argument("--evaluations", type=_int("--evaluations", 1), default=None,
                   help="budget per strategy and seed (default 4000)")
    c.add_argument("--batch", type=_int("--batch", 1),
                   help="scenarios per update of every strategy (default: each strategy's "
                   "own), so that wall times compare at the same batch")
    c.add_argument("--budgets", help="also report at these budgets, comma-separated "
                   "(the first evaluations of the same runs)")
    c.add_argument("--suite", type=_path, metavar="FILE",
                   help="a benchmark suite (e.g. experiments/suite/suite.toml): every entry's "
                   "space and SUT, at every budget of the suite")
    c.add_argument("--entries", metavar="NAMES",
                   help="with --suite: only the entries of these spaces, comma-separated "
                   "(e.g. aeb-9e6,island-dash)")
    c.add_argument("--space", help="built-in name or TOML file (default paper)")
    c.add_argument("--space-seed", type=_int("--space-seed"), dest="space_seed",
                   help="discretisation seed of the space (default 0)")
    c.add_argument("--strategy-param", action="append", dest="strategy_param",
                   metavar="STRATEGY:NAME=VALUE",
                   help="an option of one strategy, e.g. cem:elite_frac=0.2 (repeatable)")
    _add_sut(c)
    c.add_argument("--requirement", help="what counts as critical: collision (default), clash, "
                   "ttc, rss or an import path; the ground truth and every search count its "
                   "violations")
    c.add_argument("--requirement-param", action="append", dest="requirement_param",
                   metavar="NAME=VALUE", help="set a requirement parameter (repeatable)")
    _evaluator_flags(c, "default strategies then reinforce/screened,random,cem; no ground "
                     "truth: evaluations and seconds to the first failure")
    c.add_argument("--out", type=_folder, help="folder for compare.json/.md "
                   "(default runs/compare-<timestamp>)")
    c.add_argument("--jobs", type=_int("--jobs", 1, 256),
                   help="strategies searched side by side (default: one per CPU core, at "
                   "most 4; results are the same, only wall times differ)")
    c.add_argument("--force", action="store_true", help="overwrite an existing comparison")
    c.add_argument("--quiet", action="store_true", help="no progress")
    _distributed_flags(c)

    m = sub.add_parser("simulate", help="evaluate one concrete scenario and print it with its "
                       "outcome")
    m.add_argument("params", nargs="*", metavar="NAME=VALUE",
                   help="scenario parameters, e.g. ego_offset=9 ped_speed=1.237")
    _add_sut(m)
    m.add_argument("--seed", type=_int("--seed"), default=0, help="seed of the SUT's randomness")

    pl = sub.add_parser("replay", help="rerun recording of a run's scenario")
    pl.add_argument("run_dir", type=_path, metavar="RUN_DIR")
    pl.add_argument("--scenario", default="best", help="best, critical:K or eval:N")
    g = pl.add_mutually_exclusive_group()
    g.add_argument("--save", type=_path, help="write FILE.rrd (default RUN_DIR/replay-<scenario>"
                   ".rrd, a derived file rewritten like the figures); an existing FILE only "
                   "with --force")
    g.add_argument("--spawn", action="store_true", help="open a rerun viewer instead")
    pl.add_argument("--scenarios", type=_int("--scenarios", 1), default=0,
                    help="also overlay the distance of K evaluated scenarios (paper Fig. 9)")
    pl.add_argument("--campaign", action="store_true",
                    help="record the whole search instead (default RUN_DIR/campaign.rrd): every "
                    "evaluation's outcome and values, the sampling distribution per update")
    pl.add_argument("--window", type=_int("--window", 1), default=None,
                    help="with --campaign: evaluations behind each sampling-distribution chart "
                    "(default 200)")
    pl.add_argument("--force", action="store_true", help="overwrite an existing --save FILE")

    x = sub.add_parser("export", help="OpenSCENARIO (.xosc) + OpenDRIVE (.xodr) of a run's "
                       "scenarios and its logical scenario (parameter distributions)")
    x.add_argument("run_dir", type=_path, metavar="RUN_DIR")
    x.add_argument("--scenario", default="best", help="best or critical (all distinct ones)")
    x.add_argument("--ego", default="controller",
                   help="controller (default: the ego gets its start, route and cruise "
                   "request; your controller drives it) or replay (it follows its simulated "
                   "trajectory)")
    x.add_argument("--out", type=_folder, required=True, help="output folder")
    x.add_argument("--force", action="store_true", help="overwrite existing files in --out")

    e = sub.add_parser("estimate", help="how often the SUT violates a requirement under the "
                       "space's distribution, with a confidence interval")
    e.add_argument("--space", help="built-in name or TOML file (default paper)")
    e.add_argument("--space-seed", type=_int("--space-seed"), dest="space_seed",
                   help="discretisation seed of the space (default 0)")
    _add_sut(e)
    _add_requirement(e)
    e.add_argument("--method", choices=("is", "mc", "exact"), help="is: importance sampling "
                   "with a cross-entropy proposal (default); mc: naive Monte Carlo; exact: "
                   "every scenario evaluated (spaces up to 2**31 - 1)")
    e.add_argument("--target-rel-error", type=_float_positive("--target-rel-error"),
                   dest="target_rel_error", help="stop when the interval's half-width is at "
                   "most this share of the estimate (default 0.1)")
    e.add_argument("--samples", type=_int("--samples", 1),
                   help="most draws of the final stage (default 10,000,000)")
    e.add_argument("--batch", type=_int("--batch", 1),
                   help="draws per compiled call (default 65536)")
    e.add_argument("--confidence", type=_float_positive("--confidence"),
                   help="of the interval, in (0, 1) (default 0.95)")
    e.add_argument("--seed", type=_int("--seed"), help="seed of the draws (default 0)")
    e.add_argument("--out", type=_folder, help="output folder: config.toml, summary.json "
                   "(default estimates/<space>-<sut>-<requirement>-<method>-s<seed>)")
    e.add_argument("--force", action="store_true", help="overwrite an estimate in --out")
    e.add_argument("--quiet", action="store_true", help="no progress")

    f = sub.add_parser("figures", help="(re)draw a run's figures and report.md")
    f.add_argument("run_dir", type=_path, metavar="RUN_DIR")
    return p


def _progress(quiet: bool):
    from jaxfalsify.base.progress import Bar, Progress

    return Progress() if quiet else Bar()


def _assignments(items, flag, many=False):
    from jaxfalsify.base.config import parse_assignments

    return parse_assignments(items, flag, many)


def _sut_values(items, flag="--sut-param") -> dict:
    """``--sut-param NAME=VALUE`` for one calibration (``run``, ``compare``, ``simulate``):
    numbers only, a list of values refused with a pointer to ``sweep``."""
    out = _assignments(items, flag)
    for k, v in out.items():
        if isinstance(v, str):
            hint = ("" if "," not in v else
                    " (one number: only sweep's --sut-param takes a list of values)"
                    if flag == "--requirement-param" else
                    f" (a list of values is for sweep: jaxfalsify sweep --sut-param {k}={v})")
            raise UsageError(f"{flag + ' ' if flag else ''}{k}={v!r} is not a number{hint}")
    return out


def _evaluator_flags(p, default_note: str) -> None:
    p.add_argument("--evaluator", metavar="MODULE:ATTR",
                   help="evaluate the scenarios with this host function instead of the JAX "
                   "simulator (a system outside JAX: module:attr or file.py:attr taking a dict "
                   f"of parameter arrays, returning robustness); {default_note}")
    p.add_argument("--workers", type=_int("--workers", 1, 256),
                   help="evaluator processes (default: the CPU cores)")
    p.add_argument("--timeout", type=_float_positive("--timeout"),
                   help="seconds an evaluator may take per scenario (default: no limit)")
    p.add_argument("--retries", type=_int("--retries", 0, 100),
                   help="further tries of a scenario whose evaluation failed (default 1)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="run the evaluator on a Dask cluster (tcp://host:8786) instead of local "
                   "processes (pip install 'jaxfalsify[cluster]')")


EVALUATOR_FLAGS = ("workers", "timeout", "retries", "scheduler")


def _per_strategy(items) -> dict:
    """``["cem:elite_frac=0.2", ...]`` -> ``{"cem": {"elite_frac": 0.2}}``."""
    out: dict = {}
    for item in items or ():
        name, sep, assignment = item.partition(":")
        if not sep or not name.strip():
            raise UsageError(f"--strategy-param {item!r}: expected STRATEGY:NAME=VALUE, "
                             "e.g. cem:elite_frac=0.2")
        mine = out.setdefault(name.strip(), {})
        for k, v in _assignments([assignment], "--strategy-param").items():
            if k in mine:
                raise UsageError(f"--strategy-param {name.strip()}:{k} given twice")
            mine[k] = v
    return out


def _no_flags_with_resume(args, names):
    given = [n for n in names if getattr(args, n, None) not in (None, False)]
    if given:
        raise UsageError(f"--{given[0].replace('_', '-')} cannot be combined with --resume "
                         "(the folder's own config.toml is used)")


def cmd_run(args, stop, startup) -> int:
    from jaxfalsify.jobs import runs

    if args.resume is not None:
        _no_flags_with_resume(args, runs.SETTINGS + ("config", "out", "force", "sut_param",
                                                 "strategy_param", "requirement_param"))
        rc, out = runs.resume_config(args.resume), args.resume
    else:
        default = "reinforce/screened" if args.evaluator and args.config is None else None
        # (an external system: the sample-efficient strategy unless one is named)
        rc = runs.configure(args.config, sut_params=_sut_values(args.sut_param),
                            strategy_params=_assignments(args.strategy_param,
                                                         "--strategy-param"),
                            requirement_params=_sut_values(args.requirement_param,
                                                           "--requirement-param"),
                            **{k: getattr(args, k) for k in runs.SETTINGS
                               if k != "strategy"}, strategy=args.strategy or default)
        out = args.out  # None: a new folder runs/<time>-<strategy>
    if rc.evaluator:
        if args.rerun:
            raise UsageError("--rerun needs the JAX simulator (a run with an evaluator has no "
                             "trajectories to record)")
        from jaxfalsify.jobs import evaluators

        pool = evaluators.pool_settings(args.resume, workers=args.workers,
                                        timeout=args.timeout, retries=args.retries,
                                        scheduler=args.scheduler)
        o = evaluators.run(rc, out, **pool, resume=args.resume is not None,
                           force=args.force, progress=_progress(args.quiet), stop=stop,
                           figures=not args.no_figures)
    else:
        _no_evaluator_flags(args)
        o = runs.execute(rc, out, resume=args.resume is not None, force=args.force,
                         progress=_progress(args.quiet), stop=stop, figures=not args.no_figures,
                         rerun=args.rerun, startup_seconds=startup())
    if not args.quiet:
        print(runs.closing_report(o))
    print(f"wrote {o.out}/ (config.toml, evaluations.parquet, summary.json, critical.csv, "
          f"timing.json{'' if args.no_figures else ', figures/, report.md'}"
          f"{', best.rrd' if args.rerun else ''})")
    return _late_signal(stop)


def _no_evaluator_flags(args) -> None:
    given = [n for n in EVALUATOR_FLAGS if getattr(args, n) is not None]
    if given:
        raise UsageError(f"--{given[0]} needs --evaluator")


def _compare_evaluator(args, names, stop) -> int:
    from jaxfalsify.jobs import evaluators

    bad = [f for f in ("suite", "entries", "budgets", "sut", "sut_param", "jobs",
                       "requirement", "requirement_param", "coordinator", "num_processes",
                       "process_id", "coordinator_timeout")
           if getattr(args, f, None) is not None] + (["distributed"] if args.distributed else [])
    if bad:
        raise UsageError(f"--{bad[0].replace('_', '-')} cannot be combined with --evaluator "
                         "(an external system has no JAX SUT or ground truth)")
    result = evaluators.compare(
        args.evaluator, args.out, strategies=names or evaluators.COMPARE_STRATEGIES,
        seeds=args.seeds or 10, space=args.space or "paper", space_seed=args.space_seed or 0,
        evaluations=args.evaluations, batch=args.batch,
        strategy_params=_per_strategy(args.strategy_param), workers=args.workers,
        timeout=args.timeout, retries=1 if args.retries is None else args.retries,
        scheduler=args.scheduler, force=args.force, progress=_progress(args.quiet), stop=stop)
    print(evaluators.compare_markdown(result))
    return _late_signal(stop)


def _late_signal(stop) -> int:
    """0, or the signal's exit code when SIGINT / SIGTERM came after the last chunk: the work
    was complete and written (status.json says so), and the exit code still tells the caller
    that a signal arrived."""
    if stop():
        print("jaxfalsify: signal received while writing; the results are complete",
              file=sys.stderr)
        return stop.exit_code
    return 0


SWEEP_FLAGS = ("space", "space_seed", "sut", "seed", "chunk", "rows", "out", "force",
               "requirement", "requirement_param",
               "sut_param")


def _start_distributed(args) -> tuple[int, int]:
    if not args.distributed:
        if args.coordinator or args.num_processes or args.process_id is not None or \
                args.coordinator_timeout is not None:
            raise UsageError("--coordinator/--num-processes/--process-id/--coordinator-timeout "
                             "need --distributed")
        return 0, 1
    from jaxfalsify.base.distributed import TIMEOUT_S, initialize

    def say(text):
        if not args.quiet:
            print(f"jaxfalsify: {text}", file=sys.stderr, flush=True)

    return initialize(args.coordinator, args.num_processes, args.process_id,
                      timeout=args.coordinator_timeout or TIMEOUT_S, say=say)


def cmd_sweep(args, stop, startup) -> int:
    from jaxfalsify.engine.sweep_config import SweepConfig
    from jaxfalsify.jobs import sweep

    if args.resume is not None:
        _no_flags_with_resume(args, SWEEP_FLAGS)
        config, _ = sweep.resume_config(args.resume)
        out = args.resume
    else:
        config = SweepConfig(
            **{k: getattr(args, k) for k in ("space", "space_seed", "sut", "seed", "chunk",
                                             "rows", "requirement")
               if getattr(args, k) is not None},
            sut_params=_assignments(args.sut_param, "--sut-param", many=True),
            requirement_params=_sut_values(args.requirement_param, "--requirement-param"))
        config.build()  # refused before any process waits for the others
        out = args.out  # None: sweeps/<space>-<sut>-s<space seed>
    pid, n_proc = _start_distributed(args)
    s = sweep.execute(config, out, resume=args.resume is not None, force=args.force,
                      progress=_progress(args.quiet), stop=stop, process_id=pid,
                      num_processes=n_proc, startup_seconds=startup())
    if pid != 0:
        print(f"process {pid}: done ({s['out']})")
        return 0
    for line in sweep.summary_lines(s):
        print(line)
    return _late_signal(stop)


def _names(flag: str, value: str | None, what: str, example: str) -> tuple[str, ...] | None:
    """A comma-separated list of names given to ``flag`` (None when the flag is not given);
    one that names nothing is refused."""
    if value is None:
        return None
    names = tuple(n.strip() for n in value.split(","))
    if not any(names):
        raise UsageError(f"{flag} {value!r}: no {what} named (e.g. {flag} {example})")
    if not all(names):  # 'random,' or 'random,,cem': a name left out by mistake?
        raise UsageError(f"{flag} {value!r}: an empty {what} name between commas "
                         f"(e.g. {flag} {example})")
    twice = next((n for i, n in enumerate(names) if n in names[:i]), None)
    if twice is not None:
        raise UsageError(f"{flag} {value!r}: {twice!r} given twice")
    return names


def cmd_compare(args, stop, startup) -> int:
    from jaxfalsify.base.progress import timing_line
    from jaxfalsify.jobs import compare
    from jaxfalsify.jobs.compare_tables import budgets_markdown, table_markdown

    names = _names("--strategies", args.strategies, "strategy", "reinforce/default,cmaes")
    if args.evaluator:
        return _compare_evaluator(args, names, stop)
    _no_evaluator_flags(args)
    if args.suite is not None:
        return _compare_suite(args, names, stop, startup)
    if args.entries is not None:
        raise UsageError("--entries picks entries of a suite: it needs --suite FILE")
    if args.distributed and not args.out:
        raise UsageError("compare --distributed needs --out (a folder all processes share)")
    budgets = ()
    if args.budgets:
        try:
            budgets = tuple(int(b) for b in args.budgets.split(","))
        except ValueError:
            raise UsageError(f"--budgets {args.budgets!r}: comma-separated integers, "
                             "e.g. 250,1000") from None
    given = {k: getattr(args, k) for k in ("seeds", "evaluations", "space", "space_seed", "sut",
                                           "jobs", "batch", "requirement")
             if getattr(args, k) is not None}
    config = compare.CompareConfig(**given, **({"strategies": names} if names else {}),
                                   sut_params=_sut_values(args.sut_param),
                                   requirement_params=_sut_values(args.requirement_param,
                                                                  "--requirement-param"),
                                   strategy_params=_per_strategy(args.strategy_param),
                                   budgets=budgets)
    config.check()
    pid, n_proc = _start_distributed(args)
    result = compare.execute(config, args.out, force=args.force, progress=_progress(args.quiet),
                             stop=stop, process_id=pid, num_processes=n_proc,
                             startup_seconds=startup())
    if pid != 0:
        print(f"process {pid}: done")
        return 0
    if result.get("n_collisions") is not None:
        gmax = result["global_max_reward"]
        ties = result['global_max_ties']
        top = (f"global max reward {gmax:.4f} ({ties} scenario{'' if ties == 1 else 's'})"
               if gmax is not None else "no finite reward (every rollout non-finite)")
        print(f"{result['space']} space, {result['sut']}, {config.evaluations} evaluations, "
              f"{config.seeds} seeds; {top}, {result['n_collisions']:,} critical of "
              f"{result['n_scenarios']:,} scenarios")
    else:
        print(f"{result['space']} space, {result['sut']}, {config.evaluations} evaluations, "
              f"{config.seeds} seeds; {result['n_scenarios']:.3g} scenarios (too many to "
              f"sweep): collision share estimated {result['collision_share']:.2g} from "
              f"{result['sampled']:,} uniform draws")
    print(table_markdown(result))
    if budgets:
        print()
        print(budgets_markdown(result))
    print(f"wall time {timing_line(result['timing'])}")
    print(f"wrote {result['out']}/compare.json, compare.md, config.toml, timing.json")
    return 0


def _compare_suite(args, names, stop, startup) -> int:
    from jaxfalsify.base.progress import timing_line
    from jaxfalsify.jobs import suites

    for flag, given in (("--space", args.space), ("--space-seed", args.space_seed is not None),
                        ("--sut", args.sut),
                        ("--sut-param", args.sut_param), ("--budgets", args.budgets),
                        ("--requirement", args.requirement),  # the suite file's entries say
                        ("--requirement-param", args.requirement_param),
                        ("--distributed", args.distributed),
                        ("--evaluations", args.evaluations is not None)):
        if given:
            raise UsageError(f"--suite takes its spaces, SUTs and budgets from the suite file; "
                             f"drop {flag}")
    entries = _names("--entries", args.entries, "space", "aeb-9e6,island-dash")
    suite = suites.load_suite(args.suite, seeds=args.seeds, strategies=names,
                              jobs=args.jobs or 0, entries=entries,
                              strategy_params=_per_strategy(args.strategy_param),
                              batch=args.batch)
    result = suites.execute_suite(suite, args.out, force=args.force,
                                  progress=_progress(args.quiet), stop=stop,
                                  startup_seconds=startup())
    print(suites.suite_markdown(result))
    print(f"wall time {timing_line(result['timing'])}")
    print(f"wrote {result['out']}/suite.json, suite.md (and a comparison folder per space)")
    return 0


def cmd_simulate(args, stop, startup) -> int:
    from jaxfalsify.base.config import parse_number
    from jaxfalsify.core.sim import describe
    from jaxfalsify.scenario.space import KNOWN_PARAMETERS

    scenario, sut_values = {}, {}
    for item in args.params:
        name, eq, value = item.partition("=")
        if not eq:
            raise UsageError(f"expected NAME=VALUE, got {item!r}")
        if name.startswith("sut.") and len(name) > 4:  # a SUT parameter, as in a space
            if name[4:] in sut_values:
                raise UsageError(f"{name} given twice")
            sut_values[name[4:]] = value
            continue
        if name not in KNOWN_PARAMETERS:
            raise UsageError(f"unknown parameter '{name}' (known: {', '.join(KNOWN_PARAMETERS)})")
        if name in scenario:
            raise UsageError(f"{name} given twice")
        number = parse_number(value)
        if number is None:
            raise UsageError(f"{name}={value!r} is not a number")
        scenario[name] = float(number)
    flagged = _sut_values(args.sut_param)
    for name in sut_values:
        if name in flagged:
            raise UsageError(f"sut.{name} given twice (also by --sut-param)")
    given = {**flagged, **{k[4:]: v for k, v in _sut_values(
        [f"sut.{k}={v}" for k, v in sut_values.items()], "simulate").items()}}
    print(json.dumps(describe(scenario, sut=args.sut or "carla-tm", sut_params=given,
                              seed=args.seed), indent=2))
    return 0


def cmd_replay(args, stop, startup) -> int:
    from jaxfalsify.outputs.replay import record, record_campaign

    if args.save is not None and Path(args.save).is_file() and not args.force:
        raise UsageError(f"--save {args.save} exists; pass --force to overwrite it")
    if args.campaign:
        if args.scenario != "best" or args.scenarios:
            raise UsageError("--campaign records every evaluation: no --scenario/--scenarios")
        path = record_campaign(args.run_dir, save=args.save, spawn=args.spawn,
                               window=200 if args.window is None else args.window)
    else:
        if args.window is not None:
            raise UsageError("--window sets the sampling-distribution charts of --campaign; "
                             "without --campaign there are none")
        path = record(args.run_dir, args.scenario, save=args.save, spawn=args.spawn,
                      overlay=args.scenarios)
    print(f"wrote {path}" if path else "sent to the rerun viewer")
    return 0


def cmd_export(args, stop, startup) -> int:
    from jaxfalsify.io.store import check_out_plain
    from jaxfalsify.outputs.export import EXPORT_FILES, export

    if args.scenario not in ("best", "critical"):
        raise UsageError(f"--scenario {args.scenario!r}: expected best or critical")
    if args.ego not in ("controller", "replay"):
        raise UsageError(f"--ego {args.ego!r}: expected controller or replay")
    check_out_plain(args.out, EXPORT_FILES, args.force)
    files = export(args.run_dir, args.out, args.scenario, ego=args.ego, force=args.force)
    scenarios = [f for f in files if f.suffix == ".xosc" and not f.name.startswith("logical")
                 and f.name != "template.xosc"]
    extra = ", template.xosc" if any(f.name == "template.xosc" for f in files) else ""
    print(f"wrote {len(scenarios)} scenario .xosc (ego: {args.ego}){extra}, logical.xosc, "
          f"logical_stochastic.xosc and crossing.xodr to {args.out}/")
    return 0


def cmd_figures(args, stop, startup) -> int:
    from jaxfalsify.jobs import runs

    files, report = runs.redraw(args.run_dir)
    print(f"wrote {len(files)} figures to {args.run_dir}/figures/ and {report}")
    return 0


def cmd_estimate(args, stop, startup) -> int:
    from jaxfalsify.base.config import number_text
    from jaxfalsify.jobs import estimate
    from jaxfalsify.suts.registry import folder_name

    config = estimate.EstimateConfig(
        **{k: getattr(args, k) for k in ("space", "space_seed", "sut", "requirement", "method",
                                         "target_rel_error", "samples", "batch", "confidence",
                                         "seed") if getattr(args, k) is not None},
        sut_params=_sut_values(args.sut_param),
        requirement_params=_sut_values(args.requirement_param, "--requirement-param"))
    if not 0 < config.confidence < 1:
        raise UsageError(f"--confidence {number_text(config.confidence)}: must be in (0, 1)")
    if config.method == "exact":  # every scenario, no draws: these would be ignored
        given = [f for f in ("target_rel_error", "samples", "batch", "confidence", "seed")
                 if getattr(args, f) is not None]
        if given:
            raise UsageError(f"--{given[0].replace('_', '-')} does not apply to --method exact "
                             "(every scenario evaluated once, no draws)")
    space = config.build()[0]
    out = args.out or Path("estimates") / (
        f"{space.name}-{folder_name(config.sut)}-{folder_name(config.requirement)}-"
        f"{config.method}-s{config.seed}")
    s = estimate.execute(config, out, force=args.force, progress=_progress(args.quiet),
                         stop=stop, startup_seconds=startup())
    for line in estimate.summary_lines(s):
        print(line)
    print(f"wrote {out}/summary.json")
    if s["interrupted"]:  # the signal ended the draws: no "results are complete"
        return stop.exit_code
    return _late_signal(stop)


COMMANDS = {"run": cmd_run, "sweep": cmd_sweep, "compare": cmd_compare,
            "simulate": cmd_simulate, "replay": cmd_replay, "export": cmd_export,
            "figures": cmd_figures, "estimate": cmd_estimate}


def _user_file(spec) -> str | None:
    """The source file of a user's ``file.py:attr`` or ``module:attr`` (None for a built-in
    name or a module not imported)."""
    if not isinstance(spec, str) or ":" not in spec:
        return None
    mod = spec.rsplit(":", 1)[0]
    if mod.endswith(".py"):
        return str(Path(mod).resolve())
    return getattr(sys.modules.get(mod), "__file__", None)


def _who_raised(text: str, args) -> str:
    """Which user code a host callback's error ``text`` (its traceback names the file) came
    from: ``the requirement SPEC`` or ``the SUT SPEC``; where the traceback names neither,
    the one given as user code (the SUT where both or neither are)."""
    given = [(what, getattr(args, attr, None)) for what, attr in
             (("requirement", "requirement"), ("SUT", "sut"))]
    user = [(what, spec) for what, spec in given if _user_file(spec)]
    for what, spec in user:
        if f'File "{_user_file(spec)}"' in text:
            return f"the {what} {spec}"
    if len(user) == 1:
        return f"the {user[0][0]} {user[0][1]}"
    sut = getattr(args, "sut", None)
    return f"the SUT{f' {sut}' if sut else ''}"


def main(argv=None, startup: float = 0.0) -> int:
    """Run the command line ``argv``; returns the exit code. ``startup``: seconds the process
    spent before (the console script passes its start-up, for ``timing.json``)."""
    import os
    import time

    entered = time.perf_counter()

    def since_start() -> float:  # a job's start-up: the process's time until the job begins
        return startup + time.perf_counter() - entered

    stop = StopFlag().install()
    # a host callback that raises is reported in one line (sut.callback_error), not also logged
    logging.getLogger("jax._src.callback").setLevel(logging.CRITICAL)
    args = None
    try:
        args = parse(argv)
        from jaxfalsify.io.cache import check_no_cache_setting, check_xla_flags

        check_no_cache_setting()
        check_xla_flags()  # XLA would end the process on a flag it does not know
        if args.no_cache:
            os.environ["JAXFALSIFY_NO_CACHE"] = "1"
            from jaxfalsify.io.cache import enable_compilation_cache
            enable_compilation_cache()
        return COMMANDS[args.command](args, stop, since_start)
    except (UsageError, ValueError) as e:
        print(f"jaxfalsify: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}",
              file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader of our output went away (`| head`): quietly, as
        # a program killed by SIGPIPE (files, if any, were complete before printing)
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 128 + signal.SIGPIPE
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        print(f"jaxfalsify: error: {where}{e.strerror or e} (check free space, permissions and "
              "the path; files under their final names are complete)", file=sys.stderr)
        return 1
    except MemoryError:
        print("jaxfalsify: error: out of memory (lower --batch or --chunk)", file=sys.stderr)
        return 1
    except RuntimeError as e:
        from jaxfalsify.suts.registry import callback_error

        raised = callback_error(e)
        if raised is not None:
            print(f"jaxfalsify: error: {_who_raised(str(e), args)} raised at run time "
                  f"(in a host callback): {raised}", file=sys.stderr)
            return 2
        if not str(e).startswith("Unable to initialize backend"):
            raise
        from jaxfalsify.io.cache import backend_error

        print(f"jaxfalsify: error: {backend_error(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxfalsify: interrupted; nothing was written in place of earlier results",
              file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - the Interrupted of runs/sweeps, by name
        from jaxfalsify.io.store import Interrupted

        if isinstance(e, Interrupted):
            print(f"jaxfalsify: {e}", file=sys.stderr)
            return stop.exit_code
        raise
    finally:
        stop.restore()


def entry() -> None:
    """The console script: :func:`main`, then exit without the interpreter's teardown (JAX's
    takes about half a second; every file is already written and closed)."""
    import os

    from jaxfalsify.base.progress import startup_seconds

    code = main(startup=startup_seconds())
    try:
        sys.stdout.flush()
    except BrokenPipeError:  # the reader went away before our last lines (see main)
        code = code or 128 + signal.SIGPIPE
    sys.stderr.flush()
    from jaxfalsify.base.distributed import leave

    leave()  # process 0 of a multi-process command waits for the others to leave first
    os._exit(code)


if __name__ == "__main__":
    entry()
