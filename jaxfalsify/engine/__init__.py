"""What jobs are built from: the compiled campaign (campaign), the problem a job describes
(problem), the run-folder lifecycle (lifecycle), worker pools, the sweep's pieces (sweep_*),
ground truths (truth) and run-folder reading (rundir). Imports ``core``, ``search`` and below.

Its modules load on first access (``jaxfalsify.engine.campaign`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
