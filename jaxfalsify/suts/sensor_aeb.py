"""``sensor-aeb``: a perception-based AEB on the autopilot whose detection degrades with light,
glare and rain, with staged braking on time-to-collision and friction-limited braking on wet
roads."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.scenario import metrics, weather
from jaxfalsify.suts.autopilot import AutopilotParams, autopilot_command, pid_init
from jaxfalsify.suts.interface import G, Observation

__all__ = ["SensorAEBParams", "sensor_capability", "sensor_aeb_act", "sensor_init"]


@pytree.dataclass
class SensorAEBParams(AutopilotParams):
    """A perception-based AEB (camera + radar class) on the autopilot, degraded by weather.

    Detection: the pedestrian's centre within ``range`` metres and ``fov`` degrees of the
    bumper's centre line; a braking demand must persist for a latency (confirmation +
    actuation) that grows as light fails and rain falls.
    Weather model (constants are parameters; sources in README 'Systems under test'):

    * light: relative illuminance ``E = sin(sun altitude) * (1 - 0.75 * (cloud/100)^3.4)``
      (clear-sky irradiance ~ sin(altitude); Kasten & Czeplak 1980 cloud factor); latency
      ``+ dark_latency * (1 - E)`` (camera detection degrades in low light: AAA 2019, IIHS);
    * glare: the sun below ``glare_altitude`` (low sun into the camera) cuts range by
      ``glare_range_loss`` scaled by the clear-sky share ``1 - cloud/100``;
    * rain: range ``* (1 - rain_range_loss * precipitation/100)``, latency
      ``+ rain_latency * precipitation/100`` (Zang et al. 2019, IEEE VT Magazine);
    * wet road: friction falls from ``mu_dry`` to ``mu_wet`` as deposits go 0 -> 100 %;
      the AEB's full stage brakes at ``mu * g`` (the tyres' limit; the autopilot's
      ``full_brake``, its pedal at brake 1.0, is not used by the AEB).

    Braking is staged on TTC: ``partial_brake`` below ``ttc_partial`` s, full below
    ``ttc_full`` s. The TTC is the constant-velocity one of :func:`metrics.time_to_collision`
    with an *in-path* target model: a pedestrian walking away from the ego's centre line is
    taken to stay where it is laterally (no prediction that it leaves the path), so the AEB
    keeps braking for a pedestrian inside its path until the car stops or the pedestrian is out.

    ``latency`` counts from the first step a demand is perceived: with ``dt`` 0.1 s a latency
    of 0.1 s brakes one step after that, 0 on the same step. The weather's terms add to it
    (at least ``dark_latency * (1 - 0.965)`` = 0.014 s, the brightest preset's illuminance
    being 0.965) and it is served in whole steps, so the default brakes two steps after.
    """

    range: float = 40.0  # m, clear day
    fov: float = 50.0  # deg, full angle
    latency: float = 0.1  # s, confirmation + actuation in full daylight
    dark_latency: float = 0.4  # s added at zero illuminance
    glare_altitude: float = 20.0  # deg
    glare_range_loss: float = 0.5  # fraction under a clear low sun
    rain_range_loss: float = 0.5  # fraction at 100 % precipitation
    rain_latency: float = 0.3  # s added at 100 % precipitation
    ttc_partial: float = 1.6  # s
    ttc_full: float = 0.9  # s
    partial_brake: float = 4.0  # m/s^2
    mu_dry: float = 0.9
    mu_wet: float = 0.55

    RANGES = {"range": "(0, inf)", "fov": "(0, 360]", "latency": "[0, inf)",
              "dark_latency": "[0, inf)", "glare_altitude": "[0, 90]",
              "glare_range_loss": "[0, 1]", "rain_range_loss": "[0, 1]",
              "rain_latency": "[0, inf)", "ttc_partial": "[0, inf)", "ttc_full": "[0, inf)",
              "partial_brake": "[0, inf)", "mu_dry": "(0, inf)", "mu_wet": "(0, inf)"}


def illuminance(weather_index) -> jax.Array:
    """Relative daylight illuminance in [0, 1] of a weather preset (see SensorAEBParams)."""
    row = jnp.asarray(weather.TABLE)[jnp.asarray(weather_index, jnp.int32)]
    cloud, sun = row[0] / 100.0, row[3]
    return jnp.sin(jnp.deg2rad(jnp.clip(sun, 0.0, 90.0))) * (1.0 - 0.75 * cloud**3.4)


def sensor_capability(weather_index, p: SensorAEBParams):
    """(range [m], latency [s], max deceleration [m/s^2]) under a weather preset."""
    row = jnp.asarray(weather.TABLE)[jnp.asarray(weather_index, jnp.int32)]
    cloud, rain, deposits, sun = row[0] / 100.0, row[1] / 100.0, row[2] / 100.0, row[3]
    glare = jnp.where(sun < p.glare_altitude, p.glare_range_loss * (1.0 - cloud), 0.0)
    rng = p.range * (1.0 - p.rain_range_loss * rain) * (1.0 - glare)
    latency = p.latency + p.dark_latency * (1.0 - illuminance(weather_index)) \
        + p.rain_latency * rain
    mu = p.mu_dry + (p.mu_wet - p.mu_dry) * deposits
    return rng, latency, mu * G


def sensor_aeb_act(obs: Observation, state, p: SensorAEBParams, key):
    """State: (consecutive steps a braking demand has been perceived (int32), PID state).

    A demand is a detected pedestrian with TTC below ``ttc_partial``; the brake acts once the
    demand has persisted for the weather's latency (perception confirmation + actuation)."""
    armed_for, pid = state
    rng, latency, decel = sensor_capability(obs.weather, p)
    front = obs.ego_x + obs.ego_length / 2
    dx = obs.ped_x - front
    dy = obs.ped_y - obs.ego_y
    in_fov = (dx > 0) & (jnp.abs(jnp.arctan2(dy, jnp.maximum(dx, 1e-6))) <= jnp.deg2rad(p.fov / 2))
    detected = in_fov & (dx * dx + dy * dy <= rng * rng)
    gap_x, gap_y = metrics.box_gaps(obs.ped_x - obs.ego_x, obs.ped_y - obs.ego_y,
                                    (obs.ego_length + obs.ped_length) / 2,
                                    (obs.ego_width + obs.ped_width) / 2)
    # in-path target model: a pedestrian walking away from the centre line is held in place
    closing_y = jnp.maximum(-jnp.sign(obs.ped_y - obs.ego_y) * obs.ped_vy, 0.0)
    ttc = metrics.time_to_collision(gap_x, gap_y, obs.ego_speed, closing_y,
                                    obs.ego_length + obs.ped_length,
                                    obs.ego_width + obs.ped_width)
    brake = jnp.where(ttc <= p.ttc_full, decel, jnp.where(ttc <= p.ttc_partial,
                                                          jnp.minimum(p.partial_brake, decel), 0.0))
    armed_for = jnp.where(detected & (brake > 0), armed_for + 1, 0)
    # the demand has persisted (armed_for - 1) steps since it was first perceived
    confirmed = (armed_for > 0) & ((armed_for - 1).astype(jnp.float32) * obs.dt
                                   >= latency - 1e-6)
    cruise, pid = autopilot_command(obs.ego_speed, pid, p)
    accel = jnp.where(confirmed, -brake, cruise)
    return accel, (armed_for, pid)


def sensor_init(key, params):
    return (jnp.int32(0), pid_init(key, params))
