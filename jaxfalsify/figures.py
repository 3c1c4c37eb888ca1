"""The paper's figures (and critical-region maps) for a run folder, as PNG files.

Host-side only (matplotlib, Agg backend); the jitted core never imports this module.

* ``reward_per_episode.png`` — reward per evaluation and its moving average (paper Fig. 7);
* ``distance_challenging.png`` — distance over time of the best critical scenario and of a
  typical non-critical one, high-risk steps red, low-risk green, the < 1 m collision zone
  shaded (paper Fig. 8);
* ``high_risk_second_half.png`` — their high-risk shares over the second half (paper Fig. 9);
* ``distance_14_scenarios.png`` — distance over time of 14 evaluated scenarios, collisions
  red, the rest green (paper Fig. 10);
* ``critical_regions.png`` — beyond the paper: the collision share of the exhaustive sweep over
  every pair of parameters, with the run's evaluated scenarios on top.
"""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np

from jaxfalsify import analysis, store

FIGSIZE = (8, 4.5)
DPI = 100
N_TRAJECTORIES = 16  # simulated per figure set: best, typical and 14 (a fixed shape: one program)
TRUTH_LIMIT = 5_000_000  # largest space whose ground truth the critical-region map sweeps


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def load_run(run_dir: Path):
    """(space, resolved config, summary, episodes columns) of a finished run folder."""
    import pyarrow.parquet as pq

    from jaxfalsify.runs import RunConfig

    run_dir = Path(run_dir)
    missing = [f for f in ("config.toml", "summary.json", "episodes.parquet")
               if not (run_dir / f).exists()]
    if missing:
        raise ValueError(f"{run_dir} is not a finished run folder (missing "
                         f"{', '.join(missing)})")
    rc = RunConfig.from_toml(run_dir / "config.toml")
    sp = rc.build().space
    summary = json.loads((run_dir / "summary.json").read_text())
    ep = {k: np.asarray(v) for k, v in pq.read_table(run_dir / "episodes.parquet")
          .to_pydict().items()}
    return sp, rc, summary, ep


def pick(ep: dict) -> dict[str, int | None]:
    """Rows of the best evaluation and of a typical (median-reward) non-critical one."""
    return {"best": analysis.best(ep), "typical": analysis.typical_non_critical(ep)}


def indices_of(ep: dict, space, rows) -> np.ndarray:
    return np.stack([ep[f"{n}_idx"][rows] for n in space.names], -1)


def fig10_rows(ep: dict, n: int = 14, n_collisions: int = 3) -> list[int]:
    """Up to ``n`` evaluated scenarios, ``n_collisions`` of them collisions (paper Fig. 10);
    a fixed draw so redrawing gives the same figure."""
    rng = np.random.default_rng(0)
    col = np.nonzero(analysis.collided(ep))[0]
    oth = np.nonzero(~ep["collision"] & ~ep["nonfinite"])[0]
    k = min(n_collisions, col.size)
    return [int(r) for r in rng.choice(col, k, replace=False)] + \
        [int(r) for r in rng.choice(oth, min(n - k, oth.size), replace=False)]


def _distance_panel(ax, traj, k, title):
    v = np.asarray(traj.valid[k])
    t = np.asarray(traj.t[k])[v]
    d = np.asarray(traj.distance[k])[v]
    hr = np.asarray(traj.high_risk[k])[v]
    ax.axhspan(0, 1.0, color="0.85", label="collision zone (< 1 m)")
    ax.plot(t, d, color="0.6", lw=1, zorder=1)
    ax.scatter(t[hr], d[hr], s=8, color="tab:red", label="high-risk", zorder=2)
    ax.scatter(t[~hr], d[~hr], s=8, color="tab:green", label="low-risk", zorder=2)
    ax.set_title(title)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("Euclidean distance [m]")
    ax.set_ylim(bottom=0)


def prepare(space, sut, sut_params, world) -> None:
    """Build what :func:`make_figures` needs, ahead of time (``runs.execute`` calls it in a
    background thread while the campaign compiles): matplotlib, the ground truth of the space
    (per-user cache) and the compiled trajectory program."""
    import jaxfalsify as jf
    from jaxfalsify.sweep import ground_truth

    _plt()
    if space.size <= TRUTH_LIMIT:
        ground_truth(space, sut, sut_params, world)
    jf.simulate(space.scenario(np.zeros((N_TRAJECTORIES, len(space.shape)), np.int32)),
                sut=sut, sut_params=sut_params, world=world)


def make_figures(run_dir: Path, world=None) -> list[Path]:
    """Draw every figure into ``run_dir/figures``; returns the files written. The scenarios
    shown are re-simulated in one call; the critical-region map uses the cached ground truth
    (:func:`jaxfalsify.sweep.ground_truth`) for spaces of up to 5e6 scenarios."""
    import jaxfalsify as jf
    from jaxfalsify.sweep import ground_truth

    world = world or jf.WORLD
    plt = _plt()
    run_dir = Path(run_dir)
    sp, rc, summary, ep = load_run(run_dir)
    out = run_dir / "figures"
    out.mkdir(exist_ok=True)
    written = []

    def save(fig, name):
        path = out / name
        with store.atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=DPI, format="png")
        plt.close(fig)
        written.append(path)

    # Fig. 7: reward per episode
    fig, ax = plt.subplots(figsize=FIGSIZE, layout="constrained")
    e, r = ep["evaluation"], ep["reward"]
    ax.plot(e, r, ".", ms=2, color="tab:blue", alpha=0.4, label="reward per evaluation")
    w = max(1, min(100, len(r) // 10))
    ma = np.convolve(np.nan_to_num(r), np.ones(w) / w, mode="valid")
    ax.plot(e[w - 1:], ma, color="tab:orange", lw=2, label=f"moving average ({w})")
    ax.set_xlabel("evaluation (episode)")
    ax.set_ylabel("reward")
    ax.set_title(f"{rc.strategy} on {sp.name}, {rc.sut}, seed {rc.seed}")
    ax.legend(loc="lower right")
    save(fig, "reward_per_episode.png")

    # every scenario shown below, simulated in one call
    rows = pick(ep)
    typical = rows["typical"] if rows["typical"] is not None else rows["best"]
    chosen = fig10_rows(ep, N_TRAJECTORIES - 2)
    shown = [rows["best"], typical] + chosen
    shown += [shown[0]] * (N_TRAJECTORIES - len(shown))  # a fixed batch: one compiled program
    traj = jf.simulate(sp.scenario(indices_of(ep, sp, shown)), sut=rc.sut,
                       sut_params=dict(rc.sut_params), world=world)

    # Fig. 8/9: the best critical scenario vs a typical non-critical one
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5), sharey=True, layout="constrained")
    best_label = "challenging (best)" if analysis.collided(ep)[rows["best"]] else \
        "best (no collision)"
    _distance_panel(axes[0], traj, 0, best_label)
    _distance_panel(axes[1], traj, 1, "non-challenging (typical)")
    axes[0].legend(loc="upper right")
    save(fig, "distance_challenging.png")

    fig, ax = plt.subplots(figsize=(5, 4.5), layout="constrained")
    shares = [100 * ep["high_risk_share_second_half"][r] for r in (rows["best"], typical)]
    ax.bar([best_label.split(" (")[0], "non-challenging"], shares,
           color=["tab:red", "tab:green"])
    ax.set_ylabel("high-risk steps in the second half [%]")
    ax.set_ylim(0, 100)
    for i, s in enumerate(shares):
        ax.text(i, s + 2, f"{s:.0f} %", ha="center")
    save(fig, "high_risk_second_half.png")

    # Fig. 10: 14 scenarios, collisions red
    fig, ax = plt.subplots(figsize=FIGSIZE, layout="constrained")
    ax.axhspan(0, 1.0, color="0.85")
    for k, row in enumerate(chosen):
        v = np.asarray(traj.valid[2 + k])
        ax.plot(np.asarray(traj.t[2 + k])[v], np.asarray(traj.distance[2 + k])[v],
                color="tab:red" if ep["collision"][row] else "tab:green", lw=1.2)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("Euclidean distance [m]")
    ax.set_title(f"{len(chosen)} evaluated scenarios: collisions red, others green")
    ax.set_ylim(bottom=0)
    save(fig, "distance_14_scenarios.png")

    # Critical-region maps from the exhaustive sweep
    if sp.size <= TRUTH_LIMIT:
        truth = ground_truth(sp, rc.sut, dict(rc.sut_params), world)
        save(critical_region_figure(plt, sp, truth, ep), "critical_regions.png")
    return written


def critical_region_figure(plt, sp, sweep: dict, ep: dict | None = None):
    """Collision share over every pair of parameters (marginalising the others); ``sweep``
    holds ``collision`` ``(N,)`` in scenario order."""
    P = len(sp.names)
    pairs = list(itertools.combinations(range(P), 2))
    cols = min(4, len(pairs))
    rows = -(-len(pairs) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.2 * rows), squeeze=False)
    idx = np.asarray(sp.unravel(np.arange(sp.size)))
    col = sweep["collision"].astype(np.float64)
    for ax, (a, b) in zip(axes.ravel(), pairs):
        na, nb = sp.shape[a], sp.shape[b]
        hits = np.zeros((na, nb))
        count = np.zeros((na, nb))
        np.add.at(hits, (idx[:, a], idx[:, b]), col)
        np.add.at(count, (idx[:, a], idx[:, b]), 1.0)
        im = ax.imshow((hits / np.maximum(count, 1)).T, origin="lower", aspect="auto",
                       cmap="Reds", vmin=0, vmax=1)
        if ep is not None:
            ax.plot(ep[f"{sp.names[a]}_idx"] + np.random.default_rng(0).uniform(
                -0.3, 0.3, len(ep["reward"])), ep[f"{sp.names[b]}_idx"]
                + np.random.default_rng(1).uniform(-0.3, 0.3, len(ep["reward"])),
                ".", ms=1, color="tab:blue", alpha=0.3)
        ax.set_xlabel(f"{sp.names[a]} (index)")
        ax.set_ylabel(f"{sp.names[b]} (index)")
    for ax in axes.ravel()[len(pairs):]:
        ax.axis("off")
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.6, label="collision share")
    fig.suptitle("Critical regions (exhaustive sweep); dots: the run's evaluated scenarios")
    return fig
