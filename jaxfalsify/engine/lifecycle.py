"""A job folder's life, the same for every job that writes one (``run``, ``sweep``,
``compare``, ``estimate``, a system outside JAX): ``status.json`` says ``running`` when the work
starts, then ``interrupted`` (with the command that resumes it), ``failed`` (with the error, one
line) or ``complete``, written after every result file. A job whose user SUT raised discards
what it wrote (:func:`sut_raised`): nothing of it is worth keeping; complete results that
``--force`` set aside are put back then, and removed once the job completes
(:func:`jaxfalsify.io.store.set_aside`)."""

from __future__ import annotations

from pathlib import Path

from jaxfalsify.io import store
from jaxfalsify.suts.registry import callback_error

__all__ = ["ERROR_CHARS", "Status", "error_text", "sut_raised"]

ERROR_CHARS = 300  # the longest error text status.json keeps
STATES = ("running", "interrupted", "failed", "complete")


class Status:
    """``status.json`` of the job folder ``out`` of kind ``kind`` (``run``, ``sweep``, ...);
    ``always``: fields written with every state (an evaluator's settings, say)."""

    def __init__(self, out: Path | str, kind: str, **always):
        self.out, self.kind, self.always = Path(out), kind, always

    def write(self, state: str, **extra) -> None:
        """``status.json`` = ``state`` (one of :data:`STATES`) with ``extra`` fields."""
        if state not in STATES:
            raise ValueError(f"a job's state is one of {', '.join(STATES)} (got {state!r})")
        store.write_status(self.out, self.kind, state, **{**self.always, **extra})

    def running(self, **extra) -> None:
        self.write("running", **extra)

    def interrupted(self, **extra) -> None:
        self.write("interrupted", **extra)

    def complete(self, **extra) -> None:
        self.write("complete", **extra)

    def failed(self, e: BaseException, **extra) -> None:
        """``failed`` with :func:`error_text` of ``e``; best effort: when the status cannot be
        written (a full disk, the folder gone) the job's own error is what the caller raises."""
        try:
            self.write("failed", **extra, error=error_text(e))
        except OSError:
            pass


def error_text(e: BaseException) -> str:
    """What ``status.json`` says of a failure: a user's SUT's own exception when it raised in a
    host callback, else the exception's type and message (at most ``ERROR_CHARS``)."""
    return (callback_error(e) or f"{type(e).__name__}: {e}")[:ERROR_CHARS]


def sut_raised(e: BaseException) -> bool:
    """Whether ``e`` is a user's SUT raising inside the compiled program (a host callback)."""
    return callback_error(e) is not None
