"""Wall time of the commands a user types, cold and warm, side by side in one run.

    python experiments/bench_latency.py                      # about 3 minutes on 2 cores
    python experiments/bench_latency.py --baseline /tmp/old  # also an older checkout's times

Every row is a fresh process (``jaxfalsify ...``), timed from outside from start to exit, in a
scratch folder with its own per-user cache (``JAXFALSIFY_CACHE_DIR``): *cold* rows start from
an empty cache, *warm* rows follow a run that filled it. "recompiled" says whether the command
added anything to the cache (a compiled program or an exported one): another space seed or SUT
parameter value must not. With ``--baseline DIR`` (a checkout of an older commit, e.g. made by
``git worktree add /tmp/old <commit>``), the same main-job rows run on that code through
``PYTHONPATH`` (its own flags and JAX cache variable), for a ratio measured in the same run.
Writes ``experiments/results/bench_latency.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGETS = {  # seconds, from the library-core issue
    "run, figures, cold": 10.0, "run, figures, warm": 5.0, "run --no-figures, warm": 2.5,
    "run, another space seed": 3.0, "run, another SUT parameter value": 3.0,
    "compare 8 strategies x 10 seeds, warm": 20.0}


def cache_entries(cache: Path) -> int:
    return sum(1 for p in cache.rglob("*") if p.is_file())


def timed(cmd: list[str], cwd: Path, env: dict) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return dt


def rows_for(label: str, exe: list[str], work: Path, env: dict, cache: Path,
             baseline: bool = False) -> list[dict]:
    """The main-job rows for one code version (``exe`` runs its CLI)."""
    run = exe + ["run", "--quiet"]
    budget = ["--episodes", "4000"] if baseline else []  # the old flag names
    out = []

    def row(name, args, recompile_check=False):
        before = cache_entries(cache)
        sec = timed(run + args + budget + ["--out", str(work / f"{label}-{len(out)}")], work,
                    env)
        r = {"version": label, "row": name, "seconds": sec}
        if recompile_check:
            r["recompiled"] = cache_entries(cache) > before
        out.append(r)
        print(f"{label:>9}  {name:<42} {sec:7.2f} s"
              + (f"   recompiled: {'yes' if r['recompiled'] else 'no'}"
                 if recompile_check else ""), flush=True)

    row("run, figures, cold", [])
    row("run, figures, warm", [])
    row("run --no-figures, warm", ["--no-figures"])
    seed_flag = ["--space-seed", "1"]
    row("run, another space seed", seed_flag + ["--no-figures"], recompile_check=True)
    if not baseline:
        row("run, another SUT parameter value", ["--sut-param", "full_brake=7.5",
                                                 "--no-figures"], recompile_check=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", type=Path, help="a checkout of an older commit to time too")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results"
                    / "bench_latency.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory(prefix="jaxfalsify-latency-") as tmp:
        tmp = Path(tmp)
        cache = tmp / "cache"
        env = dict(os.environ, JAXFALSIFY_CACHE_DIR=str(cache))
        env.pop("JAXFALSIFY_NO_CACHE", None)
        exe = [str(Path(sys.executable).with_name("jaxfalsify"))]
        if not Path(exe[0]).exists():
            exe = [sys.executable, "-m", "jaxfalsify.cli"]
        rows += rows_for("current", exe, tmp, env, cache)
        timed(exe + ["compare", "--quiet", "--out", str(tmp / "cmp-cold")], tmp, env)
        sec = timed(exe + ["compare", "--quiet", "--out", str(tmp / "cmp-warm")], tmp, env)
        rows.append({"version": "current", "row": "compare 8 strategies x 10 seeds, warm",
                     "seconds": sec})
        print(f"{'current':>9}  {'compare 8 strategies x 10 seeds, warm':<42} {sec:7.2f} s")
        if args.baseline:
            old_cache = tmp / "old-cache"
            old_env = dict(env, PYTHONPATH=str(args.baseline.resolve()),
                           JAX_COMPILATION_CACHE_DIR=str(old_cache))
            old_cache.mkdir()
            rows += rows_for("baseline", [sys.executable, "-m", "jaxfalsify.cli"], tmp,
                             old_env, old_cache, baseline=True)
    print()
    print(f"{'row':<42} {'current s':>10} {'target s':>9}"
          + (f" {'baseline s':>11} {'baseline/current':>17}" if args.baseline else ""))
    for name, target in TARGETS.items():
        cur = next((r["seconds"] for r in rows if r["version"] == "current"
                    and r["row"] == name), None)
        old = next((r["seconds"] for r in rows if r["version"] == "baseline"
                    and r["row"] == name), None)
        line = f"{name:<42} {cur:>10.2f} {target:>9.1f}"
        if args.baseline:
            line += (f" {old:>11.2f} {old / cur:>17.2f}" if old else f" {'-':>11} {'-':>17}")
        print(line)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"cpu_count": os.cpu_count(), "rows": rows,
                                    "targets": TARGETS}, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
