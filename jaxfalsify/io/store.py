"""Result folders (a run's, sweep's, comparison's, suite's or estimate's): the checks before one
is written (:func:`check_out`), its lock, its ``status.json``, and the removal of earlier
results (``--force``) or of what a failed command wrote.

One concern: result folders: their checks, locks, status and removal.

**Locks.** A process writing a run, sweep or comparison folder holds an exclusive ``flock`` on
``.lock`` in it (the kernel releases it when the process dies, kill -9 included); a second
writer is refused with the holder's pid (:class:`FolderLock`).
"""

from __future__ import annotations

import contextlib
import fcntl
import itertools
import json
import os
import shlex
import shutil
import stat
import tempfile
from pathlib import Path

from jaxfalsify.base.config import read_toml
from jaxfalsify.io.files import write_json

__all__ = [
    "FolderError", "FIGURES", "folder_kind", "check_out", "clear", "FolderLock", "discard",
    "set_aside", "put_back", "drop_earlier", "EARLIER", "complete", "nothing_written",
    "open_folder", "open_new_folder", "shell_path", "write_status", "run_folder_lock",
    "check_out_plain", "Interrupted", "with_article"
]


class FolderError(ValueError):
    """An output folder that cannot be used as asked (one line naming it and what to do)."""


FIGURES = [  # a run's figures under figures/, with their captions in report.md
           ("reward_per_evaluation.png", "Reward per evaluation (paper Fig. 6)"),
           ("distance_challenging.png", "Distance over time, best critical vs typical "
            "non-critical; red = high-risk (paper Fig. 7)"),
           ("high_risk_second_half.png", "High-risk share in the second half (paper Fig. 8)"),
           ("distance_14_scenarios.png", "14 evaluated scenarios, the critical ones red "
            "(paper Fig. 9)"),
           ("critical_regions.png", "Critical regions from the exhaustive sweep, with a "
            "subsample of the evaluated scenarios (collisions as red crosses)"),
           ("search_distribution.png", "Where the search went: each parameter's values among "
            "the evaluations of each stretch of the run"),
           ("failure_clusters.png", "Failure clusters: their sizes, and the distinct critical "
            "scenarios on the two parameters they vary most, coloured by cluster (stars: each "
            "cluster's best-reward member)")]
RESULT_FILES = {
    "run": ("evaluations.parquet", "summary.json", "critical.csv", "timing.json", "report.md",
            "best.rrd", "trajectories.npz"),
    "sweep": ("sweep.parquet", "summary.json", "timing.json"),
    "compare": ("compare.json", "compare.md", "timing.json"),
    "suite": ("suite.json", "suite.md", "timing.json"),
    "estimate": ("summary.json", "timing.json"),
}
EARLIER = ".earlier"  # where --force sets a folder's complete results aside until the job ends
FINISHED = {"run": "summary.json", "sweep": "summary.json", "compare": "compare.json",
            "suite": "suite.json", "estimate": "summary.json"}


OPTIONAL = ("best.rrd", "campaign.rrd", "trajectories.npz")  # written on request only (--rerun,
# replay, an evaluator's trajectories)


def with_article(kind) -> str:
    """``kind`` with its indefinite article: ``a run``, ``an estimate``."""
    return f"{'an' if str(kind)[:1] in 'aeiou' else 'a'} {kind}"


def _result_names(kind: str) -> list[str]:
    """Every file a finished ``kind`` writes, relative to its folder."""
    names = list(RESULT_FILES[kind]) + ["status.json"]
    if kind == "run":
        names += [f"figures/{f}" for f, _ in FIGURES] + ["campaign.rrd"]
    return names


def folder_kind(out: Path) -> str | None:
    """``run``, ``sweep`` or ``compare`` from the folder's ``config.toml`` (None if absent);
    a FolderError if that file cannot be read."""

    path = Path(out) / "config.toml"
    if not path.exists():
        return None
    try:
        kind = read_toml(path).get("kind")
    except ValueError as e:
        raise FolderError(str(e)) from None
    if kind not in RESULT_FILES:
        raise FolderError(f"{path}: not a jaxfalsify run, sweep, compare or suite "
                          f"(kind = {kind!r})")
    return kind


def _checkpoints(out: Path) -> list[Path]:
    """A run's or sweep's checkpoint folders in ``out`` (exact names: a user's own
    ``checkpoints/`` is not one)."""
    out = Path(out)
    return [p for p in [out / "checkpoint", *out.glob("checkpoint-part-*-of-*")] if p.exists()]


def unfinished(out: Path) -> bool:
    out = Path(out)
    return (out / "status.json").exists() or bool(_checkpoints(out))


STATES = ("running", "interrupted", "failed", "complete")


def status_damage(out: Path) -> str | None:
    """What is wrong with ``out``'s ``status.json`` (None when it is absent or a JSON object
    whose ``state`` is one of :data:`STATES`)."""
    path = Path(out) / "status.json"
    if not path.exists():
        return None
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        return f"unreadable: {getattr(e, 'strerror', None) or type(e).__name__}"
    except ValueError:
        return "not JSON"
    state = doc.get("state") if isinstance(doc, dict) else None
    if state not in STATES:
        return f"state {state!r} is not one of {', '.join(STATES)}"
    return None


def complete(out: Path, kind: str) -> bool:
    """``out`` holds finished results of ``kind``: its final file, and a status (if any) that
    says complete. A run that failed while writing its outputs (summary.json written, figures
    not) is unfinished and can be resumed."""
    out = Path(out)
    if not (out / FINISHED[kind]).exists():
        return False
    try:
        return json.loads((out / "status.json").read_text()).get("state") == "complete"
    except FileNotFoundError:
        return True  # a compare or suite writes no status
    except (OSError, ValueError, AttributeError):
        return False


NESTS_NOTHING = ("run", "sweep", "estimate")  # comparisons and suites hold their own jobs


def _holds_results(folder: Path) -> str | None:
    """The kind of job whose results (its final file or a status) ``folder`` holds; None for
    a folder without them, or whose ``config.toml`` is another tool's or unreadable."""
    try:
        kind = folder_kind(folder) if folder.is_dir() else None
    except (FolderError, OSError):
        return None
    if kind is not None and ((folder / FINISHED[kind]).exists()
                             or (folder / "status.json").exists()):
        return kind
    return None


def _check_nesting(out: Path, kind: str, flag: str, resume: bool) -> None:
    """Refuse ``out`` inside a run's, sweep's or estimate's folder (by its real path: ``..``
    and links resolved), and a run, sweep or estimate into a folder holding another job's
    (``--out runs``: its runs would then be inside it)."""
    real = Path(os.path.realpath(out))
    for a in real.parents:
        outer = _holds_results(a)
        if outer in NESTS_NOTHING:
            shown = (a if out.is_absolute() or a == Path.cwd().resolve() else
                     Path(os.path.relpath(a, Path.cwd().resolve())))
            raise FolderError(f"{flag} is inside {shown}, which holds {with_article(outer)}; "
                              "choose a folder outside it")
    if kind in NESTS_NOTHING and not resume:
        with contextlib.suppress(RuntimeError, OSError):  # no home folder known
            if real == Path.home().resolve():
                raise FolderError(f"{flag} is your home folder; {with_article(kind)} takes a "
                                  "folder of its own (every later job below it would be "
                                  "refused: choose another)")
        if real == real.parent:
            raise FolderError(f"{flag} is the filesystem root; {with_article(kind)} takes a "
                              "folder of its own (choose another)")
        found = _results_below(out) if out.is_dir() else None
        if found is not None:
            inner, child = found
            raise FolderError(f"{flag} holds {with_article(inner)} in {child}; "
                              f"{with_article(kind)} takes a folder of its own (choose "
                              "another)")


NESTING_DEPTH = 4  # how deep below a new run's folder another job's folder is looked for
NESTING_FOLDERS = 5000  # and in how many folders at most (a huge tree is not walked whole)


def _results_below(out: Path) -> tuple[str, Path] | None:
    """The kind and folder of the first job's results found below ``out`` (breadth first, at
    most :data:`NESTING_DEPTH` levels and :data:`NESTING_FOLDERS` folders; links and
    ``.earlier`` not entered), or None."""
    level, seen = [out], 0
    for _ in range(NESTING_DEPTH):
        below = []
        for folder in level:
            try:
                children = sorted(c for c in folder.iterdir()
                                  if c.name != EARLIER and c.is_dir() and not c.is_symlink())
            except OSError:
                continue
            for child in children:
                kind = _holds_results(child)
                if kind is not None:
                    return kind, child
                seen += 1
                if seen >= NESTING_FOLDERS:
                    return None
                below.append(child)
        level = below
    return None


def check_out(out: Path, kind: str, *, force: bool = False, resume: bool = False) -> None:
    """Refuse an output folder that is a file, holds another kind of result, holds finished
    results (without ``force``) or unfinished ones (without ``resume`` or ``force``), or cannot
    be written (probed by creating and removing a temporary file, so it holds for root too).
    Raises :class:`FolderError`."""
    out = Path(out)
    flag = f"--resume {out}" if resume else f"--out {out}"
    if out.exists() and not out.is_dir():
        raise FolderError(f"{flag} exists and is not a folder")
    if out.is_symlink() and not out.exists():
        raise FolderError(f"{flag} is a link to nothing ({os.readlink(out)})")
    have = folder_kind(out)
    earlier = out / EARLIER
    if force and (earlier.is_symlink() or (earlier.exists() and not earlier.is_dir())):
        raise FolderError(f"{flag}: {earlier} is not a folder (--force keeps earlier results "
                          "there); move it away")
    _check_nesting(out, kind, flag, resume)
    if resume:
        if have is None:
            raise FolderError(f"--resume {out}: no config.toml there "
                              f"(not {with_article(kind)} folder)")
        if have != kind:
            raise FolderError(f"--resume {out}: that folder holds {with_article(have)}, "
                              f"not {with_article(kind)}")
        damaged = status_damage(out)
        if damaged:
            raise FolderError(f"--resume {out}: status.json is damaged ({damaged}), so whether "
                              f"the {kind} finished is unknown; start it over with --out "
                              f"{shell_path(out)} --force")
        if complete(out, kind):
            raise FolderError(f"--resume {out}: the {kind} is already complete "
                              f"({FINISHED[kind]})")
    else:
        if have is not None and have != kind:
            raise FolderError(f"--out {out} holds {with_article(have)}; {with_article(kind)} "
                              "is never written into it (choose another folder)")
        if complete(out, kind) and not force:
            raise FolderError(f"--out {out} already holds {FINISHED[kind]}; pass --force to "
                              "overwrite")
        if kind not in ("compare", "suite") and unfinished(out) and not force:
            raise FolderError(
                f"--out {out} holds an unfinished {kind}; pass --resume {shell_path(out)} to "
                "continue it or --force to start over" if kind in RESUMABLE else
                f"--out {out} holds an {kind} that did not complete (see its status.json); "
                "pass --force to start it over")
        if have is None and not force:  # a user's files under the names a result takes
            theirs = [n for n in _result_names(kind) if (out / n).exists()]
            if theirs:
                raise FolderError(f"--out {out} already holds {theirs[0]} (not written by "
                                  "jaxfalsify); pass --force to overwrite it or choose "
                                  "another folder")
    # a folder under a name the result writes as a file (or a file where it makes a folder)
    # would fail the job's last writes, after the work: refused before, with or without --force
    for name in _result_names(kind):
        if name not in OPTIONAL and (out / name).is_dir():
            raise FolderError(f"{flag}: {out / name} is a folder where the {kind} writes a "
                              "file (move it away or choose another folder)")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    if not parent.is_dir():
        raise FolderError(f"{flag}: {parent} is not a folder")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise FolderError(f"{flag}: cannot write in {parent} ({e.strerror})") from None


def _results_in(out: Path, kind: str, extra: tuple[str, ...] = ()) -> list[Path]:
    """The paths in ``out`` that hold a job's results, status and checkpoints: the files of
    those names, its checkpoint folders, and where ``config.toml`` says the folder holds a
    run, that run's figures and recordings by name; ``extra``: more names (a comparison's
    ``runs/``). A user's own files (``checkpoints/``, ``figures/plot.png``) are not among
    them."""
    out = Path(out)
    paths = [out / n for n in RESULT_FILES[kind] + ("status.json", "config.toml") + extra]
    paths += [*out.glob(".summary.part-*.json"), *_checkpoints(out),
              *out.glob("sweep.part-*.parquet")]
    if folder_kind(out) == kind and kind == "run":  # its figures and replay's recordings
        paths += [*(out / "figures" / f for f, _ in FIGURES), out / "campaign.rrd",
                  *out.glob("replay-*.rrd")]
    return [p for p in paths if p.exists() or p.is_symlink()]


def _remove_empty_figures(out: Path) -> None:
    with contextlib.suppress(OSError):  # only if nothing else is in it
        (Path(out) / "figures").rmdir()


def clear(out: Path, kind: str, extra: tuple[str, ...] = ()) -> None:
    """Remove a folder's earlier results, status and checkpoints (the paths of
    :func:`_results_in`); a user's own files stay."""
    out = Path(out)
    for p in _results_in(out, kind, extra):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    _remove_empty_figures(out)


def set_aside(out: Path, kind: str, extra: tuple[str, ...] = ()) -> None:
    """``--force``: move a folder's complete results (and the ``extra`` names) into
    ``OUT/.earlier`` (same relative paths), replacing what it held; they stay there until the
    new job completes (:func:`drop_earlier`) or are put back if it fails with nothing worth
    keeping (:func:`discard`). Results that are not complete (an interrupted or failed job
    started over) are removed, and ``.earlier`` keeps the last complete ones."""
    out = Path(out)
    if not complete(out, kind):
        clear(out, kind, extra)
        return
    drop_earlier(out)
    for p in _results_in(out, kind, extra):
        target = out / EARLIER / p.relative_to(out)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(p, target)
    _remove_empty_figures(out)


def put_back(out: Path) -> bool:
    """Move the results :func:`set_aside` kept in ``OUT/.earlier`` back into ``out`` (the
    new job's files of those names replaced). Returns whether there were any."""
    out = Path(out)
    earlier = out / EARLIER
    if not earlier.is_dir():
        return False
    for p in earlier.iterdir():
        target = out / p.name
        if p.name == "figures" and p.is_dir():  # a run's figures, beside a user's own
            target.mkdir(exist_ok=True)
            for f in p.iterdir():
                os.replace(f, target / f.name)
            continue
        if target.is_dir() and not target.is_symlink():
            shutil.rmtree(target)
        os.replace(p, target)
    shutil.rmtree(earlier, ignore_errors=True)
    return True


def drop_earlier(out: Path) -> None:
    """The job in ``out`` completed: the results :func:`set_aside` kept are removed."""
    shutil.rmtree(Path(out) / EARLIER, ignore_errors=True)


class FolderLock:
    """An exclusive OS lock (``flock``) on ``OUT/.lock``, held while a process writes the folder:
    a second writer gets a :class:`FolderError` naming the holder's pid. The kernel releases
    it when the process ends however it ends, so no stale lock survives a kill -9."""

    def __init__(self, out: Path, name: str = ".lock"):
        self.path = Path(out) / name
        self.fd: int | None = None

    def acquire(self, kind: str) -> "FolderLock":
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:  # never through a link: claim() truncates the file
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o644)
        except OSError as e:
            raise FolderError(f"{self.path}: cannot be used as the folder's lock file "
                              f"({e.strerror}; a link or a folder there?)") from None
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            os.close(fd)
            raise FolderError(f"{self.path} is not a plain file; remove it")
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            try:
                holder = os.pread(fd, 64, 0).decode(errors="replace").split()
            finally:
                os.close(fd)
            pid = holder[0] if holder else "unknown"
            what = holder[1] if len(holder) > 1 else "jaxfalsify"
            raise FolderError(f"{self.path.parent} is being written by process {pid} "
                              f"({what}); wait for it to end or choose another folder") from None
        self.fd = fd
        self.claim(kind)  # the holder's pid is readable from the moment the lock is held
        return self

    def check_free(self) -> None:
        """Raise the :class:`FolderError` naming the holder if another process holds this
        lock (an existing lock file only: nothing is created); else return."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            return
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                return
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 64, 0).decode(errors="replace").split()
                pid = holder[0] if holder else "unknown"
                what = holder[1] if len(holder) > 1 else "jaxfalsify"
                raise FolderError(f"{self.path.parent} is being written by process {pid} "
                                  f"({what}); wait for it to end or choose another folder"
                                  ) from None
            fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)

    def claim(self, kind: str) -> None:
        """Record this process as the writer in the lock file, as soon as it holds the lock
        (so a second writer is told whose it is while this one still validates; a resume then
        refused leaves its pid there, the lock file's only content: no result changes)."""
        if self.fd is not None:
            os.ftruncate(self.fd, 0)
            os.pwrite(self.fd, f"{os.getpid()} jaxfalsify-{kind}\n".encode(), 0)

    def release(self) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()


def lock(out: Path, kind: str, name: str = ".lock") -> FolderLock:
    """Take ``out``'s lock (creating the folder), or raise FolderError naming the holder."""
    return FolderLock(out, name).acquire(kind)


def discard(out: Path, kind: str, lk: "FolderLock", existed: bool) -> None:
    """Remove what a failed command wrote to ``out`` (a user's SUT that raised: its results
    mean nothing): results, status, config and checkpoints (:func:`clear`), the lock file, and
    the folder itself if the command created it and nothing else is in it. Results that
    ``--force`` set aside (:func:`set_aside`) are put back."""
    out = Path(out)
    clear(out, kind)
    put_back(out)
    with contextlib.suppress(OSError):
        lk.path.unlink()
    lk.release()
    if not existed:
        with contextlib.suppress(OSError):
            out.rmdir()


def nothing_written(out: Path) -> bool:
    """Whether a job holding ``out``'s lock has written none of its own files yet (neither
    ``config.toml`` nor ``status.json``): a failure then undoes the lock (:func:`discard`),
    leaving the folder as the job found it."""
    out = Path(out)
    return not (out / "config.toml").exists() and not (out / "status.json").exists()


def open_folder(out: Path, kind: str, *, force: bool = False, resume: bool = False,
                name: str = ".lock") -> FolderLock:
    """Check ``out`` (:func:`check_out`), lock it, and check again under the lock (another
    process may have written it meanwhile). On failure nothing is left behind: a folder this
    call created for its lock file is removed again."""
    out = Path(out)
    try:
        check_out(out, kind, force=force, resume=resume)
    except FolderError:  # the folder looks unfinished because another process writes it:
        FolderLock(out, name).check_free()  # name that process instead
        raise
    existed = out.exists()
    lk = lock(out, kind, name)
    try:
        check_out(out, kind, force=force, resume=resume)
    except BaseException:
        lk.release()
        if not existed:
            shutil.rmtree(out, ignore_errors=True)
        raise
    return lk


def open_new_folder(base: Path, kind: str) -> tuple[Path, FolderLock]:
    """A folder of a default name (``runs/<time>-<strategy>``) created here, exclusively:
    ``base``, or ``base-2``, ``base-3``, ... when another command (one started in the same
    second) has it, then locked. Returns the folder and its lock."""
    base = Path(base)
    base.parent.mkdir(parents=True, exist_ok=True)
    for k in itertools.count(1):
        out = base if k == 1 else base.with_name(f"{base.name}-{k}")
        try:
            out.mkdir()
            break
        except FileExistsError:
            continue
    try:
        return out, open_folder(out, kind)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise


def shell_path(path: Path | str) -> str:
    """A folder as a shell word for a command to paste: quoted, and ``./`` before a relative
    name that starts with ``-`` (which the command line would read as a flag)."""
    text = str(path)
    if text.startswith("-"):
        text = "./" + text
    return shlex.quote(text)


RESUMABLE = ("run", "sweep")  # the jobs a --resume continues


def write_status(out: Path, kind: str, state: str, **extra) -> None:
    """``status.json``: ``running``, ``interrupted`` or ``complete``, and how to resume (a
    run or a sweep; another job is started over with ``--force``)."""
    doc = {"state": state, **extra}
    if state != "complete" and kind in RESUMABLE:
        doc.setdefault("resume", f"jaxfalsify {kind} --resume {shell_path(out)}")
    if state != "complete" and (Path(out) / EARLIER).is_dir():
        doc.setdefault("earlier_results", f"{EARLIER}/ (set aside by --force until this "
                       f"{kind} completes)")
    write_json(Path(out) / "status.json", doc, indent=2)
    if state == "complete":
        drop_earlier(out)


def run_folder_lock(run_dir: Path, what: str) -> FolderLock:
    """The lock of a finished run's folder, claimed for ``what`` (``figures``, ``replay``):
    held while a command writes into the folder, never while the run itself or another
    writer holds it (one-line ValueError then, and for a folder that is no run)."""
    if not (Path(run_dir) / "config.toml").is_file():
        raise ValueError(f"{run_dir} is not a finished run folder (no config.toml)")
    lk = lock(Path(run_dir), "run")
    lk.claim(what)
    return lk


def check_out_plain(out: Path, patterns: tuple[str, ...], force: bool) -> None:
    """An output folder for files that are not a run, sweep or compare (exports): refuse a
    file in the way, a result folder, a file matching one of the glob ``patterns`` (what the
    command writes) without ``force``, or no write access."""
    import fnmatch

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FolderError(f"--out {out} exists and is not a folder")
    if folder_kind(out) is not None:
        raise FolderError(f"--out {out} holds {with_article(folder_kind(out))}; "
                          "choose another folder")
    for a in [out, *out.parents]:  # a job's checkpoint folder is its own: --force removes it
        if not (a.name == "checkpoint" or a.name.startswith("checkpoint-part-")) or \
                a.parent == a:
            continue
        try:
            job = folder_kind(a.parent)
        except FolderError:  # another tool's config.toml (or an unreadable one): not a job
            job = None
        if job is not None:
            raise FolderError(f"--out {out} is inside the checkpoint folder of the {job} in "
                              f"{a.parent}, which that job removes; choose another folder")
    there = sorted(f.name for f in out.iterdir() if any(
        fnmatch.fnmatch(f.name, p) for p in patterns)) if out.is_dir() else []
    if there and not force:
        raise FolderError(f"--out {out} already holds {there[0]}"
                          f"{f' (and {len(there) - 1} more)' if len(there) > 1 else ''}; "
                          "pass --force to overwrite")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise FolderError(f"--out {out}: cannot write in {parent} ({e.strerror})") from None


class Interrupted(Exception):
    """A run or sweep stopped on request (Ctrl-C, SIGTERM, ``stop()``); everything done is
    committed and ``resume`` continues it."""

    def __init__(self, kind: str, out: Path, done: int, total: int, unit: str,
                 resumable: bool = True):
        self.kind, self.out, self.done, self.total = kind, Path(out), done, total
        self.resume = (f"jaxfalsify {kind} --resume {shell_path(out)}" if resumable
                       else None)  # a command to paste into a shell
        super().__init__(f"interrupted after {done} of {total} {unit}; " + (
            f"{out} is resumable: {self.resume}" if resumable
            else f"nothing was written to {out}; run the {kind} again"))
