"""How many threads XLA's CPU runtime runs a compiled program's kernels on.

XLA's CPU client starts a pool of one thread per core and splits each kernel among them. The
simulator's and the controller's kernels are small (a batch of 4096 scenarios is a few
microseconds of work per kernel), and on a machine that gives the process two cores, handing
each kernel between two threads costs more than it saves: one batch of 4096 paper-space
rollouts took 8.2 ms on one thread against 12.0 ms on two, the ``reinforce/default`` update's
learning 4.3-4.8 ms against 5.5-5.8 ms, the main job's search 1.6 s against 2.1 s, and a
2,000,000-scenario sweep the same 8.0 s either way (docs/performance.md). Outcomes are the same
bits either way (tested). So on a machine that gives the process one or two cores, jaxfalsify
asks XLA for one thread, and leaves the other core to the run's figure process; on more cores it
leaves XLA's own choice.

XLA reads the thread count from the environment variable ``NPROC`` when it creates its CPU
client (on the first computation), so :func:`configure` runs when ``jaxfalsify`` is imported.
``JAXFALSIFY_XLA_THREADS=N`` chooses the count, ``auto`` (the default) as above; an ``NPROC``
already set is left as it is. Either is refused above the larger of :data:`FLOOR` threads and
:data:`PER_CORE` per core the process may run on (XLA starts every thread it is asked for:
100,000 took 19 GB of memory and the machine with it). Child processes inherit the setting.
"""

from __future__ import annotations

import os

__all__ = ["ENV", "PER_CORE", "FLOOR", "cores", "configure", "wanted", "most"]

ENV = "JAXFALSIFY_XLA_THREADS"
XLA_ENV = "NPROC"  # what XLA's CPU client reads for its thread pool's size
PER_CORE = 4  # the most threads per core asked of XLA ...
FLOOR = 256  # ... or this many, if more


def cores() -> int:
    """Cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def most() -> int:
    """The most threads XLA may be asked for: :data:`PER_CORE` per core, and never fewer than
    :data:`FLOOR` (a few MB of memory)."""
    return max(PER_CORE * cores(), FLOOR)


def _bounded(name: str, raw: str, n: int) -> int:
    if n > most():
        raise ValueError(f"{name}={raw!r}: at most {most()} threads (the larger of {FLOOR} and "
                         f"{PER_CORE} per core of the {cores()} this process may run on)")
    return n


def wanted(environ=os.environ) -> int | None:
    """The thread count to ask XLA for (None: XLA's own choice); ValueError (one line) for a
    ``JAXFALSIFY_XLA_THREADS`` that is neither ``auto`` nor a positive whole number, or is above
    :func:`most`."""
    value = environ.get(ENV, "auto").strip().lower()
    if value in ("", "auto"):
        return 1 if cores() <= 2 else None
    if not value.isdigit() or int(value) < 1:
        raise ValueError(f"{ENV}={environ[ENV]!r}: expected auto or a positive whole number of "
                         f"threads")
    return _bounded(ENV, environ[ENV], int(value))


def configure(environ=os.environ) -> int | None:
    """Set ``NPROC`` for XLA from :func:`wanted` unless it is set already; returns the count
    set (None: nothing set). Takes effect only before JAX's CPU client exists. An ``NPROC``
    already set that is a whole number above :func:`most` is refused (ValueError, one line)."""
    if XLA_ENV in environ:
        raw = environ[XLA_ENV].strip()
        if raw.isdigit() and raw.isascii():
            _bounded(XLA_ENV, environ[XLA_ENV], int(raw))
        return None
    n = wanted(environ)
    if n is not None:
        environ[XLA_ENV] = str(n)
    return n
