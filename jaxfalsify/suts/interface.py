"""The interface every system under test implements: what it observes (:class:`Observation`)
and the pair of pure functions it is (:class:`SUT`); see :mod:`jaxfalsify.suts.registry` for the
contract and the registry."""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

__all__ = ["G", "Observation", "no_state", "SUT"]

G = 9.81  # m/s^2


class Observation(NamedTuple):
    """What a SUT sees at one step (ground truth; a perception SUT filters it itself).

    Positions are box centres [m] in the road frame (x along the ego's lane, y to the left);
    speeds [m/s]; sizes are full box lengths [m]; ``dt`` the step [s]; ``weather`` the CARLA
    preset index.
    """

    t: jax.Array
    dt: jax.Array
    ego_x: jax.Array
    ego_y: jax.Array
    ego_speed: jax.Array
    ego_length: jax.Array
    ego_width: jax.Array
    ped_x: jax.Array
    ped_y: jax.Array
    ped_vx: jax.Array
    ped_vy: jax.Array
    ped_length: jax.Array
    ped_width: jax.Array
    road_right: jax.Array
    road_left: jax.Array
    weather: jax.Array


def no_state(key, params):
    return jnp.bool_(False)


@dataclasses.dataclass(frozen=True)
class SUT:
    """A system under test (hashable: a static argument of compiled code).

    Attributes:
      name: registry name or import path.
      act: ``act(obs, state, params, key) -> (accel [m/s^2], state)``.
      init: ``init(key, params) -> state``.
      default_params: the parameter pytree with its defaults (``None``: no parameters). Not
        part of the hash: parameters are traced.
      stochastic: whether ``init``/``act`` use their key; False skips deriving per-scenario
        and per-step keys (the built-ins are deterministic).
    """

    name: str
    act: Callable[[Observation, Any, Any, jax.Array], tuple[jax.Array, Any]]
    init: Callable[[jax.Array, Any], Any] = no_state
    default_params: Any = dataclasses.field(default=None, compare=False, hash=False)
    stochastic: bool = True
