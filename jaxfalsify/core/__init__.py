"""The simulator (sim: world, rollout, batched evaluation), the requirements a rollout is judged by
(requirements) and a NumPy reference rollout (reference). Imports the layers below and ``suts``.

Its modules load on first access (``jaxfalsify.core.reference`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'reference', 'requirements', 'sim'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
