"""Requirements: what counts as a failure of the SUT.

A requirement maps one scenario's :class:`~jaxfalsify.core.sim.Outcome` (scalars; vmapped over a
batch) and its parameters (a pytree, traced) to an STL-style robustness: >= 0 satisfied,
< 0 violated, its magnitude how far from the boundary. The outcome holds the rollout's
reductions over the episode (smallest box gap, time-to-collision, RSS margin, collision), so a
requirement of the form *always (signal >= threshold)* is exact: its robustness is
``min over the episode of (signal - threshold)``.

Built-ins (:data:`REGISTRY`):

* ``clash`` — the paper's requirement, STL *always not clash* (Eq. 1), clash = distance < ε:
  ``min_distance - epsilon``, ε = 1 m by default. The distance is the gap between the two
  bounding boxes (0 on contact). The authors' code measured the distance between the actors'
  origins (centre to centre); with a 4.6 m car and a 0.4 m walker the boxes already overlap
  while the centres are 2.5 m apart, so a centre distance below 1 m is never reached before a
  collision, and the box gap is what *clash* measures here.
* ``collision`` — *never touch*: the smallest box gap, and -1 on contact (the simulator does
  not measure how deep boxes overlap).
* ``ttc`` — *always TTC >= min_ttc* (default 1.5 s): ``min(min_ttc, 1000) - min_ttc``, the
  constant-velocity time-to-collision of :func:`jaxfalsify.scenario.metrics.time_to_collision`.
* ``rss`` — RSS's longitudinal rule while the pedestrian is ahead of the ego's front bumper:
  *always centre distance >= RSS safe distance + margin* (paper Eq. 4; margin 0 m by default):
  ``min_rss_margin - margin``. Its violations are the paper's high-risk steps.

A rollout that went non-finite counts as a violation (its robustness is -inf).

A user's requirement is named by import path (``module:attr`` or ``path/file.py:attr``, as a
SUT is) and is either a :class:`Requirement` or a function ``robustness(outcome, params) ->
scalar`` (then without parameters).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree
from jaxfalsify.core.sim import Outcome
from jaxfalsify.io import cache
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "REGISTRY", "DEFAULT", "resolve", "param_names", "with_params", "cache_key", "robustness",
    "check", "Requirement", "ClashParams", "TTCParams", "RSSParams", "register"
]

CAP = 1000.0  # robustness of a requirement whose signal never came near (inf) is capped here


@dataclasses.dataclass(frozen=True)
class Requirement:
    """A requirement (hashable: a static argument of compiled code).

    Attributes:
      name: registry name or import path.
      robustness: ``robustness(outcome, params) -> scalar`` for one scenario (float32; < 0:
        violated).
      default_params: its parameter pytree with the defaults (None: no parameters).
      doc: one line for listings.
    """

    name: str
    robustness: Callable[[Outcome, Any], jax.Array]
    default_params: Any = dataclasses.field(default=None, compare=False, hash=False)
    doc: str = dataclasses.field(default="", compare=False)


@pytree.dataclass
class ClashParams:
    epsilon: float = 1.0  # m, the paper's ε
    RANGES = {"epsilon": "[0, inf)"}


@pytree.dataclass
class TTCParams:
    min_ttc: float = 1.5  # s
    RANGES = {"min_ttc": "[0, 1000]"}


@pytree.dataclass
class RSSParams:
    margin: float = 0.0  # m, added to RSS's safe distance
    RANGES = {"margin": "[0, inf)"}


def _clash(o: Outcome, p: ClashParams) -> jax.Array:
    return o.min_distance - p.epsilon


def _collision(o: Outcome, p) -> jax.Array:
    return jnp.where(o.collision, -1.0, o.min_distance)


def _ttc(o: Outcome, p: TTCParams) -> jax.Array:
    return jnp.minimum(o.min_ttc, CAP) - p.min_ttc


def _rss(o: Outcome, p: RSSParams) -> jax.Array:
    return jnp.minimum(o.min_rss_margin, CAP) - p.margin


REGISTRY: dict[str, Requirement] = {}


def register(req: Requirement) -> Requirement:
    """Add ``req`` to :data:`REGISTRY` under its name (a user's requirement may then be named
    like a built-in one)."""
    if not isinstance(req, Requirement):
        raise ValueError(f"register() takes a Requirement (got {type(req).__name__})")
    REGISTRY[req.name] = req
    return req


register(Requirement("clash", _clash, ClashParams(),
                     "the paper's always-not-clash: box gap >= epsilon (1 m)"))
register(Requirement("collision", _collision, None, "never touch: box gap > 0"))
register(Requirement("ttc", _ttc, TTCParams(), "always time-to-collision >= min_ttc (1.5 s)"))
register(Requirement("rss", _rss, RSSParams(),
                     "always centre distance >= RSS safe distance + margin (0 m) while the "
                     "pedestrian is ahead"))
DEFAULT = "collision"  # what run, sweep, compare and estimate count unless told otherwise


def resolve(spec: str | Requirement | Callable) -> Requirement:
    """A requirement by registry name, import path, object or function (one-line ValueError)."""
    if isinstance(spec, Requirement):
        pytree.check_defaults(spec.default_params, f"requirement '{spec.name}'")
        return spec
    if callable(spec):
        return Requirement(getattr(spec, "__name__", "requirement"), spec)
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"requirement must be a name or import path (got {spec!r:.60})")
    if spec in REGISTRY:
        return REGISTRY[spec]
    if ":" not in spec:
        raise ValueError(f"unknown requirement '{spec}' (known: {', '.join(REGISTRY)}; or an "
                         "import path module:attr)")
    obj = sut_lib.load_attr(spec, "requirement")
    if isinstance(obj, Requirement):
        pytree.check_defaults(obj.default_params, f"requirement '{spec}'")
        return dataclasses.replace(obj, name=spec)
    if callable(obj):
        return Requirement(spec, obj)
    raise ValueError(f"requirement '{spec}' is a {type(obj).__name__}, not a Requirement or a "
                     "function robustness(outcome, params)")


def param_names(req: Requirement) -> tuple[str, ...]:
    """The names of the requirement's parameters (``--requirement-param NAME=VALUE``)."""
    return tuple(pytree.param_items(req.default_params))


def with_params(req: Requirement, given: Mapping[str, float] | None = None,
                where: str = "requirement_params") -> Any:
    """The requirement's parameters: its defaults with ``given`` ``{name: number}`` applied
    (one-line ValueError naming a bad name or value)."""
    if not given:
        return req.default_params
    if not isinstance(given, Mapping):  # a full parameter pytree
        return given
    return pytree.with_overrides(req.default_params, given, where,
                                 f"requirement '{req.name}'")


def cache_key(req: Requirement) -> str | None:
    """What identifies a requirement in a cached program: a built-in's name, a user's by its
    source (None: no source file, not cacheable)."""
    if REGISTRY.get(req.name) is req:
        return req.name
    code = cache.user_code_hash(req.robustness)
    return None if code is None else f"{req.name}:{code}"


def robustness(req: Requirement, outcome: Outcome, params: Any) -> jax.Array:
    """``req``'s robustness of a batch of outcomes (any leading shape), float32; -inf where
    the rollout went non-finite or the requirement returned NaN."""
    nd = jnp.ndim(outcome.reward)
    fn = lambda o: jnp.asarray(req.robustness(o, params), jnp.float32)  # noqa: E731
    for _ in range(nd):
        fn = jax.vmap(fn)
    r = fn(outcome)
    return jnp.where(outcome.nonfinite | jnp.isnan(r), -jnp.inf, r)


def check(req: Requirement, params: Any) -> None:
    """Trace the requirement on an example outcome, alone and vmapped over a batch as the
    jobs call it (:func:`robustness`), before anything runs: a function that fails either
    way (a ``jax.pure_callback`` without a ``vmap_method`` fails only batched) or returns a
    non-scalar is named in one line."""
    def example(shape):
        return Outcome(**{f.name: jax.ShapeDtypeStruct(
            shape, jnp.bool_ if f.name in ("collision", "nonfinite") else
            jnp.int32 if f.name in ("high_risk_steps", "steps") else jnp.float32)
            for f in dataclasses.fields(Outcome)})

    try:
        out = jax.eval_shape(lambda o: req.robustness(o, params), example(()))
    except Exception as e:  # noqa: BLE001 - a user's function can raise anything
        raise ValueError(f"requirement '{req.name}' fails on an example outcome: "
                         f"{sut_lib.error_line(e)[:200]}") from None
    shape = getattr(out, "shape", None)
    if shape != ():
        raise ValueError(f"requirement '{req.name}' must return one number per scenario (got "
                         f"{'shape ' + str(shape) if shape is not None else type(out).__name__})")
    try:
        jax.eval_shape(lambda o: robustness(req, o, params), example((2,)))
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"requirement '{req.name}' fails on a batch of outcomes (vmapped): "
                         f"{sut_lib.error_line(e)[:200]}") from None
