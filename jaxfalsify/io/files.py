"""Atomic files: every file is written under a temporary name in its folder and renamed into
place (with the permissions the process's umask gives), so a file under its final name is
always complete; groups of files are published together (:func:`replace_files`)."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from jaxfalsify.base.config import jsonable

__all__ = [
    "sha256", "write_atomic", "write_all_atomic", "replace_files", "atomic_path", "save_npz",
    "write_parquet", "write_json", "jsonable", "naming_errors"
]


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _tmp_in(folder: Path, name: str) -> Path:
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
    os.close(fd)
    return Path(tmp)


_UMASK = os.umask(0)  # read once, at import: setting it is process-wide, and background
os.umask(_UMASK)  # threads create files (ground truths, checkpoints) while others publish


def _publish(tmp, path: Path) -> None:
    """Rename a finished temporary file into place with the mode a plain ``open`` would give
    it (``mkstemp`` creates 0600 files)."""
    os.chmod(tmp, 0o666 & ~_UMASK)
    os.replace(tmp, path)


def write_atomic(path: Path, data: str | bytes) -> str:
    """Write text or bytes to ``path`` via a temporary file in the same folder and a rename;
    returns the SHA-256 of the bytes written."""
    path = Path(path)
    data = data.encode() if isinstance(data, str) else bytes(data)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with naming_errors(path):
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            _publish(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return sha256(data)


def write_all_atomic(files: dict[Path, bytes]) -> None:
    """Write several files as one set: every one to a temporary file first, then all renamed
    into place, so a failure while writing (a full disk) leaves every earlier file as it was
    and no temporary file behind."""
    staged = []
    try:
        for path, data in files.items():
            tmp = _tmp_in(Path(path).parent, Path(path).name)
            staged.append((tmp, Path(path)))
            with naming_errors(Path(path)):
                tmp.write_bytes(data)
        for tmp, path in staged:
            _publish(tmp, path)
    finally:
        for tmp, _ in staged:
            if tmp.exists():
                tmp.unlink()


def replace_files(staged: list[Path], folder: Path, is_old) -> list[Path]:
    """Publish a set of finished files ``staged`` (on ``folder``'s file system, e.g. in a
    temporary folder inside it, so every move is a rename) into ``folder`` in place of an
    earlier set (the files whose names ``is_old(name)`` accepts): the earlier files are moved
    aside (into a hidden folder of ``folder``) first, then the new ones in; on a failure the
    new ones are removed and every earlier one put back (where one cannot be, the hidden
    folder is kept and the error names it). Returns the published paths."""
    if not staged:
        raise ValueError("replace_files: no files to publish (the earlier set would go)")
    folder = Path(folder)
    aside = Path(tempfile.mkdtemp(dir=folder, prefix=".replaced-"))
    old, new = [], []
    try:
        for f in sorted(folder.iterdir()):
            if f.is_file() and is_old(f.name):
                os.replace(f, aside / f.name)
                old.append(f.name)
        for f in staged:
            os.replace(f, folder / f.name)
            new.append(f.name)
    except BaseException as e:
        for n in new:
            (folder / n).unlink(missing_ok=True)
        lost = []
        for n in old:
            try:
                os.replace(aside / n, folder / n)
            except OSError:
                lost.append(n)
        if lost:
            raise OSError(f"{folder}: publishing failed ({e}) and {len(lost)} earlier "
                          f"file(s) could not be put back; they are in {aside}") from e
        aside.rmdir()
        raise
    shutil.rmtree(aside, ignore_errors=True)  # the earlier set, replaced
    return [folder / f.name for f in staged]


@contextlib.contextmanager
def naming_errors(path: Path):
    """An OSError without a file name (a write to an open file on a full disk) gets
    ``path``'s, so its one-line error says which file could not be written."""
    try:
        yield
    except OSError as e:
        if e.filename or e.errno is None:
            raise
        raise OSError(e.errno, e.strerror, str(path)) from e


@contextlib.contextmanager
def atomic_path(path: Path):
    """``with atomic_path(final) as tmp: write(tmp)``: whatever writes ``tmp`` (a library
    that wants a file name: matplotlib, rerun, a Parquet writer), the result appears under
    ``final`` only once complete (a rename in the same folder); on failure the temporary
    file is removed and ``final`` is untouched."""
    path = Path(path)
    tmp = _tmp_in(path.parent, path.name)
    try:
        with naming_errors(path):
            yield tmp
            _publish(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """``np.savez``, atomically; returns the file's SHA-256."""
    return write_atomic(path, npz_bytes(arrays))


def parquet_bytes(columns: dict) -> bytes:
    import pyarrow as pa
    import pyarrow.parquet as pq

    buf = io.BytesIO()
    pq.write_table(pa.table(columns), buf)
    return buf.getvalue()


def write_parquet(path: Path, columns: dict) -> str:
    """A Parquet table of ``{name: (N,) array}``, written atomically; returns its SHA-256."""
    return write_atomic(path, parquet_bytes(columns))


def write_json(path: Path, doc: dict, indent: int = 1) -> str:
    return write_atomic(path, json.dumps(jsonable(doc), indent=indent) + "\n")
