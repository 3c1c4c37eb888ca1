"""jaxfalsify: JAX-accelerated, batched scenario-based falsification (pedestrian crossing vs AEB)."""

from jaxfalsify.metrics import rss_safe_distance
from jaxfalsify.sim import WORLD, Outcome, Trajectory, World, evaluate, simulate
from jaxfalsify.space import Space, space
from jaxfalsify.sut import SUT, SUTS, Observation

__all__ = ["rss_safe_distance", "simulate", "evaluate", "space", "Space", "World", "WORLD",
           "Outcome", "Trajectory", "SUT", "SUTS", "Observation"]
__version__ = "0.1.0"
