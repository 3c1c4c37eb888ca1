"""Files on disk: atomic writes (files), per-user caches of compiled programs and ground truths
(cache), run folders' locks and status (store), checkpoints. Imports only ``base``.

Its modules load on first access (``jaxfalsify.io.cache`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
