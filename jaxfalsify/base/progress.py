"""Progress of long work (host side): a compiling phase, then a bar whose rates and ETA count
post-compile work only, continuing from the count already done on resume.

Library calls take a :class:`Progress` (the base class reports nothing); the CLI passes a
:class:`Bar` (tqdm on stderr) unless ``--quiet``.
"""

from __future__ import annotations

import os
import sys
import time

__all__ = ["IMPORTED_AT", "Progress", "Bar", "startup_seconds", "Clock", "timing_line"]

IMPORTED_AT = time.perf_counter()  # when jaxfalsify began to load (its __init__ imports this
# module first): start-up accounting


class Progress:
    """Silent progress: the interface."""

    def phase(self, text: str) -> None:
        """A step without a count (compiling, writing, drawing figures)."""

    def start(self, total: int, done: int = 0, unit: str = "eval", desc: str = "") -> None:
        """Counted work begins (after compilation) with ``done`` of ``total`` already done."""

    def update(self, done: int, **stats) -> None:
        """``done`` of ``total`` now; ``stats`` shown beside the bar."""

    def close(self) -> None:
        """The counted work is over (or was interrupted)."""

    def message(self, text: str) -> None:
        """A line for the user."""


class Bar(Progress):
    """tqdm bar on stderr; phases are printed as lines."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr
        self.bar = None

    def phase(self, text: str) -> None:
        self.close()
        print(f"{text} ...", file=self.stream, flush=True)

    def start(self, total: int, done: int = 0, unit: str = "eval", desc: str = "") -> None:
        from tqdm import tqdm

        self.close()
        self.bar = tqdm(total=total, initial=done, unit=unit, desc=desc, file=self.stream,
                        unit_scale=unit != "eval", dynamic_ncols=True)

    def update(self, done: int, **stats) -> None:
        if self.bar is None:
            return
        if stats:
            self.bar.set_postfix(stats, refresh=False)
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def message(self, text: str) -> None:
        self.close()
        print(text, file=self.stream, flush=True)


def process_age() -> float:
    """Seconds since this process started (Linux /proc; 0 where unavailable): the start-up
    time that imports cost before any of our code ran."""
    try:
        with open("/proc/self/stat") as f:
            ticks = int(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return 0.0


EXEC_SLACK = 1.0  # s: process age beyond the package's own load time that means another program
# ran first in this process


def startup_seconds() -> float:
    """Start-up of this command: seconds since the interpreter started, as the process's age
    (:func:`process_age`: interpreter start-up and imports). A shell runs the last command of
    ``a && b`` by replacing itself (exec), so the process's age then also counts ``a`` (e.g.
    ``pip install``); when the age exceeds the time since ``jaxfalsify`` began to load by more
    than ``EXEC_SLACK``, the latter is taken (interpreter start-up before it, ~0.05 s, is then
    left out)."""
    own = time.perf_counter() - IMPORTED_AT
    age = process_age()
    return age if age <= own + EXEC_SLACK else own


class Clock:
    """Wall time of named phases (``with clock("figures"): ...``), from a start offset."""

    def __init__(self, startup: float = 0.0):
        self.t0 = time.perf_counter()
        self.startup = startup
        self.phases: dict[str, float] = {}

    def add(self, name: str, seconds: float) -> None:
        self.phases[name] = self.phases.get(name, 0.0) + seconds

    def __call__(self, name: str):
        clock = self

        class _Phase:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                clock.add(name, time.perf_counter() - self.t)

        return _Phase()

    def total(self) -> float:
        return self.startup + time.perf_counter() - self.t0

    def summary(self) -> dict[str, float]:
        """``total_seconds``, ``startup_seconds``, each phase's seconds, ``other_seconds``."""
        total = self.total()
        out = {"total_seconds": total, "startup_seconds": self.startup}
        out.update({f"{k}_seconds": v for k, v in self.phases.items()})
        out["other_seconds"] = max(0.0, total - self.startup - sum(self.phases.values()))
        return out



def timing_line(timing: dict) -> str:
    """``12.3 s (startup 1.1 s, compile 3.0 s, ...)`` from a :meth:`Clock.summary`."""
    parts = [f"{k[:-8]} {v:.1f} s" for k, v in timing.items()
             if k.endswith("_seconds") and k != "total_seconds" and v >= 0.05]
    return f"{timing['total_seconds']:.1f} s ({', '.join(parts)})"
