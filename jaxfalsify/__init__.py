"""jaxfalsify: JAX-accelerated, batched scenario-based falsification (pedestrian crossing vs AEB).

The simulator, SUTs and metrics are imported here; the run, sweep and compare entry points
(``jaxfalsify.jobs.runs.execute``, ``jaxfalsify.jobs.sweep.execute``,
``jaxfalsify.jobs.compare.execute``),
strategies (``jaxfalsify.search``) and host-side outputs are imported on first use
(``jaxfalsify.search.make(...)`` works after a bare ``import jaxfalsify``: PEP 562).
"""

import importlib as _importlib  # noqa: E402
import sys as _sys  # noqa: E402

from jaxfalsify.base.progress import IMPORTED_AT  # noqa: F401 - first: start-up accounting


def _command_line() -> bool:
    """This import is the ``jaxfalsify`` console script's or ``python -m jaxfalsify``'s."""
    import os

    orig = getattr(_sys, "orig_argv", [])
    return os.path.basename(_sys.argv[0] if _sys.argv else "") == "jaxfalsify" or \
        orig[1:3] == ["-m", "jaxfalsify"]


if _command_line() and "--no-cache" in _sys.argv[1:]:  # before the cache is set up (it
    import os as _os  # would create its folder)

    _os.environ["JAXFALSIFY_NO_CACHE"] = "1"

try:  # importing JAX takes most of a second: a Ctrl-C then ends the command in one line
    from jaxfalsify.base import threads as _threads

    _threads.configure()  # XLA's CPU thread count, before JAX's CPU client exists
    from jaxfalsify.core.sim import WORLD, Outcome, Trajectory, World, evaluate, simulate
    from jaxfalsify.io import cache as _cache
    from jaxfalsify.scenario.metrics import rss_safe_distance
    from jaxfalsify.scenario.space import Space, load_space
    from jaxfalsify.suts.registry import SUT, Observation

    _cache.enable_compilation_cache()
except ValueError as _e:  # a JAX setting from the environment that JAX refuses at import
    if not _command_line() or ("JAX flag" not in str(_e) and "for environment" not in str(_e)
                               and "JAXFALSIFY_XLA_THREADS" not in str(_e)
                               and not str(_e).startswith("NPROC=")):
        raise
    print(f"jaxfalsify: error: {str(_e).splitlines()[0]} (set in the environment: fix or unset "
          f"it)", file=_sys.stderr)
    raise SystemExit(2) from None
except KeyboardInterrupt:
    if not _command_line():  # a library user's interrupt stays theirs
        raise
    print("jaxfalsify: interrupted while starting; nothing was written", file=_sys.stderr)
    _sys.stderr.flush()
    import os as _os

    _os._exit(130)

if _command_line():  # refused before any command starts (library calls refuse in
    try:  # runs.execute and wherever a program is built: jaxfalsify.io.cache.check_settings)
        _cache.check_settings()
    except ValueError as _e:
        print(f"jaxfalsify: error: {_e}", file=_sys.stderr)
        raise SystemExit(2) from None

__all__ = ["rss_safe_distance", "simulate", "evaluate", "load_space", "Space", "World", "WORLD",
           "Outcome", "Trajectory", "SUT", "Observation"]
__version__ = "0.4.0"

# the package's layers, lowest first (each imports only from those before it), and the CLI
_SUBMODULES = frozenset({"base", "io", "scenario", "suts", "core", "search", "engine", "outputs",
                         "jobs", "cli"})
# names loaded with their module
_LAZY = {"Falsifier": "jobs.external", "RunConfig": "engine.problem"}


def __getattr__(name: str):
    """Layers not imported at start-up (``jobs``, ``search``, ``outputs``, ...) load on first
    access, so ``import jaxfalsify`` stays cheap."""
    if name in _SUBMODULES:
        return _importlib.import_module(f"jaxfalsify.{name}")
    if name in _LAZY:
        return getattr(_importlib.import_module(f"jaxfalsify.{_LAZY[name]}"), name)
    raise AttributeError(f"module 'jaxfalsify' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | _SUBMODULES | set(_LAZY))
