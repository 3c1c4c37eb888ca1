"""``RUN_DIR/report.md``: the run's summary, its best critical scenario in the paper's Table II
layout, the figures, and the commands that reproduce it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxfalsify.base.progress import timing_line
from jaxfalsify.engine.rundir import load_run
from jaxfalsify.io.files import write_atomic
from jaxfalsify.io.store import FIGURES
from jaxfalsify.outputs import analysis
from jaxfalsify.suts import registry as sut_lib

__all__ = ["simulate_command", "write_report"]


def simulate_command(sp, rc, ep: dict, row: int) -> list[str]:
    """``jaxfalsify simulate`` lines for evaluated ``row``: its parameter values, the run's SUT
    and every SUT parameter that differs from the SUT's default (a space's ``sut.NAME``
    dimensions as ``--sut-param``); for a stochastic SUT a comment that ``simulate`` draws
    other noise than the run did."""

    scen = [f"{n}={ep[n][row]:.10g}" for n in sp.names if not n.startswith("sut.")]
    sut = sut_lib.resolve(rc.sut)
    default = sut_lib.params_dict(sut.default_params)
    over = {k: v for k, v in rc.sut_params.items() if default.get(k) != v}
    over.update({n[4:]: ep[n][row] for n in sp.names if n.startswith("sut.")})
    cmd = " ".join(["jaxfalsify simulate", *scen, "--sut", str(rc.sut)]
                   + [f"--sut-param {k}={v:.10g}" for k, v in over.items()])
    if not sut.stochastic:
        return [cmd]
    return [f"# a stochastic SUT: simulate draws its own noise (--seed), not evaluation "
            f"{int(ep['evaluation'][row])}'s; replay shows the run's own draw", cmd]


def reproduce_lines(run_dir: Path, sp, rc, ep: dict, row: int) -> list[str]:
    """report.md's commands that repeat the run and show its results."""
    if rc.evaluator == "python":  # the user's own loop ran it: nothing to re-simulate
        return [f"# an ask/tell run (jaxfalsify.Falsifier): repeat your loop with the settings "
                f"of {run_dir}/config.toml", f"jaxfalsify figures {run_dir}"]
    again = [f"jaxfalsify run --config {run_dir}/config.toml --out {run_dir}-again",
             f"jaxfalsify figures {run_dir}"]
    if rc.evaluator:
        return again
    return [*again, f"jaxfalsify replay {run_dir} --scenario best --scenarios 14",
            f"jaxfalsify export {run_dir} --scenario best --out {run_dir}/openscenario",
            *simulate_command(sp, rc, ep, row)]


REPORT_CLUSTERS = 10  # failure clusters report.md tabulates (the largest)


def cluster_cell(fc: analysis.FailureClusters) -> str:
    """The summary table's failure-cluster cell: how many, and the largest's size."""
    if fc.k == 0:
        return "none (no collision)"
    return (f"{fc.k} (largest: {int(fc.sizes[0])} of the {fc.n} distinct critical scenarios; "
            "neighbours: index vectors at most one value apart in every parameter)")


def cluster_section(sp, fc: analysis.FailureClusters, fields: dict) -> list[str]:
    """report.md's failure-cluster table: the 10 largest clusters, their size, the evaluation
    that first found one of their members, and their representative (best-reward member)."""
    if fc.k == 0:
        return []
    shown = min(fc.k, REPORT_CLUSTERS)
    header = ["cluster", "size", "first found at evaluation", "best reward",
              *(f"{n} [{u}]" if u else n for n, u in zip(sp.names, sp.units))]
    rows = []
    for c in range(shown):
        j = int(fc.representative[c])
        rows.append([str(c + 1), str(int(fc.sizes[c])), str(int(fc.first_evaluation[c])),
                     f"{float(np.asarray(fields['reward'])[fc.rows[j]]):.4f}",
                     *(analysis.format_value(sp, p, sp.table[p][int(fc.indices[j, p])])
                       for p in range(len(sp.names)))])
    lead = (f"The {shown} largest of {fc.k} failure clusters (the others in `critical.csv`'s "
            "`cluster` column)" if fc.k > shown else
            f"The {fc.k} failure clusters" if fc.k > 1 else "The one failure cluster")
    return ["", "## Failure clusters", "",
            f"{lead}: distinct critical scenarios "
            "whose index vectors differ by at most one value in every parameter are neighbours, "
            "and a cluster is a chain of neighbours. Each row shows the cluster's best-reward "
            "member.", "", analysis.markdown_table(header, rows)]


def write_report(run_dir: Path, timing: dict | None = None, folder=None) -> Path:
    """Write ``run_dir/report.md``; ``timing``: the run's wall-time split (else read from its
    ``timing.json``; the run itself passes it, so report.md's writing counts in timing.json).
    ``folder``: the run folder's contents as :func:`~jaxfalsify.engine.rundir.load_run` reads
    them, when the caller holds them; else read from ``run_dir``."""
    run_dir = Path(run_dir)
    sp, rc, s, ep = folder if folder is not None else load_run(run_dir)
    if timing is None:
        timing = (json.loads((run_dir / "timing.json").read_text())
                  if (run_dir / "timing.json").exists() else {})
    wall = (timing_line(timing) + (f", resumed at evaluation {timing['resumed_from_evaluation']}"
                                   if timing.get("resumed_from_evaluation") else "")
            if "total_seconds" in timing else "not recorded yet")
    idx, fields = analysis.from_evaluations(ep, sp)
    b = analysis.best(fields)
    fc = s["first_collision_evaluation"]
    clusters = analysis.failure_clusters(idx, fields)
    lines = [f"# Falsification run `{run_dir.name}`", "",
             "| | |", "|---|---|",
             f"| strategy | {s['strategy']} |",
             f"| space | {s['space']} (space seed {s['space_seed']}) |",
             f"| system under test | {s['sut']} |" if not rc.evaluator else
             f"| system under test | evaluator `{rc.evaluator}` (critical: its collision flags, "
             f"or robustness < 0; {s.get('n_failed', 0)} evaluations failed) |",
             f"| seed | {s['seed']} |",
             f"| evaluations | {s['evaluations']} (batch {s['batch']}) |",
             f"| collisions | {s['n_collisions']} ({s['n_distinct_critical']} distinct) |",
             f"| failure clusters | {cluster_cell(clusters)} |",
             f"| first collision at evaluation | {fc if fc is not None else 'none found'} |",
             (f"| best reward | {s['best']['reward']:.4f}, first evaluated at "
              f"{s['best']['evaluation']} |" if s["best_reached_evaluation"] is not None else
              f"| best reward | none finite: all {s['n_nonfinite']} evaluations non-finite "
              "(the SUT returned NaN or inf) |"),
             f"| running best within 1 % of it from evaluation | "
             f"{s['best_reached_evaluation'] or '-'} |",
             f"| learner converged at evaluation | "
             f"{s.get('learner_converged_evaluation') or '-'} (moving mean reward within 5 % "
             "of its final value) |",
             f"| wall time | {wall} |",
             "", ("## Best critical scenario beside a typical non-critical one (paper Table II "
                  "layout)" if fc is not None else
                  "## No collision found: the best scenario beside a typical one"),
             "", analysis.markdown_table(*analysis.table_ii(sp, idx, fields)),
             *cluster_section(sp, clusters, fields)]
    figs = [(f, cap) for f, cap in FIGURES if (run_dir / "figures" / f).exists()]
    if figs:
        lines += ["", "## Figures", ""]
        for f, cap in figs:
            lines += [f"![{cap}](figures/{f})", "", f"*{cap}*", ""]
    lines += ["", "## Reproduce", "", "```bash", *reproduce_lines(run_dir, sp, rc, ep, b),
              "```", "",
              f"Files: `config.toml` (resolved configuration), `evaluations.parquet` (every "
              f"evaluated scenario), `summary.json`, `critical.csv` "
              f"({int(np.sum(analysis.collided(fields)))} collisions, distinct ones ranked by "
              "reward).", ""]
    path = run_dir / "report.md"
    write_atomic(path, "\n".join(lines))
    return path
