"""Wall time of the commands a user types, cold and warm, side by side in one run.

    python experiments/bench_latency.py                      # about 8 minutes on 2 cores
    python experiments/bench_latency.py --baseline /tmp/old  # also an older version: ~20 min

Every row is a fresh process (``jaxfalsify ...``), timed from outside from start to exit, in a
scratch folder with its own per-user cache (``JAXFALSIFY_CACHE_DIR``): *cold* rows start from
an empty cache, *warm* rows follow a run that filled it. "recompiled" says whether the command
added anything to the cache (a compiled program or an exported one): another space seed or SUT
parameter value must not. With ``--baseline DIR`` (a checkout of an older commit, e.g. made by
``git worktree add /tmp/old <commit>``, or a copy of ``jaxfalsify/`` with some files at an
older commit), the same rows run on that code through ``PYTHONPATH``, with its own per-user
cache and its own flags if it predates ``--evaluations``; each row runs for both versions in
turn, so load that drifts during the run hits both alike.
Warm rows are the median of 3 runs (the versions alternating), so one noisy run does not
decide a row; the rows that must not recompile use a new space seed or SUT parameter value in
each run. Each row also lists where its time went (the command's own ``timing.json``: start-up,
compile,
search, writing, figures), and two floor rows time a bare ``import jax`` and the CLI's imports
(``import jaxfalsify.cli``) in a fresh interpreter.
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


def phases(out: Path) -> dict:
    """The command's own split of its wall time (``timing.json``), seconds rounded."""
    try:
        t = json.loads((out / "timing.json").read_text())
    except (OSError, ValueError):
        return {}
    return {k[:-8]: round(v, 2) for k, v in t.items() if k.endswith("_seconds")}


def phases_text(ph: dict) -> str:
    return ", ".join(f"{k} {v:.1f}" for k, v in ph.items() if k != "total" and v >= 0.05)


class Version:
    """One code version's CLI, cache and scratch folders."""

    def __init__(self, label: str, exe: list[str], env: dict, cache: Path, work: Path,
                 old_flags: bool = False):
        self.label, self.exe, self.env, self.cache, self.work = label, exe, env, cache, work
        self.old_flags = old_flags  # the old budget flag (--episodes), no --sut-param
        self.n = 0

    def folder(self) -> Path:
        self.n += 1
        return self.work / f"{self.label}-{self.n}"

    def row(self, name: str, args: list[str], recompile_check: bool = False) -> dict | None:
        """``jaxfalsify run ARGS`` timed from outside (None if this version cannot run it)."""
        if self.old_flags and any(a.startswith("--sut-param") for a in args):
            return None
        budget = ["--episodes", "4000"] if self.old_flags else []
        before = cache_entries(self.cache)
        folder = self.folder()
        sec = timed(self.exe + ["run", "--quiet"] + args + budget + ["--out", str(folder)],
                    self.work, self.env)
        r = {"version": self.label, "row": name, "seconds": sec, "phases": phases(folder)}
        if recompile_check:
            r["recompiled"] = cache_entries(self.cache) > before
        print(f"{self.label:>9}  {name:<42} {sec:7.2f} s"
              + (f"   recompiled: {'yes' if r['recompiled'] else 'no'}"
                 if recompile_check else "") + f"   ({phases_text(r['phases'])})", flush=True)
        return r

    def compare(self, name: str | None) -> dict | None:
        """``jaxfalsify compare`` (the default strategies x 10 seeds), timed from outside."""
        if self.old_flags:
            return None
        folder = self.folder()
        sec = timed(self.exe + ["compare", "--quiet", "--out", str(folder)], self.work,
                    self.env)
        r = {"version": self.label, "row": name or "compare, cold", "seconds": sec,
             "phases": phases(folder)}
        print(f"{self.label:>9}  {r['row']:<42} {sec:7.2f} s   ({phases_text(r['phases'])})",
              flush=True)
        return r if name else None


REPEATS = 3  # warm rows: the median of this many runs (each version in turn every time)
RUN_ROWS = [  # (row, the arguments of each repetition, whether to check for recompilation)
    ("run, figures, cold", [[]], False),
    ("run, figures, warm", [[]] * REPEATS, False),
    ("run --no-figures, warm", [["--no-figures"]] * REPEATS, False),
    ("run, another space seed",  # a new space seed every repetition
     [["--space-seed", str(s), "--no-figures"] for s in range(1, REPEATS + 1)], True),
    ("run, another SUT parameter value",  # a new value every repetition
     [["--sut-param", f"full_brake={7.5 - 0.5 * i}", "--no-figures"] for i in range(REPEATS)],
     True)]


def median_row(samples: list[dict]) -> dict:
    """One row from repeated runs: the median wall time (and that run's phases), every
    sample's time, and whether any of them recompiled."""
    mid = sorted(samples, key=lambda r: r["seconds"])[len(samples) // 2]
    r = {**mid, "samples": [x["seconds"] for x in samples]}
    if "recompiled" in mid:
        r["recompiled"] = any(x["recompiled"] for x in samples)
    if len(samples) > 1:
        print(f"{r['version']:>9}  {r['row'] + ', median':<42} {r['seconds']:7.2f} s"
              + (f"   recompiled: {'yes' if r['recompiled'] else 'no'}"
                 if "recompiled" in r else ""), flush=True)
    return r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
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
        env.pop("JAX_COMPILATION_CACHE_DIR", None)
        exe = [str(Path(sys.executable).with_name("jaxfalsify"))]
        if not Path(exe[0]).exists():
            exe = [sys.executable, "-m", "jaxfalsify.cli"]
        versions = [Version("current", exe, env, cache, tmp)]
        if args.baseline:
            old_cache = tmp / "old-cache"
            old_cache.mkdir()
            cli = (args.baseline / "jaxfalsify" / "cli.py").read_text()
            versions.append(Version(
                "baseline", [sys.executable, "-m", "jaxfalsify.cli"],
                dict(env, PYTHONPATH=str(args.baseline.resolve()),
                     JAXFALSIFY_CACHE_DIR=str(old_cache),
                     JAX_COMPILATION_CACHE_DIR=str(old_cache / "jax")),
                old_cache, tmp, old_flags='"--evaluations"' not in cli))
        for name, code in (("python -c 'import jax' (floor)", "import jax"),
                           ("python -c 'import jaxfalsify.cli'", "import jaxfalsify.cli")):
            sec = min(timed([sys.executable, "-c", code], tmp, env) for _ in range(3))
            rows.append({"version": "current", "row": name, "seconds": sec})
            print(f"{'current':>9}  {name:<42} {sec:7.2f} s   (best of 3)", flush=True)
        # each row for every version in turn: load that drifts during the run hits both
        for name, repetitions, check in RUN_ROWS:
            samples: dict[str, list] = {v.label: [] for v in versions}
            for run_args in repetitions:
                for v in versions:
                    if r := v.row(name, run_args, check):
                        samples[v.label].append(r)
            rows += [median_row(x) for x in samples.values() if x]
        for v in versions:
            v.compare(None)  # fills the cache
        rows += [r for v in versions
                 if (r := v.compare("compare 8 strategies x 10 seeds, warm"))]
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
