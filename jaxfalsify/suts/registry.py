"""Systems under test: longitudinal controllers of the ego vehicle, black boxes to the search.

A SUT is a pair of pure functions over one scenario (the simulator vmaps them):

* ``init(key, params) -> state``
* ``act(obs, state, params, key) -> (accel_command, new_state)``: called every step with an
  :class:`Observation` (its ``dt`` is the world's step); the longitudinal acceleration command
  [m/s^2] (negative = braking) acts during the next step, within the vehicle's limits.

``params`` is a pytree (a :func:`jaxfalsify.base.pytree.dataclass` of floats) passed *traced*: a
calibration change does not recompile, and a sweep can vmap over calibrations. ``key`` is a
typed PRNG key (sensor noise); the built-ins are deterministic and ignore it.

Registry (gymnax / jumanji style): ``register(SUT(...))``, ``make(name, **params) -> (sut,
params)``; a user's SUT is named by import path, ``my_pkg.my_aeb:AEB`` or
``path/to/file.py:AEB`` (a :class:`SUT`, a function returning one, or a bare ``act``).

Built-ins:

* ``carla-tm`` (default): CARLA 0.9.9's Traffic Manager autopilot (pipeline era) with its
  ground-truth collision stage, the SUT of the paper. Weather does not change it (CARLA's
  weather is visual only).
* ``sensor-aeb``: a perception-based AEB on the same autopilot whose detection degrades with
  light, glare and rain, with staged braking on time-to-collision and friction-limited
  braking on wet roads.
* ``none``: the autopilot's speed keeping (CARLA's PID) without any emergency braking.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.base.worker import import_module
from jaxfalsify.io import cache
from jaxfalsify.suts.autopilot import (
    AutopilotParams,
    CruiseParams,
    autopilot_command,
    cruise_command,
    none_act,
    pid_init,
    target_speed,
)
from jaxfalsify.suts.carla_tm import CarlaTMParams, carla_tm_act
from jaxfalsify.suts.interface import SUT, G, Observation, no_state
from jaxfalsify.suts.sensor_aeb import SensorAEBParams, sensor_aeb_act, sensor_init

# ----------------------------------------------------------------------------- registry
REGISTRY: dict[str, SUT] = {}


def register(sut: SUT) -> SUT:
    """Add a SUT to the registry under ``sut.name`` (replacing one of the same name)."""
    if not isinstance(sut, SUT):
        raise ValueError(f"register() takes a SUT (got {type(sut).__name__})")
    REGISTRY[sut.name] = sut
    return sut


register(SUT("carla-tm", carla_tm_act, pid_init, CarlaTMParams(), stochastic=False))
register(SUT("sensor-aeb", sensor_aeb_act, sensor_init, SensorAEBParams(), stochastic=False))
register(SUT("none", none_act, pid_init, AutopilotParams(), stochastic=False))


def error_line(e: BaseException) -> str:
    """``TypeName: first line of the message`` of a user's exception, for one-line errors."""
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0] if text else ''}"


def load_attr(spec: str, what: str = "SUT"):
    """``module:attr`` or ``path/file.py:attr`` -> the attribute (one-line ValueError naming
    ``what`` it was to be: a SUT, a requirement)."""
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        known = f"a registry name ({', '.join(REGISTRY)}) or " if what == "SUT" else ""
        raise ValueError(f"{what} '{spec}': expected {known}an import path module:attr")
    if mod_name.endswith(".py") and not Path(mod_name).resolve().is_file():
        raise ValueError(f"{what} '{spec}': " + (
            f"{mod_name} is a folder, not a Python file" if Path(mod_name).is_dir()
            else f"no such file {mod_name}"))
    try:
        module = import_module(mod_name, "jaxfalsify_user_sut_")
    except (Exception, SystemExit) as e:  # noqa: BLE001 - a user module can raise anything
        # on import (sys.exit and a ValueError of its own too)
        raise ValueError(f"{what} '{spec}': cannot import {mod_name} ({error_line(e)})") from None
    try:
        return getattr(module, attr)
    except AttributeError:
        raise ValueError(f"{what} '{spec}': {mod_name} has no attribute '{attr}'") from None
    except (Exception, SystemExit) as e:  # noqa: BLE001 - a module __getattr__ can raise
        raise ValueError(f"{what} '{spec}': looking up '{attr}' in {mod_name} raised "
                         f"{error_line(e)}") from None


def recorded_spec(spec: str, folder: Path | None = None) -> str:
    """The SUT name as a run records it: a file path ``path/file.py:attr`` made absolute (a
    relative one taken from ``folder``, default the working folder), so ``--resume`` and
    ``--config`` find the same file from any working folder; registry names and module import
    paths unchanged."""
    mod_name, _, attr = spec.rpartition(":")
    if spec in REGISTRY or not mod_name.endswith(".py") or Path(mod_name).is_absolute():
        return spec
    return f"{((folder or Path.cwd()) / mod_name).resolve()}:{attr}"


def folder_name(spec: str) -> str:
    """A SUT name usable in a folder name: ``file.py:AEB`` -> ``file-AEB``, ``pkg.mod:AEB``
    -> ``pkg.mod-AEB``, registry names unchanged."""
    mod, _, attr = spec.rpartition(":")
    if mod.endswith(".py"):
        mod = Path(mod).stem
    return (f"{mod}-{attr}" if mod else spec).replace("/", "_").replace("\\", "_")


def _example_observation() -> Observation:
    return Observation(*([jnp.float32(0.0)] * (len(Observation._fields) - 1)),
                       weather=jnp.int32(0))


def is_builtin(sut: SUT) -> bool:
    """Whether ``sut``'s code is jaxfalsify's own (trusted, cached by name)."""
    return all(getattr(f, "__module__", "").startswith("jaxfalsify.") for f in (sut.act, sut.init))


_TRACEABLE: set = set()  # SUTs that passed check_traceable


def check_traceable(sut: SUT, params: Any) -> None:
    """Return once ``sut``'s ``init(key, params)`` and ``act(obs, state, params, key)`` trace
    with ``params`` (its resolved parameters) and return ``(command, state)`` with a scalar
    command and the state's structure kept, vmapped over scenarios as the simulator runs it
    (abstract evaluation: nothing is computed or compiled); else a one-line ValueError naming
    the SUT. Run on every user SUT (not the
    built-ins) where a command or library call resolves its parameters, before any file is
    written; once per SUT and process."""
    if is_builtin(sut):
        return
    try:
        if sut in _TRACEABLE:
            return
    except TypeError:  # an unhashable act or init: checked every time
        pass

    def one_step(key, obs):
        state = sut.init(key, params)
        out = sut.act(obs, state, params, key)
        if not (isinstance(out, tuple) and len(out) == 2):
            raise TypeError(f"act returned {type(out).__name__}, expected (command, state)")
        cmd, new_state = out
        if jnp.shape(cmd) != ():
            raise TypeError(f"act's command has shape {jnp.shape(cmd)}, expected a scalar "
                            "(m/s^2)")
        if jax.tree.structure(new_state) != jax.tree.structure(state):
            raise TypeError("act's new state differs in structure from init's")
        for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(new_state)):
            ta, tb = jnp.result_type(a), jnp.result_type(b)
            sa, sb = jnp.shape(a), jnp.shape(b)
            if ta != tb or sa != sb:  # the rollout's scan carries the state unchanged in type
                raise TypeError(f"act changes the state from {ta}{list(sa)} to "
                                f"{tb}{list(sb)} (init's dtype and shape must be kept)")
        return cmd

    def batched(key):  # as the simulator calls it: vmapped over the scenarios
        obs = jax.tree.map(lambda x: jnp.stack([x, x]), _example_observation())
        return jax.vmap(one_step)(jax.random.split(key, 2), obs)

    try:
        jax.eval_shape(batched, jax.random.key(0))
    except Exception as e:  # noqa: BLE001 - a user's code can raise anything when traced
        hint = (" (a bare act function gets params=None; give the SUT default_params)"
                if params is None and "NoneType" in str(e) else "")
        raise ValueError(f"SUT '{sut.name}' fails on a step: {error_line(e)}{hint}") from None
    try:
        _TRACEABLE.add(sut)
    except TypeError:
        pass


def resolve(spec: str | SUT | Callable) -> SUT:
    """A :class:`SUT` from a registry name, an import path, a SUT, or a bare ``act`` function
    (stateless: ``act(obs, state, params, key)``). Raises ValueError listing the known names."""
    if isinstance(spec, SUT):
        return spec
    if isinstance(spec, str):
        if spec in REGISTRY:
            return REGISTRY[spec]
        if ":" not in spec:
            raise ValueError(f"unknown SUT '{spec}' (one of {', '.join(REGISTRY)}, or an "
                             "import path module:attr)")
        obj = load_attr(spec)
        if isinstance(obj, type) or (callable(obj) and not isinstance(obj, SUT)
                                     and getattr(obj, "__code__", None) is not None
                                     and obj.__code__.co_argcount == 0):
            try:
                obj = obj()  # a factory returning a SUT
            except Exception as e:  # noqa: BLE001 - a user's code can raise anything
                raise ValueError(f"SUT '{spec}' could not be built (called with no "
                                 f"arguments): {error_line(e)}") from None
        if isinstance(obj, SUT):
            pytree.check_defaults(obj.default_params, f"SUT '{spec}'")
            return dataclasses.replace(obj, name=spec) if obj.name != spec else obj
        builtin = next((s for s in REGISTRY.values() if s.act is obj or s.init is obj), None)
        if builtin is not None:  # a built-in's own function needs its state and parameters
            raise ValueError(f"SUT '{spec}' is the '{builtin.name}' SUT's "
                             f"{'act' if builtin.act is obj else 'init'} function, which needs "
                             f"that SUT's state and parameters: name the SUT, --sut "
                             f"{builtin.name}")
        if callable(obj):
            return SUT(spec, obj, no_state, None)
        raise ValueError(f"SUT '{spec}' is a {type(obj).__name__}, not a SUT or act function")
    if callable(spec):
        return SUT(getattr(spec, "__name__", "custom"), spec, no_state, None)
    raise ValueError(f"sut must be a name, an import path, a SUT or a function "
                     f"(got {type(spec).__name__})")


def cache_key(sut: SUT) -> str | None:
    """What identifies a SUT's code across processes, for the per-user program cache: the
    built-ins by name, a module-level SUT by its functions' qualified names and the source of
    every loaded user module (:func:`jaxfalsify.io.cache.user_code_hash`: its own file and any
    helper it imports). None (never cached) for closures or functions without a source
    file."""

    fns = (sut.act, sut.init)
    if any(getattr(f, "__closure__", True) is not None for f in fns):
        return None
    if is_builtin(sut):
        return f"builtin:{sut.name}"
    code = cache.user_code_hash(*fns)
    return None if code is None else f"{sut.name}:{code}"


def param_names(sut: SUT) -> tuple[str, ...]:
    """The names of the SUT's parameters (``--sut-param NAME=VALUE``)."""
    return tuple(pytree.param_items(sut.default_params))


def with_params(sut: SUT, params: Any = None, where: str = "sut_params") -> Any:
    """The SUT's parameters: its defaults, a full parameter pytree, or a mapping of overrides
    ``{name: number}`` applied to the defaults. One-line ValueError naming a bad name/value."""
    if params is None:
        return sut.default_params
    if not isinstance(params, Mapping):  # a full parameter pytree
        d = sut.default_params
        if dataclasses.is_dataclass(d) and not isinstance(params, type(d)):
            raise ValueError(f"{where}: SUT '{sut.name}' takes {type(d).__name__} (got "
                             f"{type(params).__name__})")
        if dataclasses.is_dataclass(params):  # its concrete scalar values, in their intervals
            values = {f: getattr(params, f) for f in pytree.field_names(params)}
            pytree.check_ranges(params, {f: x for f, v in values.items()
                                         if (x := pytree.real_number(v)) is not None},
                                f"{where}: SUT '{sut.name}'")
        return params
    if not params:
        return sut.default_params
    return pytree.with_overrides(sut.default_params, params, where, f"SUT '{sut.name}'")


def override(params: Any, values: dict) -> Any:
    """``params`` with the fields in ``values`` replaced (traced values welcome: a space's
    ``sut.NAME`` parameters, one value per scenario under ``vmap``)."""
    if dataclasses.is_dataclass(params):
        return dataclasses.replace(params, **values)
    if isinstance(params, dict):
        return {**params, **values}
    raise ValueError(f"cannot set {', '.join(values)} on SUT parameters of type "
                     f"{type(params).__name__}")


def make(spec: str | SUT | Callable = "carla-tm", **params) -> tuple[SUT, Any]:
    """``(sut, params)``: a SUT by name or import path, and its parameters with ``params``
    overriding the defaults (``make("sensor-aeb", ttc_full=0.8)``)."""
    sut = resolve(spec)
    p = with_params(sut, params)
    check_traceable(sut, p)
    return sut, p


def params_dict(params: Any) -> dict[str, float]:
    """``{name: value}`` of a flat parameter pytree (host-side; for config files and tables)."""
    if params is None:
        return {}
    if dataclasses.is_dataclass(params):
        return {f: float(getattr(params, f)) for f in pytree.field_names(params)}
    if isinstance(params, Mapping):
        return {k: float(v) for k, v in params.items()}
    return {}


def callback_error(e: BaseException) -> str | None:
    """The user's exception (``Type: message``, one line) when ``e`` is JAX's runtime error
    for a host callback (``jax.pure_callback`` / ``io_callback`` in a user's SUT) that raised;
    None for any other error."""
    if type(e).__name__ not in ("JaxRuntimeError", "XlaRuntimeError") or \
            "callback" not in str(e).lower():
        return None
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    found = next((ln for ln in reversed(lines) if ":" in ln and ln.split(":", 1)[0].isidentifier()
                  and ln.split(":", 1)[0][0].isupper()), None)
    return (found or lines[-1] if lines else type(e).__name__)[:300]


# the interface, the registry and the plug-in loader; the speed keepers and the built-ins'
# parameter sets, which a user's SUT may build on (the built-ins themselves: jaxfalsify.suts)
__all__ = ["G", "SUT", "Observation", "no_state", "REGISTRY", "register", "make", "resolve",
           "load_attr", "recorded_spec", "folder_name", "is_builtin", "check_traceable",
           "cache_key", "param_names", "with_params", "override", "params_dict",
           "callback_error", "error_line", "AutopilotParams", "CruiseParams",
           "autopilot_command", "cruise_command", "target_speed", "CarlaTMParams",
           "SensorAEBParams"]
