"""Host-side outputs of a run: analysis (clusters, typical scenarios), figures, report, rerun
replay and OpenSCENARIO export. Imports ``engine`` and below.

Its modules load on first access (``jaxfalsify.outputs.analysis`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
