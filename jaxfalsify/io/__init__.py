"""Files on disk: atomic writes (files), per-user caches of compiled programs and ground truths
(cache), run folders' locks and status (store), checkpoints. Imports only ``base``.

Its modules load on first access (``jaxfalsify.io.cache`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'cache', 'checkpoints', 'files', 'store'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
