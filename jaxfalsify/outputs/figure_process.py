"""A second process that draws part of a run's figures while the run writes its files.

Drawing is single-threaded Python (matplotlib) and so is writing a run's files: after the
search one core of a two-core machine would idle while the other does both. ``runs.execute``
starts this process (:func:`command`) before its search; the
process imports matplotlib and draws the critical-region map up to the run's own scenarios
(:func:`jaxfalsify.outputs.figures.prepare`) while the search runs, and once it is sent the
evaluated scenarios it draws :func:`jaxfalsify.outputs.figures.sweep_figures` (the
critical-region map, where the search went, the failure clusters) and sends back their PNG
files, which the run writes with its other figures. The files are the same bytes as drawn in
the run's own process (tested); a process that cannot start, fails or stalls costs nothing but
its time: the run then draws those figures itself.

Messages are pickles over the process's stdin and stdout: ``("prepare", space, config,
world)``, then ``("draw", evaluations)``; the answer is ``("ok", {file name: PNG bytes})`` or
``("error", one line)``.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading
from pathlib import Path

from jaxfalsify.base import threads

__all__ = ["FigureProcess", "command", "wanted", "main"]

ENV = "JAXFALSIFY_FIGURE_PROCESS"  # "0": draw every figure in the run's own process


def wanted() -> bool:
    """Whether a run draws part of its figures in a second process: when the machine gives
    this process two or more cores and ``JAXFALSIFY_FIGURE_PROCESS`` is not ``0``."""
    if os.environ.get(ENV, "").strip().lower() in ("0", "false", "no"):
        return False
    return threads.cores() >= 2


def command() -> list[str]:
    """The process's command line: this interpreter, importing this very copy of the package
    first (``-P``: not whatever ``jaxfalsify`` the working directory holds)."""
    root = str(Path(__file__).resolve().parents[2])
    return [sys.executable, "-P", "-c",
            f"import sys; sys.path.insert(0, {root!r}); "
            f"from {__name__} import main; sys.exit(main())"]


class FigureProcess:
    """The run's side of the second process: start it, send it the run (:meth:`draw`), take
    its figures (:meth:`collect`). Every failure (it did not start, raised, died, stalled)
    makes :meth:`collect` return None."""

    def __init__(self, space, config, world):
        self._answer: bytes | None = None
        self._reader: threading.Thread | None = None
        self._sender: threading.Thread | None = None
        try:
            self._proc = subprocess.Popen(command(), stdin=subprocess.PIPE,
                                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        except OSError:
            self._proc = None
            return
        self._send(("prepare", space, config, world), close=False)

    def _send(self, message, close: bool) -> None:
        before = self._sender

        def work():
            if before is not None:  # one message after the other
                before.join()
            try:
                pickle.dump(message, self._proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                self._proc.stdin.flush()
                if close:
                    self._proc.stdin.close()
            except (OSError, ValueError, pickle.PicklingError):  # the process died
                pass

        # the process reads a message only when it is ready for it: a large one is written
        # from a thread (the pipe's write releases the GIL)
        self._sender = threading.Thread(target=work, daemon=True, name="jaxfalsify-figure-send")
        self._sender.start()

    def draw(self, evaluations: dict) -> None:
        """Send the run's evaluated scenarios (``evaluations.parquet``'s columns); the
        process draws its figures from them and answers."""
        if self._proc is None:
            return
        self._send(("draw", evaluations), close=True)

        def read():
            try:
                self._answer = self._proc.stdout.read()
            except (OSError, ValueError):
                pass

        self._reader = threading.Thread(target=read, daemon=True, name="jaxfalsify-figure-read")
        self._reader.start()

    def collect(self, timeout: float = 300.0) -> dict[str, bytes] | None:
        """``{file name: PNG bytes}`` of the figures the process drew, or None (it failed,
        or gave no answer within ``timeout`` seconds: it is stopped)."""
        if self._reader is None:  # it did not start, or was never sent the run
            self.close()
            return None
        self._reader.join(timeout)
        self.close()
        try:
            kind, value = pickle.loads(self._answer) if self._answer else (None, None)
        except Exception:  # noqa: BLE001 - a truncated or foreign answer: draw here
            return None
        return value if kind == "ok" else None

    def close(self) -> None:
        """Stop the process if it still runs (an interrupted run, a stalled process)."""
        if self._proc is None:
            return
        if self._proc.poll() is None:
            self._proc.kill()
        try:
            self._proc.wait(5)
        except subprocess.TimeoutExpired:
            pass
        for f in (self._proc.stdin, self._proc.stdout):
            try:
                f.close()
            except (OSError, ValueError):
                pass


def main() -> int:
    """The process itself: prepare, then draw when asked, answer, exit."""
    stdin = sys.stdin.buffer
    stdout = os.fdopen(os.dup(1), "wb")  # the answer's own stream: whatever a library
    os.dup2(2, 1)  # prints goes where the process's stderr goes
    try:
        from jaxfalsify.outputs import figures

        kind, space, config, world = pickle.load(stdin)
        if kind != "prepare":
            raise ValueError(f"expected prepare, got {kind!r}")
        try:  # as in the run's own process: a failure here only costs the head start
            prepared = figures.prepare(space, config.sut, dict(config.sut_params), world,
                                       trajectories=False)
        except Exception:  # noqa: BLE001
            prepared = None
        kind, evaluations = pickle.load(stdin)
        if kind != "draw":
            raise ValueError(f"expected draw, got {kind!r}")
        answer = ("ok", figures.sweep_figures(space, config, evaluations, world, prepared))
    except Exception as e:  # noqa: BLE001 - the run draws these figures itself
        answer = ("error", f"{type(e).__name__}: {str(e)[:200]}")
    stdout.write(pickle.dumps(answer, protocol=pickle.HIGHEST_PROTOCOL))
    stdout.flush()
    return 0 if answer[0] == "ok" else 1


if __name__ == "__main__":
    sys.exit(main())
