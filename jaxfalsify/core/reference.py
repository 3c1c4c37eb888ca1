"""A plain NumPy reference of the crossing rollout: the test oracle and the benchmark baseline.

Independent of the JAX code path: float64, an explicit Python loop over time steps (vectorised
over the batch only), its own implementation of the pedestrian profile (the original's loop),
CARLA's PID and the Traffic Manager's collision stage, the metrics and the paper's reward. It
shares only the constants (``World``,
the SUT parameter tuples). Supports the ``carla-tm`` and ``none`` SUTs.
"""

from __future__ import annotations

import math

import numpy as np

from jaxfalsify.core.sim import WORLD, World
from jaxfalsify.scenario.space import KNOWN_PARAMETERS
from jaxfalsify.suts.registry import REGISTRY

__all__ = ["reference_evaluate", "ttc_scalar", "python_loop_evaluate"]


def _rss(v):
    # d_min = v*1 + 3.5/2 + (v + 3.5)^2 / (2*4) - 0, floored at 0 (paper Eq. 4, ad-rss-lib)
    return np.maximum(v * 1.0 + 0.5 * 3.5 + (v + 3.5) ** 2 / 8.0, 0.0)


def _round_half_up(x, decimals):
    f = 10.0**decimals
    return np.floor(x * f + 0.5) / f


def reference_evaluate(scenario: dict, sut: str = "carla-tm", world: World = WORLD,
                       record: bool = False) -> dict:
    """Evaluate a flat batch ``{name: (B,)}``; returns a dict of ``(B,)`` NumPy arrays with the
    same outcome fields as :class:`jaxfalsify.core.sim.Outcome` (float64); with ``record`` also
    ``ego_x``, ``ego_speed``, ``ped_y``, ``distance`` (between the boxes) and ``valid``
    histories ``(B, T)`` (after each step)."""
    if sut not in ("carla-tm", "none"):
        raise ValueError(f"the reference supports carla-tm and none, not '{sut}'")
    w = world
    B = len(np.atleast_1d(next(iter(scenario.values()))))
    p = {k: np.broadcast_to(np.asarray(scenario.get(k, spec["default"]), np.float64), (B,))
         for k, spec in KNOWN_PARAMETERS.items()}
    tm = REGISTRY[sut].default_params
    dt = w.dt
    L, W, PL, PW = w.ego_length, w.ego_width, w.ped_length, w.ped_width
    ego_y = -w.lane_width / 2
    right = -w.lane_width * w.lanes_right
    px = w.crosswalk_x

    x = -p["ego_offset"].copy()
    v = np.zeros(B)
    py = right + w.walker_base - (p["ped_offset"] + 1.0)
    ped_v = np.zeros(B)  # the walker's velocity, as the SUT sees it (last step's)
    integral, prev_e = np.zeros(B), np.zeros(B)
    alive = np.ones(B, bool)
    collided = np.zeros(B, bool)
    coll_step = np.full(B, -1)
    hr_flags = np.zeros((B, w.horizon), bool)
    n = np.zeros(B, int)
    min_d = _box_gap(x, py, w)
    last_c = np.full(B, np.nan)
    min_ttc = np.full(B, np.inf)
    min_rss = np.full(B, np.inf)
    hist = {k: np.zeros((B, w.horizon)) for k in ("ego_x", "ego_speed", "ped_y", "distance",
                                                   "valid")}

    # the original's pdf.py loop: s starts at speed - 5*accel; steps 0..5 at s; then s += accel
    # per step until it exceeds speed + 0.25; the change window (6 steps from T) walks at
    # s + change and does not advance s, whatever the change
    s = p["ped_speed"] - 5 * p["ped_accel"]
    T = p["ped_change_step"]
    for k in range(w.horizon):
        in_win = (k >= T) & (k <= T + 5)
        grow = ~in_win & (k > 5) & (s <= p["ped_speed"] + 0.25 + 1e-4 * p["ped_accel"]) \
            & (p["ped_accel"] > 0)
        s = np.where(grow, s + p["ped_accel"], s)
        vp = np.maximum(np.where(in_win, s + p["ped_speed_change"], s), 0.0)

        # SUT: CARLA's PID, and for carla-tm the collision stage's hazard decision
        target = tm.speed_limit / 3.6 * (1 - tm.below_limit / 100)
        e = (v - target) / target
        integral = np.clip(integral + e * tm.pid_dt, -5, 5)
        expr = tm.kp * e + tm.ki * integral + tm.kd * (e - prev_e) / tm.pid_dt
        prev_e = e
        cmd = np.where(expr < 0, np.minimum(-expr, tm.max_throttle) * tm.throttle_accel,
                       -np.minimum(expr, 1.0) * tm.full_brake)
        if sut == "carla-tm":
            hazard = tm_hazard_reference(x, ego_y, v, px, py, ped_v, L, W, PL, PW, tm)
            cmd = np.where(hazard, -tm.full_brake, cmd)
            integral = np.where(hazard, 0.0, integral)

        # the tick
        a = np.clip(cmd, -w.max_brake, w.max_accel)
        v_new = v + a * dt
        stop = v_new < 0
        dx = np.where(stop, v**2 / (2 * np.maximum(-a, 1e-12)), (v + v_new) / 2 * dt)
        v1, x1, y1 = np.maximum(v_new, 0), x + dx, py + vp * dt

        # metrics on the state after the tick
        gx = abs(px - x1) - (L + PL) / 2
        gy = abs(y1 - ego_y) - (W + PW) / 2
        d = np.hypot(np.maximum(gx, 0), np.maximum(gy, 0))
        centre_after = np.sqrt((px - x1) ** 2 + (y1 - ego_y) ** 2 + w.origin_dz ** 2)
        centre_before = np.sqrt((px - x) ** 2 + (py - ego_y) ** 2 + w.origin_dz ** 2)
        valid = alive.copy()
        ahead = px + PL / 2 > x1 + L / 2
        hr_flags[:, k] = valid & ahead & (_rss(v1) > centre_after)
        min_rss = np.where(valid & ahead, np.minimum(min_rss, centre_after - _rss(v1)), min_rss)
        n += valid
        # contact during the tick: the times the ego's centre enters and leaves the x band
        # (roots of its constant-acceleration motion) against the walker's y band times
        swept = _swept_overlap(x, v, a, py, vp, px, ego_y, (L + PL) / 2, (W + PW) / 2, dt)
        hit = valid & (((gx <= 0) & (gy <= 0)) | swept)
        d = np.where(hit, 0.0, d)
        min_d = np.where(valid, np.minimum(min_d, d), min_d)
        last_c = np.where(valid, centre_before, last_c)
        cx = np.where(px > x1, v1, -v1)
        cy = np.where(y1 < ego_y, vp, -vp)
        ttc = np.where(hit, 0.0, _ttc_vector(gx, gy, cx, cy, L + PL, W + PW))
        min_ttc = np.where(valid, np.minimum(min_ttc, ttc), min_ttc)
        collided |= hit
        coll_step = np.where(hit, k + 1, coll_step)
        done = hit | (x > w.end_x)
        x, v = np.where(valid, x1, x), np.where(valid, v1, v)
        py, ped_v = np.where(valid, y1, py), np.where(valid, vp, ped_v)
        alive = valid & ~done
        for key, val in (("ego_x", x), ("ego_speed", v), ("ped_y", py), ("distance", d),
                         ("valid", valid)):
            hist[key][:, k] = val

    hr = hr_flags.sum(1)
    second = np.array([hr_flags[i, n[i] // 2:n[i]].sum() for i in range(B)])
    frac_rss = _round_half_up((hr - 1) / np.maximum(n - 1, 1), 2)
    r_rss = 0.02 * frac_rss - 0.01
    r_dist = 0.02 * (1 - np.round((last_c - 1) / 9, 2)) - 0.01
    r_col = np.where(collided, 0.25, 0.0)
    return dict(
        reward=r_rss + r_dist + r_col, reward_rss=r_rss, reward_distance=r_dist,
        reward_collision=r_col, collision=collided,
        collision_time=np.where(collided, coll_step * dt, np.nan),
        min_distance=min_d, final_distance=last_c, high_risk_steps=hr,
        high_risk_share=hr / np.maximum(n, 1),
        high_risk_share_second_half=second / np.maximum(n - n // 2, 1),
        robustness=min_d - w.epsilon, steps=n, min_ttc=min_ttc, min_rss_margin=min_rss,
        **(hist if record else {}))


def _reach_time(x, v, a, target):
    """First time [s] at which ``x + v t + a t^2 / 2`` (stopping at v = 0) reaches
    ``target`` >= x: the smaller root of the quadratic, in the cancellation-free form
    ``2 D / (v + sqrt(v^2 + 2 a D))``; inf where it never does."""
    D = target - x
    disc = v * v + 2 * a * D
    den = v + np.sqrt(np.maximum(disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where((disc >= 0) & (den > 0), 2 * D / np.where(den > 0, den, 1.0), np.inf)
    return np.where(D <= 0, 0.0, t)


def _swept_overlap(x, v, a, py, vp, px, ego_y, hx, hy, dt):
    """Do the boxes overlap at some instant of a tick of ``dt`` s? The ego's centre is in
    the band ``|x - px| <= hx`` between the times it reaches ``px - hx`` and passes
    ``px + hx``; the walker's centre in ``|y - ego_y| <= hy`` between the times its linear
    motion crosses the band's edges."""
    t_in, t_out = _reach_time(x, v, a, px - hx), _reach_time(x, v, a, px + hx)
    t_out = np.where(x > px + hx, -np.inf, t_out)  # already past: never in the band again
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (ego_y - hy - py) / vp, (ego_y + hy - py) / vp
    inside = np.abs(py - ego_y) <= hy
    ya = np.where(vp != 0, np.minimum(t1, t2), np.where(inside, 0.0, np.inf))
    yb = np.where(vp != 0, np.maximum(t1, t2), np.where(inside, np.inf, -np.inf))
    lo = np.maximum.reduce([t_in, ya, np.zeros_like(x)])
    hi = np.minimum.reduce([t_out, yb, np.full_like(x, dt)])
    return lo <= hi


def _box_gap(x, py, w):
    gx = abs(w.crosswalk_x - x) - (w.ego_length + w.ped_length) / 2
    gy = abs(py + w.lane_width / 2) - (w.ego_width + w.ped_width) / 2
    return np.hypot(np.maximum(gx, 0), np.maximum(gy, 0))


def _extension(v, tm):
    """The pipeline-era GetBoundingBoxExtention, written as CARLA's if/else chain."""
    out = np.empty_like(v)
    for i, s in enumerate(v):
        if s > tm.highway_speed:
            out[i] = tm.highway_time * s
        elif s < tm.crawl_speed:
            out[i] = tm.ext_min
        else:
            out[i] = math.sqrt(tm.ext_square_point * s) + tm.time_horizon * s + tm.ext_min
    return out


def _interval_gap(a0, a1, b0, b1):
    return np.maximum(np.maximum(b0 - a1, a0 - b1), 0.0)


def tm_hazard_reference(ex, ey, v, px, py, pv, L, W, PL, PW, tm):
    """The collision stage's decision for a walker, NumPy (float64): the same rules as
    ``jaxfalsify.suts.carla_tm.carla_tm_hazard``, written separately from CARLA's description."""
    ex, v, py, pv = (np.asarray(a, np.float64) for a in (ex, v, py, pv))
    ext = _extension(np.atleast_1d(v), tm).reshape(v.shape)
    geo_ext = np.maximum(tm.leading_distance, ext)
    grow = tm.walker_time * np.abs(pv)
    wx0, wx1 = px - PL / 2 - grow, px + PL / 2 + grow
    wy0, wy1 = py - PW / 2 - grow, py + PW / 2 + grow
    gy = _interval_gap(ey - W / 2, ey + W / 2, wy0, wy1)
    g_geo = _interval_gap(ex - L / 2, ex + L + geo_ext, wx0, wx1)
    g_box = _interval_gap(ex - L / 2, ex + L / 2, wx0, wx1)
    geo, bb = np.hypot(g_geo, gy), np.hypot(g_box, gy)
    dx, dy = px - ex, py - ey
    d2 = dx**2 + dy**2
    lim = tm.bbox_multiplier * (L / 2 + PW / 2)
    behind_far = (dx < 0) & (d2 > (ext + lim) ** 2)
    ahead_far = (dx > 0) & (d2 > np.maximum((ext + lim) ** 2, (tm.leading_distance + lim) ** 2))
    unit = np.sqrt(np.maximum(d2, 1e-300))
    dr, do = dx / unit, -dy / unit
    rule = ((bb > tm.touch) & (bb > geo)) | ((bb < tm.touch) & (dr > do))
    return ~behind_far & ~ahead_far & (geo < tm.touch) & rule


def _ttc_vector(gx, gy, cx, cy, span_x, span_y):
    lo = np.zeros_like(gx)
    hi = np.full_like(gx, np.inf)
    never = np.zeros(gx.shape, bool)
    for g, c, s in ((gx, cx, span_x), (gy, cy, span_y)):
        with np.errstate(divide="ignore", invalid="ignore"):
            moving, away = c > 1e-6, c < -1e-6
            start = np.where(moving, np.maximum(g / np.where(moving, c, 1), 0.0), 0.0)
            end = np.where(moving, np.where(g + s > 0, (g + s) / np.where(moving, c, 1), -np.inf),
                           np.where(away, g / np.where(away, c, 1), np.inf))
        never |= ~moving & ~((g <= 0) & (g + s > 0))
        lo, hi = np.maximum(lo, start), np.minimum(hi, end)
    return np.where(~never & (lo <= hi), lo, np.inf)


def ttc_scalar(gx, gy, cx, cy, span_x, span_y):
    """Earliest t >= 0 with both axes overlapping (|gap - c*t| windows), or inf."""
    windows = []
    for g, c, s in ((gx, cx, span_x), (gy, cy, span_y)):
        if c > 1e-6:
            windows.append((max(g / c, 0.0), (g + s) / c if g + s > 0 else -math.inf))
        elif g <= 0 and g + s > 0:  # overlapping: until an opening axis's gap reaches 0
            windows.append((0.0, g / c if c < -1e-6 else math.inf))
        else:
            return math.inf
    lo = max(w[0] for w in windows)
    hi = min(w[1] for w in windows)
    return lo if lo <= hi else math.inf


def python_loop_evaluate(scenario: dict, world: World = WORLD) -> dict:
    """One scenario at a time, scalar Python (the original's shape of work); benchmark only."""
    B = len(np.atleast_1d(next(iter(scenario.values()))))
    outs = [reference_evaluate({k: np.atleast_1d(v)[i:i + 1] for k, v in scenario.items()},
                               world=world) for i in range(B)]
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}
