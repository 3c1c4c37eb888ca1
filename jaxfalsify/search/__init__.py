"""Search strategies: a registry of named entries, ``make(name, shape, batch, **options)``.

An entry is a strategy class with its default batch and fixed options (static configuration
and hyperparameter defaults), so presets are plain entries: ``reinforce/paper`` (the original
code) and ``reinforce/default`` (ours; ``reinforce`` names it too). See
:mod:`jaxfalsify.search.base` for the interface.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np

from jaxfalsify.base import pytree
from jaxfalsify.search.anneal import Anneal
from jaxfalsify.search.base import SIGNALS, Strategy, resolve_signal
from jaxfalsify.search.batched import DEFAULT_EVALUATIONS, BatchedReinforce
from jaxfalsify.search.cem import CEM
from jaxfalsify.search.cmaes import CMAES
from jaxfalsify.search.grid import Grid
from jaxfalsify.search.random_search import RandomSearch
from jaxfalsify.search.reinforce import Reinforce
from jaxfalsify.search.reinforce_ar import AutoregressiveReinforce

PAPER_BUDGET = 4000  # the paper's evaluations (episodes)


@dataclasses.dataclass(frozen=True)
class Entry:
    cls: type
    batch: int  # default scenarios per ask on CPUs
    options: tuple[tuple[str, Any], ...] = ()  # fixed static config / params of the entry
    doc: str = ""
    evaluations: int = PAPER_BUDGET  # default budget of a run
    batch_accelerator: int | None = None  # default batch on GPUs / TPUs (None: ``batch``)


REGISTRY: dict[str, Entry] = {}
ALIASES: dict[str, str] = {"reinforce": "reinforce/default"}


def register(name: str, cls: type, *, batch: int, doc: str = "",
             evaluations: int = PAPER_BUDGET, batch_accelerator: int | None = None,
             **options) -> None:
    """Add a registry entry ``name``: ``cls`` with a default batch (``batch_accelerator`` on
    a GPU or TPU), a default budget and option defaults."""
    if not (isinstance(cls, type) and issubclass(cls, Strategy)):
        raise ValueError(f"register('{name}'): {cls!r} is not a Strategy class")
    _split(cls, options, where=f"register('{name}')")
    REGISTRY[name] = Entry(cls, batch, tuple(options.items()), doc, evaluations,
                           batch_accelerator)


def canonical(name: str) -> str:
    """The registry name (aliases resolved); ValueError listing the known names."""
    name = ALIASES.get(name, name)
    if name not in REGISTRY:
        raise ValueError(f"unknown strategy '{name}' (one of {', '.join(names())})")
    return name


def names() -> list[str]:
    return list(REGISTRY) + list(ALIASES)


def _static_fields(cls) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls) if f.name not in ("shape", "batch"))


def _split(cls, options: dict, where: str) -> tuple[dict, dict]:
    static, params = {}, {}
    known_p = pytree.field_names(cls.Params)
    known_s = _static_fields(cls)
    for k, v in options.items():
        if k in ("shape", "batch"):
            raise ValueError(f"{where}: '{k}' is not a strategy option (" + (
                "scenarios per update: --batch, or make's batch argument)" if k == "batch"
                else "it comes from the space)"))
        if k in known_p:  # a traced number: as a float option
            params[k] = _typed(v, 0.0, f"{where}: {k}={v!r}")
        elif k in known_s and k in cls.FUNCTION_OPTIONS:  # a name or a function
            try:
                cls.FUNCTION_OPTIONS[k](v)
            except ValueError as e:
                raise ValueError(f"{where}: {e}") from None
            static[k] = v
        elif k in known_s:
            static[k] = _typed(v, _default(cls, k), f"{where}: {k}={v!r}")
        else:
            raise ValueError(f"{where}: no option '{k}' (known: "
                             f"{', '.join(known_s + known_p) or 'none'})")
    pytree.check_ranges(cls.Params, params, where)
    pytree.check_ranges(cls, {k: options[k] for k in static}, where)  # sizes, e.g. hidden
    return static, params


def _default(cls, name: str):
    return next(f.default for f in dataclasses.fields(cls) if f.name == name)


def _typed(value, default, what: str):
    """``value`` as the type of the option's ``default`` (bool: true/false, 1/0; int: a whole
    number; str); one-line ValueError ``what ...`` otherwise."""
    if isinstance(default, bool):
        if isinstance(value, str) and value.strip().lower() in ("true", "false"):
            return value.strip().lower() == "true"
        if not isinstance(value, str) and np.ndim(value) == 0 and \
                np.asarray(value).dtype.kind in "biu" and value in (0, 1):  # Python or NumPy
            return bool(value)
        raise ValueError(f"{what} is not a boolean (true or false)")
    if isinstance(default, int):
        if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            return int(value)  # exact, however large
        x = pytree.real_number(value)  # Python, NumPy or 0-d JAX numbers
        if x is None or not x.is_integer():
            raise ValueError(f"{what} is not a whole number")
        return int(x)
    if isinstance(default, float):
        x = pytree.real_number(value)
        if x is None or not math.isfinite(x):
            raise ValueError(f"{what} is not a finite number")
        if abs(x) > pytree.FLOAT32_MAX:
            raise ValueError(f"{what} is beyond float32's range (the search computes in "
                             "float32)")
        return float(x)
    if isinstance(default, str) and not isinstance(value, str):
        raise ValueError(f"{what} is not a string")
    return value


register("reinforce/default", BatchedReinforce, batch=4096, batch_accelerator=65536,
         evaluations=DEFAULT_EVALUATIONS,
         doc="the Flax LSTM controller + REINFORCE (optax Adam) on thousands of scenarios per "
         "update: a mixture of discretised logistics over the value ranks (cost independent of "
         "the number of values), rank-based advantages of the STL-robustness-shaped signal, a "
         "uniform floor, four learners sharing the batch (independent until novelty_until, then "
         "learning together), collisions already found count less (keeps looking for others)")
register("reinforce/screened", AutoregressiveReinforce, batch=32, learners=1, queue=32,
         resample=8, surrogate=128, anchored=True, advantage="rank", signal="shaped", lr=0.02,
         lr_found=0.03, sigma_min=0.001, repeat_found=0.8, anchor_decay=0.9,
         anchor_decay_found=0.9, global_share_found=0.0, zoom=0.3, kappa=1.0, edge_mass=0.2,
         prior_mean=-0.5, entropy_found=0.1, entropy_until=2000.0, kernel="auto",
         ttc_weight=0.05,
         doc="the autoregressive LSTM controller + REINFORCE (ours): draws around the best "
         "scenarios found so far (a learnt local move, multi-scale, partly stopping at the "
         "bounds) and afresh, a GP (its kernel and length scales by marginal likelihood) picking "
         "which draws are asked until the first collision, no repeats until a collision, rank "
         "baseline of the STL-robustness-shaped signal (near misses told apart by their minimum "
         "time-to-collision until the first collision), 32 per update; after the first "
         "collision it explores among the failures (an entropy bonus fading out over 2000 "
         "evaluations), then converges")
register("reinforce/factorised", Reinforce, batch=50, chains=0, advantage="normalised",
         signal="shaped", entropy=0.1,
         doc="the paper's factorised LSTM controller + REINFORCE, 50 per update, normalised "
         "advantages of the shaped signal, entropy bonus 0.1")
register("reinforce/paper", Reinforce, batch=25, chains=1, advantage="reward", lr=0.01,
         alpha=1e-4, entropy=0.0, eps_start=1.0, eps_decay=0.995, eps_every=4.0,
         eps_floor=0.01, eps_off_after=2000.0, doc="the LSTM controller + REINFORCE as the "
         "original code")
register("random", RandomSearch, batch=200, doc="uniform random (Crude Monte Carlo)")
register("grid", Grid, batch=200, doc="every scenario once, in a seeded random order")
register("cem", CEM, batch=200, doc="cross-entropy method, per-parameter categoricals")
register("anneal", Anneal, batch=200, doc="simulated annealing, one chain per batch slot")
register("cmaes", CMAES, batch=200, doc="CMA-ES (evosax) on the index box")


def options(name: str) -> dict[str, Any]:
    """Every option of an entry with its value: static configuration and hyperparameters."""
    e = REGISTRY[canonical(name)]
    fixed = dict(e.options)
    out = {f.name: fixed.get(f.name, f.default) for f in dataclasses.fields(e.cls)
           if f.name not in ("shape", "batch")}
    defaults = e.cls.Params()
    out.update({k: fixed.get(k, getattr(defaults, k)) for k in pytree.field_names(defaults)})
    return out


def check_options(name: str, options: Mapping[str, Any], where: str | None = None) -> None:
    """One-line ValueError (prefixed by ``where``, else the strategy's name) when ``options``
    name an unknown option or a value of the wrong type or outside its range, without a
    space (:func:`make` checks the same and builds)."""
    e = REGISTRY[canonical(name)]
    _split(e.cls, {**dict(e.options), **dict(options)},
           where=where or f"strategy '{canonical(name)}'")


def default_batch(name: str) -> int:
    """Scenarios per update when none is given: the entry's ``batch_accelerator`` when JAX's
    default backend is a GPU or TPU, its ``batch`` otherwise."""
    e = REGISTRY[canonical(name)]
    if e.batch_accelerator is not None:
        import jax

        # JAX limited to CPUs: known without starting the backend, which a multi-process
        # comparison must leave to jax.distributed.initialize
        if (jax.config.jax_platforms or "").strip().lower() != "cpu" \
                and jax.default_backend() != "cpu":
            return e.batch_accelerator
    return e.batch


def default_evaluations(name: str) -> int:
    """A run's budget when none is given: the entry's (the paper's 4000 unless it says)."""
    return REGISTRY[canonical(name)].evaluations


def make(name: str, shape: tuple[int, ...], batch: int | None = None, /,
         **overrides) -> tuple[Strategy, Any]:
    """``(strategy, params)`` for a registry entry; ``overrides`` set static options or
    hyperparameters by name (``make("cem", shape, elite_frac=0.2)``). ValueError (one line)
    naming a bad name, option or value (``shape`` and ``batch`` are not options: an override
    of that name is refused like any unknown one)."""
    e = REGISTRY[canonical(name)]
    if batch is not None and (isinstance(batch, bool) or not isinstance(batch, int)
                              or batch <= 0):
        raise ValueError(f"batch must be a positive integer (got {batch!r})")
    try:
        dims = tuple(shape)
    except TypeError:
        dims = None
    if not dims or not all(isinstance(n, (int, np.integer)) and not isinstance(n, bool)
                           and n >= 1 for n in dims):
        raise ValueError(f"shape must be the values per parameter, positive integers, e.g. "
                         f"space.shape (got {shape!r})")
    static, params = _split(e.cls, {**dict(e.options), **overrides},
                            where=f"strategy '{canonical(name)}'")
    if batch is None and getattr(e.cls, "BATCH_AT_MOST_SIZE", False):
        batch = min(e.batch, math.prod(int(n) for n in dims))  # grid on a small space
    strat = e.cls(shape=tuple(int(n) for n in dims), batch=batch or default_batch(name),
                  **static)
    return strat, pytree.replace(strat.default_params(), **params)


__all__ = ["Strategy", "SIGNALS", "resolve_signal", "REGISTRY", "register", "make",
           "canonical", "options", "check_options", "default_batch", "default_evaluations",
           "names"]
