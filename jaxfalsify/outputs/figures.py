"""The paper's figures (and critical-region maps) for a run folder, as PNG files.

One concern: drawing a run folder's figures.

Host-side only (matplotlib, Agg backend); the jitted core never imports this module.

* ``reward_per_evaluation.png`` — reward per evaluation and its moving average (paper Fig. 6;
  for a batch of ``PER_UPDATE_FROM`` or more, the mean reward of each update instead; at most
  ``MAX_POINTS`` evaluations drawn, evenly thinned);
* ``distance_challenging.png`` — distance over time of the best critical scenario and of a
  typical non-critical one, high-risk steps red, low-risk green, the < 1 m collision zone
  shaded (paper Fig. 7);
* ``high_risk_second_half.png`` — their high-risk shares over the second half (paper Fig. 8);
* ``distance_14_scenarios.png`` — distance over time of 14 evaluated scenarios, the critical
  ones red (collisions, or the violations of the run's ``--requirement``), the rest green
  (paper Fig. 9);
* ``critical_regions.png`` — beyond the paper: the collision share of the exhaustive sweep over
  every pair of parameters (a perceptual colour scale fitted to the data), with a subsample of
  the run's evaluated scenarios on top; axes in the parameters' units, ticks at their values;
* ``search_distribution.png`` — beyond the paper: where the search went, per parameter the
  share of each value among the evaluations of each stretch of the run (the learner's
  sampling distribution over time);
* ``failure_clusters.png`` — beyond the paper: the failure clusters
  (:func:`jaxfalsify.outputs.analysis.failure_clusters`), their sizes and the distinct critical
  scenarios on the two parameters they vary most, coloured by cluster.
"""

from __future__ import annotations

import io
import itertools
from pathlib import Path

import numpy as np

from jaxfalsify.core import sim
from jaxfalsify.engine.rundir import load_run, resimulate
from jaxfalsify.engine.truth import ground_truth
from jaxfalsify.io.files import write_all_atomic
from jaxfalsify.outputs import analysis

__all__ = [
    "fig10_rows", "prepare", "make_figures", "critical_region_figure", "search_figure",
    "cluster_figure", "distance_figure", "png", "sweep_figures", "SWEEP_FIGURES"
]

FIGSIZE = (8, 4.5)
MAX_POINTS = 200_000  # evaluations drawn in the reward figure (evenly thinned beyond)
PER_UPDATE_FROM = 256  # batch from which the reward figure's curve is the mean per update
DPI = 100
N_TRAJECTORIES = 16  # simulated per figure set: best, typical and 14 (a fixed shape: one program)
TRUTH_LIMIT = 5_000_000  # largest space whose ground truth the critical-region map sweeps
PNG = {"compress_level": 1}  # fast zlib: ~3x faster to write than the default, ~12 % larger


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ----------------------------------------------------------------------------- fixed layout
# Every figure is placed by hand, with margins measured from its own texts (FreeType metrics,
# nothing drawn), instead of matplotlib's constrained layout, which draws each figure once
# more to measure it and took more than half of the drawing time.
PT = 1 / 72  # inch
EDGE = 0.1  # inch: margin at the figure's edges
TICK = 7 * PT  # tick length + label pad (rc defaults 3.5 + 3.5 pt)
LABELPAD = 4 * PT
LEGEND = 0.34  # inch: a one-row figure legend at the bottom
TITLE = 6 * PT + 1.2 * 12 * PT  # inch: an axes title (pad + one line at 12 pt)


def _line(size: float = 10.0) -> float:
    """Height in inches of one line of text at ``size`` points (ascent + descent)."""
    return 1.2 * size * PT


class _Metrics:
    """Text widths in inches at the figure's dpi (FreeType layout, no drawing)."""

    def __init__(self, fig):
        self.renderer = fig.canvas.get_renderer()
        self.dpi = fig.dpi

    def width(self, texts, size: float = 10.0) -> float:
        from matplotlib.font_manager import FontProperties

        prop = FontProperties(size=size)
        return max((self.renderer.get_text_width_height_descent(str(t), prop, ismath=False)[0]
                    for t in texts if str(t)), default=0.0) / self.dpi


def _tick_texts(axis) -> list[str]:
    """The tick labels an axis with automatic ticks will draw (its locator and formatter)."""
    lo, hi = sorted(axis.get_view_interval())
    eps = 1e-10 * max(1.0, abs(hi - lo))
    locs = [x for x in axis.get_major_locator()() if lo - eps <= x <= hi + eps]
    return axis.get_major_formatter().format_ticks(locs)


def _left_margin(m: _Metrics, ax, size: float = 10.0) -> float:
    """Inches left of an axes for its y tick labels and y label."""
    return (TICK + m.width(_tick_texts(ax.yaxis), size) + LABELPAD
            + (_line(size) if ax.get_ylabel() else 0.0))


def _place(fig, ax, left: float, bottom: float, width: float, height: float) -> None:
    """Put ``ax`` at a rectangle given in inches from the figure's lower-left corner."""
    w, h = fig.get_size_inches()
    ax.set_position([left / w, bottom / h, width / w, height / h])


def _single(plt, figsize, *, top: float = 0.1, legend=False, xlabel=True):
    """A figure with one axes, placed once its texts are known: returns ``(fig, ax, place)``;
    call ``place()`` after drawing into ``ax``. ``top``: inches kept above the axes."""
    fig = plt.figure(figsize=figsize)
    ax = fig.add_axes([0.1, 0.1, 0.8, 0.8])

    def place():
        m = _Metrics(fig)
        left = EDGE + _left_margin(m, ax)
        bottom = EDGE + (LEGEND if legend else 0.0) + TICK + _line() + (
            LABELPAD + _line() if xlabel else 0.0)
        w, h = figsize
        _place(fig, ax, left, bottom, w - left - 0.25, h - bottom - EDGE - top)

    return fig, ax, place


def _bottom_legend(fig, handles=None, labels=None, ncol=2):
    args = () if handles is None else (handles, labels)
    fig.legend(*args, loc="lower center", bbox_to_anchor=(0.5, EDGE / fig.get_figheight()),
               ncol=ncol, frameon=False, borderaxespad=0.0)


def pick(ep: dict) -> dict[str, int | None]:
    """Rows of the best evaluation and of a typical (median-reward) non-critical one."""
    return {"best": analysis.best(ep), "typical": analysis.typical_non_critical(ep)}


def fig10_rows(ep: dict, n: int = 14, n_collisions: int = 3) -> list[int]:
    """Up to ``n`` evaluated scenarios, ``n_collisions`` of them critical (collisions, or the
    run's requirement's violations: paper Fig. 9); a fixed draw so redrawing gives the same
    figure."""
    rng = np.random.default_rng(0)
    crit = analysis.critical(ep)  # a run's requirement's violations (without one: collisions)
    col = np.nonzero(crit)[0]
    oth = np.nonzero(~crit & ~ep["nonfinite"])[0]
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
    ax.set_ylabel("Euclidean distance between the boxes [m]")
    ax.set_ylim(bottom=0)


class Prepared:
    """What :func:`prepare` built ahead of a run's figures: the critical-region map without
    the run's scenarios (``base``), for the space and ground truth it was drawn from."""

    def __init__(self, space, collision, base):
        self.describe, self.collision, self.base = space.describe(), collision, base

    def critical_base(self, sp, collision):
        """The prepared map if it shows this space and ground truth (else None), once."""
        base, self.base = self.base, None
        if base is None or sp.describe() != self.describe or \
                not np.array_equal(collision, self.collision):
            return None
        return base


def prepare(space, sut, sut_params, world, *, trajectories: bool = True,
            critical: bool = True) -> Prepared | None:
    """Build what :func:`make_figures` needs, ahead of time (``runs.execute`` calls it in a
    background thread while the campaign compiles and searches): matplotlib, with
    ``trajectories`` the compiled trajectory program, with ``critical`` the ground truth of
    the space (per-user cache) and the critical-region map up to the run's own scenarios."""
    plt = _plt()
    if trajectories:
        sim.simulate(space.scenario(np.zeros((N_TRAJECTORIES, len(space.shape)), np.int32)),
                     sut=sut, sut_params=sut_params, world=world)
    if not critical or space.size > TRUTH_LIMIT or sum(n > 1 for n in space.shape) < 2:
        return None
    truth = ground_truth(space, sut, sut_params, world)
    return Prepared(space, truth["collision"], _critical_base(plt, space, truth, overlay=True))


def png(plt, fig) -> bytes:
    """The PNG file of ``fig`` (closed afterwards)."""
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=DPI, format="png", pil_kwargs=PNG)
    finally:
        plt.close(fig)
    return buf.getvalue()


SWEEP_FIGURES = ("critical_regions.png", "search_distribution.png", "failure_clusters.png")


def sweep_figures(sp, rc, ep: dict, world, prepared: Prepared | None = None
                  ) -> dict[str, bytes]:
    """The figures drawn from the evaluations alone, no trajectory simulated: the
    critical-region map (a run of a JAX SUT on a space of up to ``TRUTH_LIMIT`` scenarios),
    where the search went and the failure clusters; ``{file name: PNG}`` in that order (a
    subset of :data:`SWEEP_FIGURES`). ``runs.execute`` draws them in a second process
    (:mod:`jaxfalsify.outputs.figure_process`) while it writes the run's files."""
    plt = _plt()
    out = {}
    if not rc.evaluator and sp.size <= TRUTH_LIMIT and sum(n > 1 for n in sp.shape) >= 2:
        truth = ground_truth(sp, rc.sut, dict(rc.sut_params), world)
        base = prepared and prepared.critical_base(sp, truth["collision"])
        out["critical_regions.png"] = png(plt, critical_region_figure(plt, sp, truth, ep,
                                                                      base=base))
    out["search_distribution.png"] = png(plt, search_figure(plt, sp, ep, rc.strategy))
    out["failure_clusters.png"] = png(plt, cluster_figure(plt, sp, ep))
    return out


def make_figures(run_dir: Path, world=None, prepared: Prepared | None = None,
                 drawn_elsewhere=None, folder=None) -> list[Path]:
    """Draw every figure into ``run_dir/figures``; returns the files written. The scenarios
    shown are re-simulated in one call; the critical-region map uses the cached ground truth
    (:func:`jaxfalsify.engine.truth.ground_truth`) for spaces of up to 5e6 scenarios. ``prepared``:
    what :func:`prepare` built for this run (used only where it matches).
    ``drawn_elsewhere``: a callable returning :func:`sweep_figures`' files drawn by another
    process for this run (or None when that failed: they are drawn here). ``folder``: the
    run folder's contents as :func:`~jaxfalsify.engine.rundir.load_run` reads them, when the
    caller holds them (the run that just wrote them); else read from ``run_dir``."""
    world = world or sim.WORLD
    plt = _plt()
    run_dir = Path(run_dir)
    sp, rc, summary, ep = folder if folder is not None else load_run(run_dir)
    out = run_dir / "figures"
    drawn: dict[Path, bytes] = {}  # written together at the end: a failure while drawing
    # leaves the earlier figures as they were, not some redrawn and some not

    def save(fig, name):
        drawn[out / name] = png(plt, fig)

    # Fig. 6: reward per episode
    fig, ax, place = _single(plt, (8, 5), top=TITLE, legend=True)
    e, r = ep["evaluation"], ep["reward"]
    thin = max(1, -(-len(r) // MAX_POINTS))  # every thin-th evaluation drawn (file size, time)
    ax.plot(e[::thin], r[::thin], ".", ms=2, color="tab:blue", alpha=0.4,
            label="reward per evaluation" + (f" (every {thin}th)" if thin > 1 else ""))
    batch = int(rc.batch or 1)
    if batch >= PER_UPDATE_FROM and len(r) >= 2 * batch:  # a batched search: its learning
        # curve is the mean reward of each update
        n_up = -(-len(r) // batch)
        padded = np.full(n_up * batch, np.nan)
        padded[:len(r)] = np.where(np.isfinite(r), r, np.nan)
        with np.errstate(all="ignore"):
            means = np.nanmean(padded.reshape(n_up, batch), axis=1)
        ends = np.minimum(np.arange(1, n_up + 1) * batch, len(r))
        ax.plot(ends, means, color="tab:orange", lw=2, label=f"mean per update ({batch})")
    else:
        w = max(1, min(100, len(r) // 10))
        ma = np.convolve(np.nan_to_num(r), np.ones(w) / w, mode="valid")
        ax.plot(e[w - 1:], ma, color="tab:orange", lw=2, label=f"moving average ({w})")
    ax.set_xlabel("evaluation (episode)")
    ax.set_ylabel("reward")
    ax.set_title(f"{rc.strategy} on {sp.name}, {rc.sut}, seed {rc.seed}")
    _bottom_legend(fig, ncol=2)
    place()
    save(fig, "reward_per_evaluation.png")

    if not rc.evaluator:  # an evaluator's run has no JAX SUT to simulate its scenarios
        _simulated_figures(plt, save, sp, rc, ep, world)
    else:  # but perhaps the trajectories its evaluator returned
        _told_figures(plt, save, run_dir, ep, rc)
    rest = drawn_elsewhere() if drawn_elsewhere is not None else None
    if rest is None:
        rest = sweep_figures(sp, rc, ep, world, prepared)
    drawn.update({out / name: data for name, data in rest.items()})
    out.mkdir(exist_ok=True)
    write_all_atomic(drawn)
    return list(drawn)


def distance_figure(plt, ep: dict, rc, rows, t, distance, valid):
    """Paper Fig. 9: the distance over time of the evaluated ``rows`` (``t``, ``distance``,
    ``valid`` ``(len(rows), T)`` their histories), the critical ones (collisions, or the run's
    requirement's violations) red, the rest green."""
    fig, ax, place = _single(plt, (8, 5), top=TITLE, legend=True)
    ax.axhspan(0, 1.0, color="0.85", label="collision zone (< 1 m)")
    labelled = set()
    crit = analysis.critical(ep)
    req = rc.requirement if rc.requirement not in ("collision", "evaluator") else None
    words = (f"violates {req}", f"satisfies {req}") if req else \
        ("failure", "no failure") if rc.evaluator else ("collision", "no collision")
    # the others first, critical ones on top (drawn last, higher zorder)
    for k, row in sorted(enumerate(rows), key=lambda kr: bool(crit[kr[1]])):
        v = np.asarray(valid[k], bool)
        hit = bool(crit[row])
        label = words[0] if hit else words[1]
        ax.plot(np.asarray(t[k])[v], np.asarray(distance[k])[v],
                color="tab:red" if hit else "tab:green", lw=1.6 if hit else 1.0,
                zorder=3 if hit else 2, label=None if label in labelled else label)
        labelled.add(label)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("Euclidean distance between the boxes [m]")
    ax.set_title(f"{len(rows)} evaluated scenarios")
    ax.set_ylim(bottom=0)
    _bottom_legend(fig, ncol=3)
    place()
    return fig


def _told_figures(plt, save, run_dir: Path, ep: dict, rc) -> None:
    """An evaluator's run: Fig. 9 from the trajectories its evaluator returned (the run
    folder's ``trajectories.npz``), when they hold ``t`` and ``distance``."""
    path = run_dir / "trajectories.npz"
    if not path.exists():
        return
    with np.load(path) as z:
        if not {"t", "distance", "evaluation"} <= set(z.files):
            return
        t, d, ev = z["t"], z["distance"], z["evaluation"]
    n = len(np.asarray(ep["evaluation"]))
    told = np.zeros(n, bool)
    at = np.searchsorted(np.asarray(ep["evaluation"]), ev)  # rows of the stored histories
    ok = at < n
    told[at[ok]] = np.isfinite(d[ok]).any(axis=1)
    kept = np.nonzero(told)[0]  # Fig. 9's rows chosen among the evaluations with a history
    if kept.size:
        sub = {k: np.asarray(v)[kept] for k, v in ep.items()
               if k in ("collision", "violated", "nonfinite")}
        rows = kept[fig10_rows(sub, N_TRAJECTORIES - 2)]
        idx = np.searchsorted(ev, np.asarray(ep["evaluation"])[rows])
        valid = np.isfinite(d[idx]) & np.isfinite(t[idx])
        save(distance_figure(plt, ep, rc, list(rows), t[idx], d[idx], valid),
             "distance_14_scenarios.png")


def _simulated_figures(plt, save, sp, rc, ep, world) -> None:
    """The figures that simulate the run's scenarios again (Fig. 7-9)."""
    # every scenario shown below, simulated in one call
    rows = pick(ep)
    typical = rows["typical"] if rows["typical"] is not None else rows["best"]
    chosen = fig10_rows(ep, N_TRAJECTORIES - 2)
    shown = [rows["best"], typical] + chosen
    shown += [shown[0]] * (N_TRAJECTORIES - len(shown))  # a fixed batch: one compiled program
    traj = resimulate(sp, rc, ep, shown, world)

    # Fig. 7/8: the best critical scenario vs a typical non-critical one
    fig = plt.figure(figsize=(12, 5))
    axes = [fig.add_axes([0.1, 0.1, 0.35, 0.8]), fig.add_axes([0.55, 0.1, 0.35, 0.8])]
    best_label = "challenging (best)" if analysis.collided(ep)[rows["best"]] else \
        "best (no collision)"
    _distance_panel(axes[0], traj, 0, best_label)
    if rows["typical"] is not None:
        _distance_panel(axes[1], traj, 1, "non-challenging (typical)")
    else:  # every evaluation collided: nothing to set beside the best
        _distance_panel(axes[1], traj, 1, "no non-critical scenario evaluated")
        for a in axes[1].collections + axes[1].lines:
            a.remove()
        axes[1].text(0.5, 0.5, "every evaluated scenario collided", ha="center",
                     va="center", transform=axes[1].transAxes)
    handles, labels = axes[0].get_legend_handles_labels()
    _bottom_legend(fig, handles, labels, ncol=3)
    m = _Metrics(fig)
    lefts = [_left_margin(m, ax) for ax in axes]
    bottom = EDGE + LEGEND + TICK + _line() + LABELPAD + _line()
    height = 5 - bottom - EDGE - TITLE
    width = (12 - 2 * EDGE - sum(lefts) - 0.3 - 0.25) / 2
    _place(fig, axes[0], EDGE + lefts[0], bottom, width, height)
    _place(fig, axes[1], EDGE + lefts[0] + width + 0.3 + lefts[1], bottom, width, height)
    save(fig, "distance_challenging.png")

    fig, ax, place = _single(plt, (5, 4.5), top=_line() + 0.05, xlabel=False)
    both = rows["typical"] is not None  # else every evaluation collided: the best alone
    shares = [100 * ep["high_risk_share_second_half"][r]
              for r in ((rows["best"], typical) if both else (rows["best"],))]
    ax.bar([best_label.split(" (")[0], "non-challenging"][:len(shares)], shares,
           color=["tab:red", "tab:green"][:len(shares)])
    if not both:
        ax.set_xlim(-0.5, 1.5)
        ax.text(1, 50, "no non-critical\nscenario evaluated", ha="center", va="center")
    ax.set_ylabel("high-risk steps in the second half [%]")
    ax.set_ylim(0, 100)
    for i, s in enumerate(shares):
        ax.text(i, s + 2, f"{s:.0f} %", ha="center")
    place()
    save(fig, "high_risk_second_half.png")

    # Fig. 9: 14 scenarios, the critical ones (collisions, or the requirement's violations) red
    save(distance_figure(plt, ep, rc, chosen, np.asarray(traj.t)[2:], np.asarray(traj.distance)[2:],
                         np.asarray(traj.valid)[2:]), "distance_14_scenarios.png")


def axis_label(sp, p: int) -> str:
    """``name [unit]`` (or just the name for a unitless parameter)."""
    u = sp.units[p]
    return f"{sp.names[p]} [{u}]" if u else sp.names[p]


def value_ticks(sp, p: int, most: int = 6) -> tuple[np.ndarray, list[str]]:
    """At most ``most`` tick positions (value indices) and their labels: the parameter's own
    values, with the decimals the space declares."""
    n = sp.shape[p]
    pos = np.unique(np.round(np.linspace(0, n - 1, min(n, most))).astype(int))
    return pos, [analysis.format_value(sp, p, sp.table[p][i]) for i in pos]


def pair_shares(sp, collision: np.ndarray, pairs) -> list[np.ndarray]:
    """Collision share ``(n_a, n_b)`` of each pair of parameters ``(a, b)``, marginalising the
    others (``collision`` ``(N,)`` in scenario order: the full grid)."""
    grid = np.asarray(collision, np.float64).reshape(sp.shape)
    out = []
    for a, b in pairs:
        others = tuple(p for p in range(grid.ndim) if p not in (a, b))
        hits = grid.sum(axis=others)  # (n_a, n_b): a < b keeps that order
        out.append(hits / max(sp.size // (sp.shape[a] * sp.shape[b]), 1))
    return out


def _colorbar_width(m: _Metrics, cb, size: float = 10.0) -> float:
    """Inches right of a vertical colorbar for its tick labels and label."""
    return TICK + m.width(_tick_texts(cb.ax.yaxis), size) + LABELPAD + _line(size)


def critical_region_figure(plt, sp, sweep: dict, ep: dict | None = None, points: int = 400,
                           base=None):
    """Collision share over every pair of parameters with two or more values (marginalising
    the others), on a perceptual colour scale fitted to the largest share; ``sweep`` holds
    ``collision`` ``(N,)`` in scenario order; ``ep``: a subsample of ``points`` of the run's
    evaluated scenarios drawn on top (collisions as crosses). Axes in the parameters' units,
    ticks at their values; 2-8 parameters lay out on a grid of at most 4 columns. ``base``:
    the map already drawn without ``ep`` (:func:`prepare`), room left for its legend."""
    overlay = ep is not None and len(ep["reward"]) > 0
    fig, axes, pairs = base or _critical_base(plt, sp, sweep, overlay)
    if overlay:
        rng = np.random.default_rng(0)
        sub = np.sort(rng.choice(len(ep["reward"]), min(points, len(ep["reward"])),
                                 replace=False))
        hit = np.asarray(ep["collision"])[sub].astype(bool)
        for ax, (a, b) in zip(axes, pairs):
            xa = ep[f"{sp.names[a]}_idx"][sub]
            yb = ep[f"{sp.names[b]}_idx"][sub]
            ax.scatter(xa[~hit], yb[~hit], s=5, facecolors="none", edgecolors="white",
                       linewidths=0.5, alpha=0.7, label="evaluated (subsample)")
            ax.scatter(xa[hit], yb[hit], s=14, marker="x", color="tab:red", linewidths=0.8,
                       label="evaluated, collision")
        handles, labels = axes[0].get_legend_handles_labels()
        _bottom_legend(fig, handles, labels, ncol=2)
    return fig


def _critical_base(plt, sp, sweep: dict, overlay: bool):
    """``(fig, axes, pairs)``: the critical-region map without the run's scenarios (room
    left for their legend when ``overlay``)."""
    from matplotlib.colors import Normalize
    from matplotlib.ticker import MaxNLocator

    multi = [p for p in range(len(sp.names)) if sp.shape[p] > 1]
    pairs = list(itertools.combinations(multi, 2))
    cols = min(4, len(pairs))
    rows = -(-len(pairs) // cols)
    W, H = 3.9 * cols + 1.2, 3.5 * rows + 0.8
    fig = plt.figure(figsize=(W, H))
    shares = pair_shares(sp, sweep["collision"], pairs)
    top = max(float(max(np.max(x) for x in shares)), 1e-9)
    norm = Normalize(0.0, top)
    ticks = {p: value_ticks(sp, p) for p in multi}
    axes = []
    for (a, b), share in zip(pairs, shares):
        ax = fig.add_axes([0.1, 0.1, 0.1, 0.1])
        axes.append(ax)
        im = ax.imshow(share.T, origin="lower", aspect="auto", cmap="viridis", norm=norm,
                       interpolation="nearest")
        ax.set_xticks(*ticks[a])
        ax.set_yticks(*ticks[b])
        ax.tick_params(axis="x", labelrotation=45, labelsize=7)
        ax.tick_params(axis="y", labelsize=7)
        ax.set_xlabel(axis_label(sp, a), fontsize=8)
        ax.set_ylabel(axis_label(sp, b), fontsize=8)
    # the layout, in inches: every cell alike, sized for the widest tick labels
    m = _Metrics(fig)
    rot = np.sqrt(0.5) * (max(m.width(ticks[p][1], 7) for p in multi) + _line(7))
    left = TICK + max(m.width(ticks[p][1], 7) for p in multi) + LABELPAD + _line(8)
    below = TICK + rot + LABELPAD + _line(8)
    gap_x, gap_y = max(0.2, rot / 2 + 0.05), 0.25
    grid_bottom = EDGE + (LEGEND if overlay else 0.0)
    grid_top = H - EDGE - _line(12) - 0.15  # below the suptitle
    cell_h = (grid_top - grid_bottom) / rows
    cb_h = 0.8 * (grid_top - grid_bottom - below - gap_y)
    cax = fig.add_axes([0.9, 0.1, 0.02, cb_h / H])
    cb = fig.colorbar(im, cax=cax, ticks=MaxNLocator(6),
                      label=f"collision share (0 .. {top:.2g}, the largest)")
    cb_w = cb_h / 20
    right = 0.3 + cb_w + _colorbar_width(m, cb) + EDGE
    cell_w = (W - EDGE - right) / cols
    for k, ax in enumerate(axes):
        r, c = divmod(k, cols)
        _place(fig, ax, EDGE + c * cell_w + left, grid_top - (r + 1) * cell_h + below,
               cell_w - left - gap_x, cell_h - below - gap_y)
    _place(fig, cax, W - right + 0.3, grid_bottom + below + (grid_top - grid_bottom - below
                                                             - gap_y - cb_h) / 2, cb_w, cb_h)
    fig.suptitle("Critical regions (exhaustive sweep)", y=1 - EDGE / H, va="top")
    return fig, axes, pairs


def search_figure(plt, sp, ep: dict, strategy: str = "", stretches: int = 20):
    """Where the search went: per parameter with two or more values, the share of each of its
    values among the evaluations of each of ``stretches`` equal stretches of the run (an
    estimate of the learner's sampling distribution over time; uniform search is flat)."""
    from matplotlib.ticker import MaxNLocator

    multi = [p for p in range(len(sp.names)) if sp.shape[p] > 1]
    n = len(ep["reward"])
    k = max(1, min(stretches, n))
    edges = np.linspace(0, n, k + 1).astype(int)
    W, H = 3.2 * len(multi) + 1.2, 4.2
    fig = plt.figure(figsize=(W, H))
    bottom = EDGE + TICK + _line(7) + LABELPAD + _line()
    height = H - bottom - EDGE - _line(12) - 0.15
    cb_h = 0.8 * height
    m = _Metrics(fig)
    panels = []
    for p in multi:
        ax = fig.add_axes([0.1, 0.1, 0.1, 0.1])
        vals = ep[f"{sp.names[p]}_idx"]
        freq = np.zeros((sp.shape[p], k))
        for j in range(k):
            seg = vals[edges[j]:edges[j + 1]]
            if seg.size:
                freq[:, j] = np.bincount(seg, minlength=sp.shape[p]) / seg.size
        im = ax.imshow(freq, origin="lower", aspect="auto", cmap="magma",
                       extent=(0, n, -0.5, sp.shape[p] - 0.5), vmin=0,
                       vmax=max(float(freq.max()), 1e-9), interpolation="nearest")
        pos, labels = value_ticks(sp, p)
        ax.set_yticks(pos, labels)
        ax.tick_params(labelsize=7)
        ax.set_xlabel("evaluation")
        ax.set_ylabel(axis_label(sp, p))
        cax = fig.add_axes([0.9, 0.1, 0.02, cb_h / H])
        cb = fig.colorbar(im, cax=cax, ticks=MaxNLocator(5), label="share of the stretch")
        panels.append((ax, cax, TICK + m.width(labels, 7) + LABELPAD + _line(),
                       0.15 + cb_h / 20 + _colorbar_width(m, cb) + 0.1))
    width = (W - 2 * EDGE - sum(lw + rw for _, _, lw, rw in panels)) / max(len(panels), 1)
    x = EDGE
    for ax, cax, lw, rw in panels:
        _place(fig, ax, x + lw, bottom, width, height)
        _place(fig, cax, x + lw + width + 0.15, bottom + (height - cb_h) / 2, cb_h / 20, cb_h)
        x += lw + width + rw
    fig.suptitle(f"Where the search went ({strategy}): share of each value per stretch of "
                 f"{max(1, n // k)} evaluations", y=1 - EDGE / H, va="top")
    return fig


CLUSTER_BARS = 20  # failure clusters the bar chart shows (the largest; summary.json lists as many)
CLUSTER_COLOURS = 9  # failure clusters drawn in their own colour (tab10 but its grey)
CLUSTER_POINTS = 5000  # distinct critical scenarios drawn at most (a fixed subsample beyond)


def cluster_axes(sp, points: np.ndarray) -> tuple[int, int | None]:
    """The two parameters along which ``points`` ``(n, P)`` (index vectors) vary most: the
    most distinct values, then the wider index range, then the space's order; the second is
    None in a one-parameter space."""
    pts = np.asarray(points).reshape(-1, len(sp.names))
    score = [(-len(np.unique(c)), -(int(np.ptp(c)) if c.size else 0), p)
             for p, c in enumerate(pts.T)]
    ranked = [p for _, _, p in sorted(score)]
    return ranked[0], (ranked[1] if len(ranked) > 1 else None)


def cluster_colours(plt, k: int) -> list:
    """A colour per failure cluster 1..k: the 9 largest in tab10's colours (its grey left
    out), the rest light grey."""
    cmap = plt.get_cmap("tab10")
    own = [cmap(i) for i in (0, 1, 2, 3, 4, 5, 6, 8, 9)][:CLUSTER_COLOURS]
    return [own[c] if c < len(own) else "0.75" for c in range(k)]


def cluster_figure(plt, sp, ep: dict):
    """The failure clusters of a run (:func:`jaxfalsify.outputs.analysis.failure_clusters`, from its
    ``evaluations.parquet`` columns ``ep``): left, the size (distinct critical scenarios) of
    the 20 largest, bars in the clusters' colours (:func:`cluster_colours`); right, the
    distinct critical scenarios on the two parameters they vary most (:func:`cluster_axes`;
    value indices jittered by up to 0.3 so that scenarios sharing a cell stay visible, ticks
    at the values; at most 5000, a fixed subsample beyond), each coloured cluster's
    representative (its best-reward member) a black-edged star. A run without a collision
    gets a figure saying so."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    idx, fields = analysis.from_evaluations(ep, sp)
    fc = analysis.failure_clusters(idx, fields)
    W, H = 12, 5
    fig = plt.figure(figsize=(W, H))
    axes = [fig.add_axes([0.1, 0.1, 0.35, 0.8]), fig.add_axes([0.55, 0.1, 0.35, 0.8])]
    colours = cluster_colours(plt, fc.k)
    bars, scat = axes
    shown = min(fc.k, CLUSTER_BARS)
    bars.bar(np.arange(1, shown + 1), fc.sizes[:shown], color=colours[:shown])
    bars.set_xlabel("failure cluster (numbered by size)")
    bars.set_ylabel("distinct critical scenarios")
    bars.set_xlim(0.5, max(shown, 1) + 0.5)
    bars.set_xticks(np.arange(1, shown + 1))
    bars.yaxis.set_major_locator(MaxNLocator(integer=True))
    more = f", {fc.k - shown} smaller not shown" if fc.k > shown else ""
    bars.set_title(f"{fc.k} failure cluster{'s' if fc.k > 1 else ''} of {fc.n} distinct "
                   f"critical scenario{'s' if fc.n > 1 else ''}{more}"
                   if fc.k else "no collision found: no failure clusters", fontsize=10)
    if not fc.k:
        bars.set_xticks([])
        bars.set_yticks([])
    a, b = cluster_axes(sp, fc.indices)
    handles = []
    if fc.k:
        rows = np.arange(fc.n)
        if fc.n > CLUSTER_POINTS:
            rows = np.sort(np.random.default_rng(0).choice(fc.n, CLUSTER_POINTS,
                                                         replace=False))
        jitter = np.random.default_rng(0).uniform(-0.3, 0.3, (rows.size, 2))
        x = fc.indices[rows, a] + jitter[:, 0]
        y = (fc.indices[rows, b] if b is not None else fc.labels[rows]) + jitter[:, 1]
        lab = fc.labels[rows]
        for c in range(fc.k if fc.k <= CLUSTER_COLOURS else CLUSTER_COLOURS + 1, 0, -1):
            sel = lab == c if c <= CLUSTER_COLOURS else lab > CLUSTER_COLOURS
            scat.scatter(x[sel], y[sel], s=10, color=colours[c - 1], alpha=0.7,
                         linewidths=0, zorder=2)
        top = min(fc.k, CLUSTER_COLOURS)
        rep = fc.representative[:top]
        scat.scatter(fc.indices[rep, a], fc.indices[rep, b] if b is not None else
                     np.arange(1, top + 1), s=150, marker="*", color=colours[:top],
                     edgecolors="black", linewidths=0.8, zorder=3)
        handles.append(Line2D([], [], ls="", marker="*", ms=11, color="0.8", mec="black",
                              label="representative (best reward) of a cluster"))
        if fc.k > CLUSTER_COLOURS:
            handles.append(Line2D([], [], ls="", marker="o", ms=4, color=colours[-1],
                                  label=f"clusters {CLUSTER_COLOURS + 1}..{fc.k}"))
        sub = f" ({rows.size} of {fc.n} shown)" if rows.size < fc.n else ""
        scat.set_title(f"Distinct critical scenarios by cluster{sub}", fontsize=10)
    else:
        scat.text(0.5, 0.5, "no collision found", ha="center", va="center",
                  transform=scat.transAxes)
    scat.set_xlim(-0.5, sp.shape[a] - 0.5)
    scat.set_xticks(*value_ticks(sp, a))
    scat.set_xlabel(axis_label(sp, a))
    if b is not None:
        scat.set_ylim(-0.5, sp.shape[b] - 0.5)
        scat.set_yticks(*value_ticks(sp, b))
        scat.set_ylabel(axis_label(sp, b))
    else:
        scat.set_ylim(0.5, max(fc.k, 1) + 0.5)
        scat.yaxis.set_major_locator(MaxNLocator(integer=True))
        scat.set_ylabel("failure cluster")
    if handles:
        _bottom_legend(fig, handles, [h.get_label() for h in handles], ncol=len(handles))
    m = _Metrics(fig)
    lefts = [_left_margin(m, ax) for ax in axes]
    bottom = EDGE + LEGEND + TICK + _line() + LABELPAD + _line()
    height = H - bottom - EDGE - TITLE
    width = (W - 2 * EDGE - sum(lefts) - 0.3 - 0.25) / 2
    _place(fig, axes[0], EDGE + lefts[0], bottom, width, height)
    _place(fig, axes[1], EDGE + lefts[0] + width + 0.3 + lefts[1], bottom, width, height)
    return fig
