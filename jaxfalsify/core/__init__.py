"""The simulator (sim: world, rollout, batched evaluation), the requirements a rollout is judged by
(requirements), a kinematic screen of scenarios (screen) and a NumPy reference rollout
(reference). Imports the layers below and ``suts``.

Its modules load on first access (``jaxfalsify.core.reference`` after ``import jaxfalsify``).
"""

import importlib as _importlib
from pathlib import Path as _Path

__all__ = []


def __getattr__(name: str):
    if (_Path(__file__).parent / f"{name}.py").is_file():  # a module of this folder
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
