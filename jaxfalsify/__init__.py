"""jaxfalsify: JAX-accelerated, batched scenario-based falsification (pedestrian crossing vs AEB).

The simulator, SUTs and metrics are imported here; the run, sweep and compare entry points
(``jaxfalsify.runs.execute``, ``jaxfalsify.sweep.execute``, ``jaxfalsify.compare.execute``),
strategies (``jaxfalsify.search``) and host-side outputs are imported on use.
"""

from jaxfalsify import cache as _cache
from jaxfalsify.metrics import rss_safe_distance
from jaxfalsify.sim import WORLD, Outcome, Trajectory, World, evaluate, simulate
from jaxfalsify.space import Space, load_space
from jaxfalsify.sut import SUT, Observation

_cache.enable_compilation_cache()

__all__ = ["rss_safe_distance", "simulate", "evaluate", "load_space", "Space", "World", "WORLD",
           "Outcome", "Trajectory", "SUT", "Observation"]
__version__ = "0.2.0"
