"""Host-side outputs of a run: analysis (clusters, typical scenarios), figures, report, rerun
replay and OpenSCENARIO export. Imports ``engine`` and below.

Its modules load on first access (``jaxfalsify.outputs.analysis`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({'analysis', 'export', 'figures', 'replay', 'report'})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
