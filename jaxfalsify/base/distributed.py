"""Multi-process runs on JAX's own distributed runtime (``jax.distributed``).

Every process evaluates its own contiguous share of the work on its local devices and writes
its own result part; processes meet at the runtime's named barriers (:func:`barrier`) and
process 0 writes the merged summary (and removes the parts once every process has read them).

The coordinator address, process count and process id come from flags or from the usual
environment variables ``JAX_COORDINATOR_ADDRESS``, ``JAX_NUM_PROCESSES``, ``JAX_PROCESS_ID``.
"""

from __future__ import annotations

import math
import os
import sys
import time

import jax

__all__ = ["TIMEOUT_S", "initialize", "barrier", "agree", "leave", "share"]

TIMEOUT_S = 120  # how long a process waits for the coordinator (and process 0 for its peers)


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None, timeout: int = TIMEOUT_S,
               say=None) -> tuple[int, int]:
    """Start ``jax.distributed``; returns ``(process_id, num_processes)``.

    ``timeout``: seconds to wait for the coordinator to answer (processes 1..n-1) and for the
    runtime to start. ``say(text)``: told once when a process starts waiting for an
    unreachable coordinator. Raises ValueError (one line) naming what is missing or invalid,
    or the coordinator that did not answer within ``timeout``.
    """
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0:
        raise ValueError(f"coordinator timeout {timeout!r}: expected a number of seconds > 0")
    coordinator = coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS")
    if num_processes is None and "JAX_NUM_PROCESSES" in os.environ:
        num_processes = _env_int("JAX_NUM_PROCESSES")
    if process_id is None and "JAX_PROCESS_ID" in os.environ:
        process_id = _env_int("JAX_PROCESS_ID")
    if not coordinator:
        raise ValueError("--distributed needs --coordinator HOST:PORT "
                         "(or JAX_COORDINATOR_ADDRESS)")
    host, _, port = coordinator.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--coordinator {coordinator!r}: expected HOST:PORT with a port in "
                         "1..65535")
    if num_processes is None or num_processes < 1:
        raise ValueError("--distributed needs --num-processes N >= 1 (or JAX_NUM_PROCESSES)")
    if process_id is None or not 0 <= process_id < num_processes:
        raise ValueError(f"--process-id must be in 0..{num_processes - 1} (or JAX_PROCESS_ID)")
    try:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
    except Exception:  # older jax without the option: CPU barriers may be unavailable
        pass
    if process_id != 0:
        _probe(host, int(port), timeout, say)
    try:
        jax.distributed.initialize(coordinator_address=coordinator,
                                   num_processes=num_processes, process_id=process_id,
                                   initialization_timeout=max(1, math.ceil(timeout)))
    except Exception as e:  # noqa: BLE001 - the runtime's errors are many and verbose
        raise ValueError(f"--coordinator {coordinator}: could not start the distributed "
                         f"runtime within {timeout} s ({type(e).__name__}: "
                         f"{str(e).splitlines()[0][:120] if str(e) else ''})") from None
    return process_id, num_processes


def _env_int(name: str) -> int:
    """The environment variable ``name`` as an int, or a one-line ValueError naming it."""
    text = os.environ[name]
    try:
        return int(text.strip())
    except ValueError:
        raise ValueError(f"{name}={text[:40]!r}: expected an integer") from None


def _probe(host: str, port: int, timeout: float, say=None) -> None:
    """Wait until the coordinator accepts connections, or raise a one-line ValueError: JAX's
    own runtime aborts the whole process (a fatal C++ error) when it cannot reach it."""
    import socket
    import time

    deadline = time.monotonic() + timeout
    while True:
        try:
            with socket.create_connection((host, port), timeout=1.0):
                return
        except OSError as e:
            if say is not None:
                say(f"waiting up to {timeout:g} s for the coordinator {host}:{port} "
                    f"({e.strerror or type(e).__name__}; --coordinator-timeout sets the wait)")
                say = None
            if time.monotonic() > deadline:
                raise ValueError(f"--coordinator {host}:{port}: not reachable within "
                                 f"{timeout:g} s ({e.strerror or type(e).__name__}); is "
                                 "process 0 running?") from None
            time.sleep(0.25)


BARRIER_TIMEOUT_S = 7 * 24 * 3600  # a barrier waits for the slowest process's share of work
_barriers = 0  # barriers passed by this process (every process passes them in the same order)


def barrier(name: str) -> None:
    """All processes wait here (no-op for a single process), for up to ``BARRIER_TIMEOUT_S``.

    The wait is the distributed runtime's own named barrier (its coordination service, as
    JAX's array checkpointing uses), not a device collective: it moves no data over gloo's
    sockets, and two processes at different barriers do not pass each other. A process that
    dies fails the others' wait through the runtime's heartbeats (about 100 s).
    """
    global _barriers
    if jax.process_count() <= 1:
        return
    from jax._src import distributed as runtime

    _barriers += 1
    runtime.global_state.client.wait_at_barrier(f"{name}-{_barriers}",
                                                timeout_in_ms=BARRIER_TIMEOUT_S * 1000)


AGREE_TIMEOUT_S = 120  # how long a process waits for another's configuration


def agree(what: str, value: str) -> None:
    """ValueError (one line) unless every process passes the same ``value`` (no-op for a
    single process): each publishes it in the coordination service's key-value store, then
    reads every process's, so processes started with different flags (another space seed,
    chunk, seed count or process count) stop before any work instead of merging mismatched
    results. ``what`` names the value in the message."""
    global _barriers
    if jax.process_count() <= 1:
        return
    from jax._src import distributed as runtime

    client = runtime.global_state.client
    _barriers += 1
    key = f"jaxfalsify-agree-{_barriers}"
    client.key_value_set(f"{key}/{jax.process_index()}", value)
    other = None
    for i in range(jax.process_count()):
        try:
            theirs = client.blocking_key_value_get(f"{key}/{i}", AGREE_TIMEOUT_S * 1000)
        except Exception:  # noqa: BLE001 - the runtime's timeout error
            raise ValueError(f"process {i} did not report its {what} within "
                             f"{AGREE_TIMEOUT_S} s (started with another --num-processes?)"
                             ) from None
        if theirs != value and other is None:
            other = i
    if other is not None:  # (the console script's leave() orders the processes' exits)
        raise ValueError(f"process {other} was started with another {what} than process "
                         f"{jax.process_index()}: start every process with the same flags")


LEAVE_TIMEOUT_S = 10
LEAVE_GRACE_S = 0.5


def leave() -> None:
    """Called as a process of a multi-process command exits (the console script does; no-op
    otherwise): process 0 hosts the coordination service, and its exit aborts a peer still
    in a call to it (a barrier's reply, an error), so every other process says it is leaving
    and process 0 waits for them (at most ``LEAVE_TIMEOUT_S`` each: a dead peer costs that)."""
    runtime = sys.modules.get("jax._src.distributed")
    client = getattr(getattr(runtime, "global_state", None), "client", None)
    if client is None or jax.process_count() <= 1:
        return
    try:
        if jax.process_index() != 0:
            client.key_value_set(f"jaxfalsify-left/{jax.process_index()}", "1")
            return
        for i in range(1, jax.process_count()):
            client.blocking_key_value_get(f"jaxfalsify-left/{i}", LEAVE_TIMEOUT_S * 1000)
        time.sleep(LEAVE_GRACE_S)  # each said so just before its os._exit: let it happen
    except Exception:  # noqa: BLE001 - a peer or the service already gone: nothing to wait for
        pass


def share(n: int, process_id: int, num_processes: int) -> tuple[int, int]:
    """This process's contiguous share ``[begin, end)`` of n items."""
    return n * process_id // num_processes, n * (process_id + 1) // num_processes
