"""What jobs are built from: the compiled campaign (campaign), the problem a job describes
(problem), the run-folder lifecycle (lifecycle), worker pools, the sweep's pieces (sweep_*),
ground truths (truth) and run-folder reading (rundir). Imports ``core``, ``search`` and below.

Its modules load on first access (``jaxfalsify.engine.campaign`` after ``import jaxfalsify``).
"""

import importlib as _importlib

__all__ = []

_MODULES = frozenset({
    'campaign', 'lifecycle', 'pools', 'problem', 'rundir', 'sweep_chunks', 'sweep_config',
    'sweep_merge', 'sweep_totals', 'truth'
})


def __getattr__(name: str):
    if name in _MODULES:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
