"""A plain NumPy reference of the crossing rollout: the test oracle and the benchmark baseline.

Independent of the JAX code path: float64, an explicit Python loop over time steps (vectorised
over the batch only), its own implementation of the pedestrian profile, the Traffic Manager's
emergency stop, the metrics and the paper's reward. It shares only the constants (``World``,
the SUT parameter tuples). Supports the ``carla-tm`` and ``none`` SUTs.
"""

from __future__ import annotations

import math

import numpy as np

from jaxfalsify.sim import WORLD, World
from jaxfalsify.space import KNOWN_PARAMETERS
from jaxfalsify.sut import REGISTRY


def _rss(v):
    # d_min = v*1 + 3.5/2 + (v + 3.5)^2 / (2*4) - 0, floored at 0 (paper Eq. 4, ad-rss-lib)
    return np.maximum(v * 1.0 + 0.5 * 3.5 + (v + 3.5) ** 2 / 8.0, 0.0)


def _round_half_up(x, decimals):
    f = 10.0**decimals
    return np.floor(x * f + 0.5) / f


def reference_evaluate(scenario: dict, sut: str = "carla-tm", world: World = WORLD,
                       record: bool = False) -> dict:
    """Evaluate a flat batch ``{name: (B,)}``; returns a dict of ``(B,)`` NumPy arrays with the
    same outcome fields as :class:`jaxfalsify.sim.Outcome` (float64); with ``record`` also
    ``ego_x``, ``ego_speed``, ``ped_y`` and ``valid`` histories ``(B, T)``."""
    if sut not in ("carla-tm", "none"):
        raise ValueError(f"the reference supports carla-tm and none, not '{sut}'")
    w = world
    B = len(np.atleast_1d(next(iter(scenario.values()))))
    p = {k: np.broadcast_to(np.asarray(scenario.get(k, spec["default"]), np.float64), (B,))
         for k, spec in KNOWN_PARAMETERS.items()}
    cruise = REGISTRY[sut].default_params
    tm = REGISTRY["carla-tm"].default_params
    dt = w.dt
    L, W, PL, PW = w.ego_length, w.ego_width, w.ped_length, w.ped_width
    ego_y = -w.lane_width / 2
    right, left = -w.lane_width * w.lanes_right, w.lane_width * w.lanes_left
    px = w.crosswalk_x

    x = -p["ego_offset"].copy()
    v = np.zeros(B)
    py = right - (p["ped_offset"] + 1.0)
    hold = np.zeros(B, bool)
    alive = np.ones(B, bool)
    collided = np.zeros(B, bool)
    coll_step = np.full(B, -1)
    hr_flags = np.zeros((B, w.horizon), bool)
    n = np.zeros(B, int)
    min_d = np.full(B, np.inf)
    last_d = np.full(B, np.nan)
    min_ttc = np.full(B, np.inf)

    # pedestrian profile: start, then +accel per step from step 5 until above speed + 0.25
    hist = {k: np.zeros((B, w.horizon)) for k in ("ego_x", "ego_speed", "ped_y", "valid")}
    start = p["ped_speed"] - 5 * p["ped_accel"]
    vp_prev = start.copy()
    for k in range(w.horizon):
        if k < 5:
            vp = start.copy()
        else:
            grow = vp_prev <= p["ped_speed"] + 0.25 + 1e-4 * p["ped_accel"]
            vp = np.where(grow & (p["ped_accel"] > 0), vp_prev + p["ped_accel"], vp_prev)
        vp_prev = vp
        win = (k >= p["ped_change_step"]) & (k < p["ped_change_step"] + 5) & \
            (p["ped_speed_change"] != 0)
        vp_eff = np.maximum(np.where(win, start + p["ped_speed_change"], vp), 0.0)

        # SUT
        cruise_a = np.clip(cruise.gain * (cruise.cruise_speed - v), -cruise.decel_max,
                           cruise.accel_max)
        if sut == "carla-tm":
            ext = tm.walker_time * vp_eff
            lat = (py + PW / 2 + ext > ego_y - W / 2) & (py - PW / 2 < ego_y + W / 2)
            front = x + L / 2
            lon = (px + PL / 2 > front) & \
                (px - PL / 2 < front + tm.boundary_min + tm.boundary_rate * v)
            crossed = py - PW / 2 > left
            behind = px + PL / 2 < x - L / 2
            hold = (lat & lon) | (hold & ~crossed & ~behind)
            cmd = np.where(hold, -tm.full_brake, cruise_a)
        else:
            cmd = cruise_a

        # metrics
        gx = abs(px - x) - (L + PL) / 2
        gy = abs(py - ego_y) - (W + PW) / 2
        d = np.hypot(np.maximum(gx, 0), np.maximum(gy, 0))
        valid = alive.copy()
        for key, val in (("ego_x", x), ("ego_speed", v), ("ped_y", py), ("valid", valid)):
            hist[key][:, k] = val
        ahead = px + PL / 2 > x + L / 2
        hr_flags[:, k] = valid & ahead & (_rss(v) > d)
        n += valid
        min_d = np.where(valid, np.minimum(min_d, d), min_d)
        last_d = np.where(valid, d, last_d)
        # time to collision: per-axis overlap windows under constant velocities
        cx = np.where(px > x, v, -v)
        cy = np.where(py < ego_y, vp_eff, -vp_eff)
        ttc = _ttc_vector(gx, gy, cx, cy, L + PL, W + PW)
        min_ttc = np.where(valid, np.minimum(min_ttc, ttc), min_ttc)
        hit = valid & (gx <= 0) & (gy <= 0)
        collided |= hit
        coll_step = np.where(hit, k, coll_step)
        done = hit | (x >= w.end_x)
        alive = valid & ~done

        # integrate
        a = np.clip(cmd, -w.max_brake, w.max_accel)
        v_new = v + a * dt
        stop = v_new < 0
        dx = np.where(stop, v**2 / (2 * np.maximum(-a, 1e-12)), (v + v_new) / 2 * dt)
        x = np.where(alive, x + dx, x)
        v = np.where(alive, np.maximum(v_new, 0), v)
        py = np.where(alive, py + vp_eff * dt, py)

    hr = hr_flags.sum(1)
    second = np.array([hr_flags[i, n[i] // 2:n[i]].sum() for i in range(B)])
    frac_rss = _round_half_up((hr - 1) / np.maximum(n - 1, 1), 2)
    r_rss = 0.02 * frac_rss - 0.01
    r_dist = 0.02 * (1 - np.round((last_d - 1) / 9, 2)) - 0.01
    r_col = np.where(collided, 0.25, 0.0)
    return dict(
        reward=r_rss + r_dist + r_col, reward_rss=r_rss, reward_distance=r_dist,
        reward_collision=r_col, collision=collided,
        collision_time=np.where(collided, coll_step * dt, np.nan),
        min_distance=min_d, final_distance=last_d, high_risk_steps=hr,
        high_risk_share=hr / np.maximum(n, 1),
        high_risk_share_second_half=second / np.maximum(n - n // 2, 1),
        robustness=min_d - w.epsilon, steps=n, min_ttc=min_ttc, **(hist if record else {}))


def _ttc_vector(gx, gy, cx, cy, span_x, span_y):
    lo = np.zeros_like(gx)
    hi = np.full_like(gx, np.inf)
    never = np.zeros(gx.shape, bool)
    for g, c, s in ((gx, cx, span_x), (gy, cy, span_y)):
        with np.errstate(divide="ignore", invalid="ignore"):
            moving = c > 1e-6
            start = np.where(moving, np.maximum(g / np.where(moving, c, 1), 0.0), 0.0)
            end = np.where(moving, np.where(g + s > 0, (g + s) / np.where(moving, c, 1), -np.inf),
                           np.inf)
        never |= ~moving & ~((g <= 0) & (g + s > 0))
        lo, hi = np.maximum(lo, start), np.minimum(hi, end)
    return np.where(~never & (lo <= hi), lo, np.inf)


def ttc_scalar(gx, gy, cx, cy, span_x, span_y):
    """Earliest t >= 0 with both axes overlapping (|gap - c*t| windows), or inf."""
    windows = []
    for g, c, s in ((gx, cx, span_x), (gy, cy, span_y)):
        if c > 1e-6:
            windows.append((max(g / c, 0.0), (g + s) / c if g + s > 0 else -math.inf))
        elif g <= 0 and g + s > 0:
            windows.append((0.0, math.inf))
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
