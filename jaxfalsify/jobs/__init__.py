"""The jobs the CLI runs, as library calls: run, sweep, compare (with its statistics, tables and
suite), estimate, and external evaluation (ask/tell, evaluators). Imports every layer below.

Its modules load on first access (``jaxfalsify.jobs.compare`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
