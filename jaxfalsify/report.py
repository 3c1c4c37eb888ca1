"""``RUN_DIR/report.md``: the run's summary, its best critical scenario in the paper's Table II
layout, the figures, and the commands that reproduce it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxfalsify.config import write_atomic
from jaxfalsify.figures import load_run, pick

FIGURES = [("reward_per_episode.png", "Reward per evaluation (paper Fig. 7)"),
           ("distance_challenging.png", "Distance over time, best critical vs typical "
            "non-critical; red = high-risk (paper Fig. 8)"),
           ("high_risk_second_half.png", "High-risk share in the second half (paper Fig. 9)"),
           ("distance_14_scenarios.png", "14 evaluated scenarios, collisions red (paper Fig. 10)"),
           ("critical_regions.png", "Critical regions from the exhaustive sweep, with the "
            "evaluated scenarios")]


def write_report(run_dir: Path) -> Path:
    run_dir = Path(run_dir)
    sp, rc, s, ep = load_run(run_dir)
    import json
    timing = (json.loads((run_dir / "timing.json").read_text())
              if (run_dir / "timing.json").exists() else {})
    wall = (f"{timing['wall_seconds']:.1f} s ({timing['compile_seconds']:.1f} s compile)"
            + (f", resumed at evaluation {timing['resumed_from_evaluation']}"
               if timing.get("resumed_from_evaluation") else "")
            if "wall_seconds" in timing else "not recorded")
    rows = pick(ep, sp)
    b, t = rows["best"], rows["typical"]
    fc = s["first_collision_evaluation"]
    lines = [f"# Falsification run `{run_dir.name}`", "",
             "| | |", "|---|---|",
             f"| strategy | {s['strategy']}{' / ' + s['preset'] if s['preset'] else ''} |",
             f"| space | {s['space']} (space seed {s['space_seed']}) |",
             f"| system under test | {s['sut']} |",
             f"| seed | {s['seed']} |",
             f"| evaluations | {s['evaluations']} (batch {s['batch']}) |",
             f"| collisions | {s['n_collisions']} ({s['n_distinct_critical']} distinct) |",
             f"| first collision at evaluation | {fc if fc is not None else 'none'} |",
             f"| best reward | {s['best']['reward']:.4f} at evaluation "
             f"{s['best']['evaluation']} |",
             f"| converged (running best within 1 %) at | {s['convergence_evaluation']} |",
             f"| wall time | {wall} |",
             "", "## Best critical scenario (paper Table II layout)", "",
             "| parameter | challenging (best) | non-challenging (typical) |", "|---|---|---|"]
    for n, u in zip(sp.names, sp.units):
        unit = f" {u}" if u in ("m", "m/s") else ""
        lines.append(f"| {n} | {ep[n][b]:.3f}{unit} | {ep[n][t]:.3f}{unit} |")
    for f in ("reward", "collision", "min_distance", "final_distance",
              "high_risk_share_second_half"):
        bv, tv = ep[f][b], ep[f][t]
        fmt = (lambda x: str(bool(x))) if ep[f].dtype == bool else (lambda x: f"{x:.4f}")
        lines.append(f"| {f} | {fmt(bv)} | {fmt(tv)} |")
    figs = [(f, cap) for f, cap in FIGURES if (run_dir / "figures" / f).exists()]
    if figs:
        lines += ["", "## Figures", ""]
        for f, cap in figs:
            lines += [f"![{cap}](figures/{f})", "", f"*{cap}*", ""]
    lines += ["", "## Reproduce", "", "```bash",
              f"jaxfalsify run --config {run_dir}/config.toml --out {run_dir}-again",
              f"jaxfalsify figures {run_dir}",
              f"jaxfalsify replay {run_dir} --scenario best --scenarios 14",
              f"jaxfalsify export {run_dir} --scenario best --out {run_dir}/openscenario",
              "jaxfalsify simulate " + " ".join(f"{n}={ep[n][b]:g}" for n in sp.names)
              + f" --sut {s['sut']}", "```", "",
              f"Files: `config.toml` (resolved configuration), `episodes.parquet` (every "
              f"evaluated scenario), `summary.json`, `critical.csv` "
              f"({int(np.sum(ep['collision']))} collisions, distinct ones ranked by reward).", ""]
    path = run_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path
