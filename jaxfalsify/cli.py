"""Command line: ``jaxfalsify sweep`` (exhaustive ground truth) and ``jaxfalsify simulate``.

Bad input prints one line ``jaxfalsify: error: ...`` naming the offending flag or key and exits
with code 2, before anything is written.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path


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


def build_parser() -> argparse.ArgumentParser:
    from jaxfalsify.sut import SUTS

    p = _Parser(prog="jaxfalsify", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("sweep", help="evaluate every concrete scenario of a space")
    s.add_argument("--space", default="paper", help="built-in name (paper, paper-extended) or a "
                   "TOML file (default: paper)")
    s.add_argument("--seed", type=_seed, default=0, help="discretisation seed (default 0)")
    s.add_argument("--sut", default="carla-tm", help=f"system under test: {', '.join(SUTS)} "
                   "(default carla-tm)")
    s.add_argument("--out", type=Path, default=None,
                   help="output folder (default sweeps/<space>-<sut>-s<seed>)")
    s.add_argument("--chunk", type=_positive_int("--chunk"), default=1 << 16,
                   help="scenarios per compiled batch (default 65536)")
    s.add_argument("--force", action="store_true", help="overwrite an existing sweep in --out")
    s.add_argument("--quiet", action="store_true", help="no progress bar")

    m = sub.add_parser("simulate", help="evaluate one concrete scenario and print its outcome")
    m.add_argument("params", nargs="*", metavar="NAME=VALUE",
                   help="scenario parameters, e.g. ego_offset=9 ped_speed=1.237")
    m.add_argument("--sut", default="carla-tm")
    return p


def _check_out(out: Path, marker: str, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out} exists and is not a folder")
    if (out / marker).exists() and not force:
        raise UsageError(f"--out {out} already holds {marker}; pass --force to overwrite")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    if not os.access(parent, os.W_OK):
        raise UsageError(f"--out {out}: folder {parent} is not writable")


def cmd_sweep(args) -> int:
    from tqdm import tqdm

    from jaxfalsify.space import space as load_space
    from jaxfalsify import sut as sut_lib
    from jaxfalsify.sweep import run_sweep

    try:
        sp = load_space(args.space, seed=args.seed)
        sut = sut_lib.get(args.sut)
    except ValueError as e:
        raise UsageError(str(e)) from None
    out = args.out or Path("sweeps") / f"{Path(sp.name).stem}-{sut.name}-s{args.seed}"
    _check_out(out, "sweep.parquet", args.force)
    bar = tqdm(total=sp.size, unit="scn", unit_scale=True, disable=args.quiet,
               desc=f"sweep {sp.name} / {sut.name}")
    try:
        summary = run_sweep(sp, sut.name, out, chunk=args.chunk, progress=bar.update)
    finally:
        bar.close()
    best = summary["global_max_scenario"] or {}
    print(f"{summary['n_scenarios']} scenarios, {summary['n_collisions']} collisions "
          f"({100 * summary['collision_rate']:.2f} %) in {summary['wall_seconds']:.2f} s "
          f"(compile {summary['compile_seconds']:.2f} s)")
    print(f"global maximum reward {summary['global_max_reward']:.4f} at "
          + ", ".join(f"{k}={v:g}" for k, v in best.get("values", {}).items()))
    print(f"wrote {out}/sweep.parquet, summary.json, config.toml")
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
        handler = {"sweep": cmd_sweep, "simulate": cmd_simulate}[args.command]
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
