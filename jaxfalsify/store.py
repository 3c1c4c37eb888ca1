"""Everything that writes result folders: atomic writes, run/sweep folder checks, status,
and checkpoints of long work (a campaign's carry and records, a sweep's progress).

Every file is written under a temporary name in its folder and renamed into place, so a file
under its final name is always complete. A checkpoint is a folder written only through atomic renames, in an order that keeps it
consistent whatever moment the process dies (SIGKILL included):

1. the new chunk's data (``records-<c>.npz`` or ``rows-<c>.parquet``) under a temporary name,
   then renamed;
2. for campaigns, the carry after chunk ``c`` (``carry-<c>.npz``), the same way;
3. ``state.json`` naming how many chunks are done: the commit point. Files of chunks past it
   are ignored (and rewritten, identically, when the work resumes).

The carry is any pytree of arrays (strategy state, optimiser state, typed PRNG keys); it is
stored as its leaves and restored into the tree structure of a template (``jax.eval_shape``
of the campaign's ``init``), checking every leaf's shape and dtype. Anything that does not
match — a truncated file, another configuration's checkpoint, hand edits — raises
:class:`CheckpointError` with one line naming the file.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

FORMAT = 1


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (corrupt, missing files, another configuration)."""


def _is_key(x) -> bool:
    return jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _tmp_in(folder: Path, name: str) -> Path:
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{name}.", suffix=".tmp")
    os.close(fd)
    return Path(tmp)


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """``np.savez`` to a temporary file in the same folder, then rename."""
    tmp = _tmp_in(path.parent, path.name)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint file {path} is missing") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CheckpointError(f"checkpoint file {path} is corrupt ({type(e).__name__})") from None


def write_atomic(path: Path, data: str | bytes) -> None:
    """Write text or bytes to ``path`` via a temporary file in the same folder and a rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def write_parquet(path: Path, columns: dict) -> None:
    """A Parquet table of ``{name: (N,) array}``, written atomically."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    tmp = _tmp_in(path.parent, path.name)
    try:
        pq.write_table(pa.table(columns), tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json(path: Path, doc: dict, indent: int = 1) -> None:
    from jaxfalsify.config import jsonable

    write_atomic(path, json.dumps(jsonable(doc), indent=indent) + "\n")


def read_json(path: Path) -> dict:
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint file {path} is missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"checkpoint file {path} is corrupt ({type(e).__name__})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint file {path} is not a jaxfalsify checkpoint "
                              f"(format {FORMAT})")
    return doc


def carry_arrays(carry) -> dict[str, np.ndarray]:
    """The leaves of a carry as host arrays (typed keys as their raw key data)."""
    leaves = jax.tree.leaves(carry)
    return {f"leaf_{i:04d}": np.asarray(jax.random.key_data(x) if _is_key(x) else x)
            for i, x in enumerate(leaves)}


def restore_carry(arrays: dict[str, np.ndarray], template, where: Path):
    """Rebuild a carry from :func:`carry_arrays` output into ``template``'s structure."""
    leaves, treedef = jax.tree.flatten(template)
    if len(arrays) != len(leaves):
        raise CheckpointError(f"checkpoint file {where} holds {len(arrays)} arrays, this "
                              f"configuration's state has {len(leaves)}")
    out = []
    for i, t in enumerate(leaves):
        a = arrays.get(f"leaf_{i:04d}")
        if a is None:
            raise CheckpointError(f"checkpoint file {where} lacks state array {i}")
        if _is_key(t):
            try:
                x = jax.random.wrap_key_data(a)
            except (TypeError, ValueError):
                raise CheckpointError(f"checkpoint file {where}: state array {i} is not a "
                                      "PRNG key") from None
            if x.dtype != t.dtype or x.shape != t.shape:
                raise CheckpointError(f"checkpoint file {where}: PRNG key {i} does not match "
                                      "this configuration")
        else:
            if a.shape != t.shape or a.dtype != t.dtype:
                raise CheckpointError(f"checkpoint file {where}: state array {i} is "
                                      f"{a.dtype}{list(a.shape)}, expected "
                                      f"{t.dtype}{list(t.shape)}")
            x = a
        out.append(x)
    return jax.tree.unflatten(treedef, out)


class CampaignCheckpoint:
    """The checkpoint folder of one campaign (``RUN_DIR/checkpoint``).

    ``fingerprint`` identifies the configuration (resolved config and plan); a checkpoint
    written under another fingerprint is refused.
    """

    def __init__(self, folder: Path, fingerprint: dict[str, Any]):
        self.folder = Path(folder)
        self.fingerprint = fingerprint

    @property
    def state_path(self) -> Path:
        return self.folder / "state.json"

    def exists(self) -> bool:
        return self.state_path.exists()

    def evaluations_done(self) -> int:
        """Evaluations committed so far (0 without a checkpoint)."""
        return int(read_json(self.state_path)["evaluations_done"]) if self.exists() else 0

    def load(self, template) -> tuple[Any, list[dict[str, np.ndarray]]]:
        """``(carry, records of the chunks done)``; ``(None, [])`` when nothing is saved."""
        if not self.exists():
            return None, []
        st = read_json(self.state_path)
        if st.get("fingerprint") != self.fingerprint:
            raise CheckpointError(f"checkpoint {self.state_path} was written by another "
                                  "configuration (config.toml changed?)")
        n = st.get("chunks_done")
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise CheckpointError(f"checkpoint {self.state_path}: bad chunks_done {n!r}")
        carry_path = self.folder / f"carry-{n:06d}.npz"
        carry = restore_carry(load_npz(carry_path), template, carry_path)
        # the records' fields and shapes are checked against the plan by campaign.restore
        records = [load_npz(self.folder / f"records-{c:06d}.npz") for c in range(n)]
        return carry, records

    def save(self, chunk: int, carry, record: dict[str, np.ndarray],
             evaluations_done: int) -> None:
        """Commit chunk ``chunk`` (0-based): its records, the carry after it, then state."""
        self.folder.mkdir(parents=True, exist_ok=True)
        save_npz(self.folder / f"records-{chunk:06d}.npz", record)
        save_npz(self.folder / f"carry-{chunk + 1:06d}.npz", carry_arrays(carry))
        write_json(self.state_path, {"format": FORMAT, "chunks_done": chunk + 1,
                                     "evaluations_done": evaluations_done,
                                     "fingerprint": self.fingerprint})
        (self.folder / f"carry-{chunk:06d}.npz").unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


# ----------------------------------------------------------------------------- folders
class FolderError(ValueError):
    """An output folder that cannot be used as asked (one line naming it and what to do)."""


RESULT_FILES = {
    "run": ("episodes.parquet", "summary.json", "critical.csv", "timing.json", "report.md",
            "best.rrd"),
    "sweep": ("sweep.parquet", "summary.json", "timing.json"),
    "compare": ("compare.json", "compare.md", "timing.json"),
}
FINISHED = {"run": "summary.json", "sweep": "summary.json", "compare": "compare.json"}


def folder_kind(out: Path) -> str | None:
    """``run``, ``sweep`` or ``compare`` from the folder's ``config.toml`` (None if absent);
    a FolderError if that file cannot be read."""
    from jaxfalsify.config import read_toml

    path = Path(out) / "config.toml"
    if not path.exists():
        return None
    try:
        kind = read_toml(path).get("kind")
    except ValueError as e:
        raise FolderError(str(e)) from None
    if kind not in RESULT_FILES:
        raise FolderError(f"{path}: not a jaxfalsify run, sweep or compare (kind = {kind!r})")
    return kind


def unfinished(out: Path) -> bool:
    out = Path(out)
    return (out / "status.json").exists() or any(out.glob("checkpoint*"))


def check_out(out: Path, kind: str, *, force: bool = False, resume: bool = False) -> None:
    """Refuse an output folder that is a file, holds another kind of result, holds finished
    results (without ``force``) or unfinished ones (without ``resume`` or ``force``), or cannot
    be written (probed by creating and removing a temporary file, so it holds for root too).
    Raises :class:`FolderError`."""
    out = Path(out)
    flag = f"--resume {out}" if resume else f"--out {out}"
    if out.exists() and not out.is_dir():
        raise FolderError(f"{flag} exists and is not a folder")
    have = folder_kind(out)
    if resume:
        if have is None:
            raise FolderError(f"--resume {out}: no config.toml there (not a {kind} folder)")
        if have != kind:
            raise FolderError(f"--resume {out}: that folder holds a {have}, not a {kind}")
        if (out / FINISHED[kind]).exists():
            raise FolderError(f"--resume {out}: the {kind} is already complete "
                              f"({FINISHED[kind]})")
    else:
        if have is not None and have != kind:
            raise FolderError(f"--out {out} holds a {have}; a {kind} is never written into it "
                              "(choose another folder)")
        if (out / FINISHED[kind]).exists() and not force:
            raise FolderError(f"--out {out} already holds {FINISHED[kind]}; pass --force to "
                              "overwrite")
        if kind != "compare" and unfinished(out) and not force:
            raise FolderError(f"--out {out} holds an unfinished {kind}; pass --resume {out} to "
                              "continue it or --force to start over")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    if not parent.is_dir():
        raise FolderError(f"{flag}: {parent} is not a folder")
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise FolderError(f"{flag}: cannot write in {parent} ({e.strerror})") from None


def clear(out: Path, kind: str) -> None:
    """Remove a folder's earlier results, status and checkpoints (``--force``)."""
    out = Path(out)
    for name in RESULT_FILES[kind] + ("status.json", "config.toml"):
        (out / name).unlink(missing_ok=True)
    for p in list(out.glob("checkpoint*")) + [out / "figures"]:
        shutil.rmtree(p, ignore_errors=True)
    for p in out.glob("sweep.part-*.parquet"):
        p.unlink(missing_ok=True)


def write_status(out: Path, kind: str, state: str, **extra) -> None:
    """``status.json``: ``running``, ``interrupted`` or ``complete``, and how to resume."""
    doc = {"state": state, **extra}
    if state != "complete":
        doc["resume"] = f"jaxfalsify {kind} --resume {out}"
    write_json(Path(out) / "status.json", doc, indent=2)


def check_out_plain(out: Path, marker: str, force: bool) -> None:
    """An output folder for files that are not a run, sweep or compare (exports): refuse a
    file in the way, a result folder, existing output without ``force``, or no write access."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise FolderError(f"--out {out} exists and is not a folder")
    if folder_kind(out) is not None:
        raise FolderError(f"--out {out} holds a {folder_kind(out)}; choose another folder")
    if (out / marker).exists() and not force:
        raise FolderError(f"--out {out} already holds {marker}; pass --force to overwrite")
    parent = out if out.exists() else next((a for a in out.parents if a.exists()), Path("."))
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError as e:
        raise FolderError(f"--out {out}: cannot write in {parent} ({e.strerror})") from None
