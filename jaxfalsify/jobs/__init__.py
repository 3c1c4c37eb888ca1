"""The jobs the CLI runs, as library calls: run, sweep, compare (with its statistics, tables and
suite), estimate, and external evaluation (ask/tell, evaluators). Imports every layer below.

Its modules load on first access (``jaxfalsify.jobs.compare`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({
    'compare', 'compare_stats', 'compare_tables', 'estimate', 'evaluators', 'external', 'runs',
    'suites', 'sweep'
})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
