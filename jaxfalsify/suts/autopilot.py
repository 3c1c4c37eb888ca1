"""The autopilot's speed keeping: CARLA 0.9.9 Traffic Manager's PID (``none``: no emergency
braking at all), and a simple speed keeper for users' SUTs (:class:`CruiseParams`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.suts.interface import Observation

__all__ = [
    "CruiseParams", "cruise_command", "AutopilotParams", "target_speed", "pid_init",
    "autopilot_command", "none_act"
]


@pytree.dataclass
class CruiseParams:
    """A simple speed keeper (a clipped P controller), a helper for user SUTs; the built-ins
    use CARLA's PID (:class:`AutopilotParams`)."""

    cruise_speed: float = 30.0 / 3.6 * 0.7  # m/s
    gain: float = 1.0  # 1/s
    accel_max: float = 1.5  # m/s^2, comfortable launch
    decel_max: float = 3.0  # m/s^2, normal (non-emergency) braking

    RANGES = {"cruise_speed": "[0, inf)", "gain": "[0, inf)", "accel_max": "[0, inf)",
              "decel_max": "[0, inf)"}


def cruise_command(speed, p) -> jax.Array:
    """Speed-keeping acceleration command [m/s^2] (``p`` has the :class:`CruiseParams` fields)."""
    return jnp.clip(p.gain * (p.cruise_speed - speed), -p.decel_max, p.accel_max)


@pytree.dataclass
class AutopilotParams:
    """CARLA 0.9.9's Traffic Manager speed keeping (pipeline era: ``PIDController.cpp``,
    ``MotionPlannerStage.cpp``, ``TrafficManager.cpp``; see README 'Systems under test').

    Target speed = ``speed_limit * (1 - below_limit / 100)`` (TM's default: 30 % below the
    limit). PID on the normalised error ``e = (v - target) / target`` with CARLA's urban
    longitudinal gains and its fixed ``pid_dt = 1/20 s``; the integral clamped to +-5;
    ``expr < 0`` gives throttle ``min(-expr, 0.7)``, otherwise brake ``min(expr, 1)``.

    Not fixed by CARLA's code (assumptions, parameters): Town05's speed limit where the original
    spawns (40 km/h), and the accelerations that full throttle and a full brake
    pedal give the BMW Gran Tourer (``throttle_accel``, ``full_brake``; no drag, no gears).
    """

    speed_limit: float = 40.0  # km/h (assumption, calibrated; Town05 has 30-60 km/h roads)
    below_limit: float = 30.0  # %, CARLA's perc_difference_from_limit default
    kp: float = 2.0  # CARLA urban longitudinal gains {2.0, 0.05, 0.07}
    ki: float = 0.05
    kd: float = 0.07
    pid_dt: float = 0.05  # s, CARLA's PID assumes 20 FPS whatever the tick
    max_throttle: float = 0.7
    throttle_accel: float = 2.75  # m/s^2 at throttle 1.0 (assumption, calibrated)
    full_brake: float = 6.0  # m/s^2 at brake 1.0 (assumption, calibrated)

    # below_limit < 0: faster than the limit, as in CARLA
    RANGES = {"speed_limit": "(0, inf)", "below_limit": "(-inf, 100)", "kp": "[0, inf)",
              "ki": "[0, inf)", "kd": "[0, inf)", "pid_dt": "(0, inf)",
              "max_throttle": "[0, 1]", "throttle_accel": "(0, inf)", "full_brake": "(0, inf)"}


def target_speed(p) -> jax.Array:
    """The autopilot's target speed [m/s]."""
    return p.speed_limit / 3.6 * (1.0 - p.below_limit / 100.0)


def pid_init(key, params):
    """PID state: (integral of the normalised error [s], previous normalised error)."""
    return (jnp.float32(0.0), jnp.float32(0.0))


def autopilot_command(speed, pid, p: AutopilotParams):
    """One PID step: ``(acceleration [m/s^2], new pid state)``."""
    integral, prev = pid
    target = jnp.maximum(target_speed(p), 1e-3)
    e = (speed - target) / target
    integral = jnp.clip(integral + e * p.pid_dt, -5.0, 5.0)
    expr = p.kp * e + p.ki * integral + p.kd * (e - prev) / p.pid_dt
    throttle = jnp.where(expr < 0, jnp.minimum(-expr, p.max_throttle), 0.0)
    brake = jnp.where(expr < 0, 0.0, jnp.minimum(expr, 1.0))
    return throttle * p.throttle_accel - brake * p.full_brake, (integral, e)


def none_act(obs: Observation, state, p: AutopilotParams, key):
    """The autopilot's speed keeping only: no emergency braking at all."""
    return autopilot_command(obs.ego_speed, state, p)
