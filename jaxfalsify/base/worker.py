"""The worker process of :class:`jaxfalsify.engine.pools.Pool`, and the evaluator's loading and
calling convention. Standard library and NumPy only: a worker is started as this file
(``python worker.py FD``), so it imports neither JAX nor the user's script, only the
evaluator's own module, and a restarted worker is ready in a fraction of a second."""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import os
import signal
import sys
import time
import traceback
from pathlib import Path
from typing import Callable

import numpy as np

__all__ = [
    "SIGNALS", "EvaluatorError", "import_module", "load", "call", "trajectory_arrays",
    "dask_task", "TRAJECTORY", "first_non_flag", "shown"
]

TRAJECTORY = ("t", "distance", "ego_x", "ego_y", "ped_x", "ped_y", "ego_speed")  # what an
# evaluator's trajectory may hold, (n, T) each: time [s], the distance between the boxes [m],
# positions [m] and the ego's speed [m/s] per step (NaN after a scenario's end)
SIGNALS = ("reward", "min_distance", "final_distance", "min_ttc")  # what a result may add to
# the robustness, (B,) each: the reward the search ranks failures by (default: -robustness),
# distances for the tables [m], the minimum time-to-collision [s] (tells near misses apart)

OUTPUTS = ("robustness", "collision", *SIGNALS)  # what an evaluator may return


class EvaluatorError(ValueError):
    """An evaluator that cannot be loaded or used (one line)."""


def import_module(mod_name: str, prefix: str):
    """A user's module: ``path/file.py`` (loaded once per path, as ``<prefix><hash of the
    path>``) or an importable name (the working folder on the path, as ``python -m`` has it).
    Raises what the import raises."""
    if mod_name.endswith(".py"):
        path = Path(mod_name).resolve()
        name = prefix + hashlib.sha256(str(path).encode()).hexdigest()[:12]
        module = sys.modules.get(name)
        if module is None:
            loader = importlib.util.spec_from_file_location(name, path)
            module = importlib.util.module_from_spec(loader)
            sys.modules[name] = module
            try:
                loader.loader.exec_module(module)
            except BaseException:
                del sys.modules[name]
                raise
        return module
    if "" not in sys.path and str(Path.cwd()) not in sys.path:
        sys.path.insert(0, str(Path.cwd()))
    return importlib.import_module(mod_name)


def load(spec: str) -> Callable:
    """The evaluator ``module:attr`` or ``path/file.py:attr`` (one-line EvaluatorError:
    no such module, file or attribute, not callable, not taking one argument)."""
    mod_name, _, attr = spec.rpartition(":")
    if not mod_name or not attr:
        raise EvaluatorError(f"evaluator '{spec}': expected an import path module:attr")
    try:
        if mod_name.endswith(".py") and not Path(mod_name).resolve().is_file():
            raise EvaluatorError(f"evaluator '{spec}': " + (
                f"{mod_name} is a folder, not a Python file" if Path(mod_name).is_dir()
                else f"no such file {mod_name}"))
        module = import_module(mod_name, "jaxfalsify_user_evaluator_")
    except EvaluatorError:
        raise
    except Exception as e:  # noqa: BLE001 - the user's module: any error, in one line
        raise EvaluatorError(f"evaluator '{spec}': importing {mod_name} failed: "
                             f"{type(e).__name__}: {e}") from None
    fn = getattr(module, attr, None)
    if fn is None:
        raise EvaluatorError(f"evaluator '{spec}': {mod_name} has no attribute '{attr}'")
    if not callable(fn):
        raise EvaluatorError(f"evaluator '{spec}': {attr} is not callable")
    try:
        inspect.signature(fn).bind({})
    except TypeError:
        raise EvaluatorError(f"evaluator '{spec}': {attr} must take one argument (a dict of "
                             "parameter arrays)") from None
    except ValueError:  # no signature to read (a builtin): it is called as it is
        pass
    return fn


def call(fn: Callable, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Call an evaluator on one batch and check what it returned: ``{output: (n,)}`` with
    ``robustness`` float64, ``collision`` bool where given, and a returned ``trajectory``
    ``{name: (n, T)}`` as ``trajectory/<name>`` entries (ValueError, one line, otherwise)."""
    n = len(next(iter(values.values())))
    out = fn({k: np.array(v, np.float64) for k, v in values.items()})
    if not isinstance(out, dict):
        out = {"robustness": out}
    unknown = sorted(set(out) - set(OUTPUTS) - {"trajectory"})
    if unknown or "robustness" not in out:
        raise ValueError(f"returned {'key ' + repr(unknown[0]) if unknown else 'no robustness'}"
                         f" (a robustness array, or a dict of {', '.join(OUTPUTS)}, "
                         "trajectory)")
    res = {}
    traj = out.pop("trajectory", None)
    if traj is not None:
        res.update(trajectory_arrays(traj, n))
    for k, v in out.items():
        if v is None:
            raise ValueError(f"returned {k} None (a missing return?)")
        try:
            a = np.asarray(v, object if k == "collision" else np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"returned {k} that is not {n} numbers") from None
        if a.ndim == 0:  # never taken as one scenario's: the batch's shape is (n,)
            raise ValueError(f"returned one {k} value (a scalar) for {n} scenario"
                             f"{'s' if n != 1 else ''}: return an array of shape (n,)")
        a = a.reshape(-1)
        if a.shape != (n,):
            raise ValueError(f"returned {k} of {a.size} values for {n} scenarios")
        if k == "collision":
            bad = first_non_flag(a)
            if bad is not None:
                raise ValueError(f"returned collision {shown(a[bad])} for scenario {bad} "
                                 "(true or false, or 1 or 0)")
            a = a.astype(float).astype(bool)
        res[k] = a
    return res


def first_non_flag(a: np.ndarray) -> int | None:
    """The first position of ``a (n,)`` holding neither a boolean nor the number 0 or 1 (a
    string, NaN, 0.5: refused rather than read as true), or None."""
    if a.dtype == bool:
        return None
    items = [v.item() if np.ndim(v) == 0 and hasattr(v, "item") else v  # JAX/NumPy scalars
             for v in a.tolist()]
    ok = [isinstance(v, (bool, int, float)) and v in (0, 1) for v in items]
    return None if all(ok) else ok.index(False)


def shown(v) -> str:
    """A value as a one-line message shows it: strings quoted, numbers plain."""
    return repr(str(v)) if isinstance(v, str) else str(v)


def trajectory_arrays(traj, n: int) -> dict[str, np.ndarray]:
    """An evaluator's ``trajectory`` ``{name: (n, T)}`` (names from :data:`TRAJECTORY`, one
    ``T`` for all; NaN after a scenario's end) as ``{"trajectory/<name>": (n, T) float64}``
    (ValueError, one line, otherwise)."""
    if not isinstance(traj, dict) or not traj:
        raise ValueError(f"returned a trajectory that is not a dict of {', '.join(TRAJECTORY)}")
    bad = sorted(set(traj) - set(TRAJECTORY))
    if bad:
        raise ValueError(f"returned trajectory {bad[0]!r} (one of {', '.join(TRAJECTORY)})")
    res, steps = {}, None
    for k, v in traj.items():
        try:
            a = np.asarray(v, np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"returned trajectory {k} that is not numbers") from None
        if a.ndim != 2 or a.shape[0] != n or (steps is not None and a.shape[1] != steps):
            raise ValueError(f"returned trajectory {k} of shape {a.shape}: expected (n={n}, "
                             f"T){'' if steps is None else f' with T = {steps}'}")
        steps = a.shape[1]
        res[f"trajectory/{k}"] = a
    return res


_LOADED: dict[str, Callable] = {}


def dask_task(spec: str, values: dict[str, np.ndarray]):
    """What a Dask worker runs: the evaluator (loaded once per worker process) on one chunk:
    ``("ok", outputs)``, ``("error", reason)`` when it raised, ``("load", message)`` when it
    cannot be loaded there."""
    fn = _LOADED.get(spec)
    if fn is None:
        try:
            fn = _LOADED[spec] = load(spec)
        except EvaluatorError as e:
            return "load", f"{e} (on a Dask worker)"
    try:
        return "ok", call(fn, values)
    except Exception as e:  # noqa: BLE001 - the user's evaluator: recorded per scenario
        return "error", f"{type(e).__name__}: {e}"[:300]


def _watch_parent(parent: int) -> None:
    """End this worker when the process that started it is gone (killed, even with
    SIGKILL): a hung evaluation does not outlive the run."""
    while True:
        time.sleep(1.0)
        if os.getppid() != parent:
            os._exit(1)


def serve(fd: int) -> None:
    """A worker process (this file run by the interpreter, so a user's script is never
    imported again, as ``multiprocessing``'s spawn would): read the evaluator's spec, the
    parent's ``sys.path`` and folder from the connection on ``fd``, load it, then evaluate
    the chunks sent until None."""
    from multiprocessing.connection import Connection

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent stops us (its own group)
    conn = Connection(fd)
    spec, path, cwd = conn.recv()
    sys.path[:] = path
    os.chdir(cwd)
    try:
        fn = load(spec)
    except Exception as e:  # noqa: BLE001
        conn.send(("load", str(e)))
        return
    conn.send(("ready", None))
    while True:
        try:
            job = conn.recv()
        except EOFError:
            return
        if job is None:
            return
        tag, values = job
        try:
            reply = ("ok", call(fn, values))
        except Exception as e:  # noqa: BLE001 - the user's evaluator: recorded per scenario
            tb = traceback.extract_tb(e.__traceback__)
            where = f" ({Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
            reply = ("error", f"{type(e).__name__}: {e}"[:300] + where)
        try:
            conn.send((tag, reply))
        except OSError:  # the parent is gone
            return


if __name__ == "__main__":
    import threading

    threading.Thread(target=_watch_parent, args=(int(sys.argv[2]),), daemon=True).start()
    serve(int(sys.argv[1]))
