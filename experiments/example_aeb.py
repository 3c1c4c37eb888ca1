"""An example user SUT: a TTC-triggered AEB with a noisy range sensor.

Name it wherever a SUT is named, by import path:

    jaxfalsify run --sut experiments/example_aeb.py:AEB --sut-param ttc_brake=1.2
    jaxfalsify sweep --sut experiments/example_aeb.py:AEB --sut-param corridor=0,1,2

or from Python: ``jaxfalsify.evaluate(scenario, sut=AEB, sut_params={"noise": 0.5})``.

The contract (see ``jaxfalsify/suts/registry.py``): ``init(key, params) -> state`` and
``act(obs, state, params, key) -> (acceleration command [m/s^2], state)`` for ONE scenario at
ONE step (the simulator vmaps and scans it); ``params`` is a pytree of floats with defaults,
passed traced, so a calibration sweep does not recompile; ``key`` is this step's PRNG key.
"""

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.suts.registry import SUT, cruise_command


@pytree.dataclass
class Params:
    cruise_speed: float = 30.0 / 3.6 * 0.7  # m/s, 30 % below a 30 km/h limit
    gain: float = 1.0  # 1/s, speed-keeping P gain
    accel_max: float = 1.5  # m/s^2
    decel_max: float = 3.0  # m/s^2
    ttc_brake: float = 1.5  # s, brake when the measured time-to-collision falls below this
    brake: float = 7.0  # m/s^2, emergency deceleration
    noise: float = 0.3  # m, standard deviation of the measured gap
    corridor: float = 0.5  # m, lateral margin beside the car in which a pedestrian counts


def init(key, p: Params):
    """State: whether the emergency brake is latched (released once the lane is clear)."""
    return jnp.bool_(False)


def act(obs, braking, p: Params, key):
    front = obs.ego_x + obs.ego_length / 2
    gap = obs.ped_x - obs.ped_length / 2 - front  # m, along the lane
    in_path = jnp.abs(obs.ped_y - obs.ego_y) < (obs.ego_width + obs.ped_width) / 2 + p.corridor
    measured = gap + p.noise * jax.random.normal(key)  # a noisy range sensor
    ttc = measured / jnp.maximum(obs.ego_speed, 0.1)
    ahead = gap > -obs.ped_length
    braking = (braking | (in_path & ahead & (ttc < p.ttc_brake))) & in_path & ahead
    return jnp.where(braking, -p.brake, cruise_command(obs.ego_speed, p)), braking


AEB = SUT("example-aeb", act, init, Params())
