"""Search strategies: a registry of ``make(shape, batch, **options) -> Strategy`` by name.

See :mod:`jaxfalsify.search.base` for the interface. ``reinforce`` is the paper's method;
the others are the baselines users of this field compare against.
"""

from __future__ import annotations

from jaxfalsify.search import anneal, cem, cmaes, grid, random_search
from jaxfalsify.search.base import Strategy

DEFAULT_BATCH = {"random": 200, "grid": 200, "cem": 200, "anneal": 200, "cmaes": 200}


def _reinforce(shape, batch=None, preset="default"):
    from jaxfalsify import reinforce
    return reinforce.make(shape, batch, preset)


STRATEGIES = {
    "random": random_search.make,
    "grid": grid.make,
    "cem": cem.make,
    "anneal": anneal.make,
    "cmaes": cmaes.make,
    "reinforce": _reinforce,
}


def default_batch(name: str, preset: str = "default") -> int:
    if name not in STRATEGIES:
        raise ValueError(f"unknown strategy '{name}' (one of {', '.join(STRATEGIES)})")
    if name == "reinforce":
        from jaxfalsify.reinforce import get_preset
        return get_preset(preset).batch
    return DEFAULT_BATCH[name]


def make(name: str, shape: tuple[int, ...], batch: int | None = None,
         preset: str = "default") -> Strategy:
    """Build a strategy by registry name; raises ValueError naming a bad name or option."""
    if name not in STRATEGIES:
        raise ValueError(f"unknown strategy '{name}' (one of {', '.join(STRATEGIES)})")
    if batch is not None and (isinstance(batch, bool) or not isinstance(batch, int)
                              or batch <= 0):
        raise ValueError(f"batch must be a positive integer (got {batch!r})")
    if name == "reinforce":
        return STRATEGIES[name](shape, batch, preset)
    return STRATEGIES[name](shape, batch or DEFAULT_BATCH[name])


__all__ = ["Strategy", "STRATEGIES", "make", "default_batch"]
