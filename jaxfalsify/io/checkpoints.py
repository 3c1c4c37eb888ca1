"""Checkpoints of long work (a campaign's carry and records, a sweep's rows and totals), written
in an order that keeps them consistent whatever moment the process dies (SIGKILL included):

1. the new chunk's data (``records-<c>.npz`` or ``rows-<c>.parquet``), atomically;
2. for campaigns, the carry after chunk ``c`` (``carry-<c+1>.npz``), the same way;
3. ``state.json``, the *commit record*: how many chunks are done, the configuration's
   fingerprint, and for every file of the checkpoint its SHA-256 and its identity (chunk index,
   what it holds), sealed by a SHA-256 of the record itself. Files past the commit point are
   ignored (and rewritten, identically, when the work resumes).

Resuming verifies the seal, the fingerprint and every file's hash and identity: a truncated,
bit-flipped, swapped, copied or foreign file, or an edited record, is refused with one line
naming the file (:class:`CheckpointError`), never used. The carry is the campaign's flat list of
state arrays (PRNG keys as key data), checked leaf by leaf against the shapes and dtypes the
configuration's program expects.
"""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from jaxfalsify.base.config import jsonable
from jaxfalsify.io.files import save_npz, sha256, write_atomic

__all__ = [
    "CheckpointError", "read_verified", "write_commit", "read_json", "identity",
    "check_checkpoint_folder", "CampaignCheckpoint"
]

FORMAT = 2


class CheckpointError(ValueError):
    """A checkpoint that cannot be used (corrupt, missing files, another configuration)."""


def read_verified(path: Path, expected: dict | None) -> bytes:
    """A checkpoint file's bytes, checked against its entry in the commit record."""
    path = Path(path)
    if expected is None:
        raise CheckpointError(f"checkpoint file {path} is not in the commit record "
                              "(state.json damaged or edited)")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint file {path} is missing") from None
    except OSError as e:
        raise CheckpointError(f"checkpoint file {path} cannot be read ({e.strerror})") from None
    if sha256(data) != expected.get("sha256"):
        raise CheckpointError(f"checkpoint file {path} does not match its commit record "
                              "(damaged, swapped, or from another run)")
    return data


def load_npz_bytes(data: bytes, where: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise CheckpointError(f"checkpoint file {where} is corrupt ({type(e).__name__})") from None


def load_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        return load_npz_bytes(Path(path).read_bytes(), path)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint file {path} is missing") from None


def _seal(doc: dict) -> str:
    body = {k: v for k, v in doc.items() if k != "sha256"}
    return sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())


def write_commit(path: Path, doc: dict) -> None:
    """A commit record (``state.json``) sealed with the SHA-256 of its content."""

    doc = jsonable({**doc, "format": FORMAT})
    doc["sha256"] = _seal(doc)
    write_atomic(path, json.dumps(doc, indent=1) + "\n")


def read_json(path: Path) -> dict:
    """A checkpoint's commit record, its seal verified."""
    try:
        doc = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint file {path} is missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:
        raise CheckpointError(f"checkpoint file {path} is corrupt ({type(e).__name__})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint file {path} is not a jaxfalsify checkpoint "
                              f"(format {FORMAT})")
    if doc.get("sha256") != _seal(doc):
        raise CheckpointError(f"checkpoint file {path} was edited or damaged (its seal does "
                              "not match)")
    return doc


def restore_leaves(arrays: dict[str, np.ndarray], template: list, where: Path) -> list:
    """A carry's leaves from :func:`save_npz` of ``leaf_0000...``, checked against
    ``template`` (shapes and dtypes of the leaves)."""
    if len(arrays) != len(template):
        raise CheckpointError(f"checkpoint file {where} holds {len(arrays)} arrays, this "
                              f"configuration's state has {len(template)}")
    out = []
    for i, t in enumerate(template):
        a = arrays.get(f"leaf_{i:04d}")
        if a is None:
            raise CheckpointError(f"checkpoint file {where} lacks state array {i}")
        if a.shape != tuple(t.shape) or a.dtype != t.dtype:
            raise CheckpointError(f"checkpoint file {where}: state array {i} is "
                                  f"{a.dtype}{list(a.shape)}, expected {t.dtype}{list(t.shape)}")
        out.append(a)
    return out


def identity(fingerprint: Any) -> str:
    """A short hash of a configuration fingerprint (stored beside every file's entry)."""
    return sha256(json.dumps(fingerprint, sort_keys=True).encode())[:16]


def check_checkpoint_folder(folder: Path) -> None:
    """A checkpoint path that exists must be a folder: CheckpointError (one line naming it)
    before anything is written when something else stands there."""
    folder = Path(folder)
    if (folder.exists() or folder.is_symlink()) and not folder.is_dir():
        raise CheckpointError(f"checkpoint {folder} is damaged: not a folder (remove it, and "
                              "start the run again with --force)")


class CampaignCheckpoint:
    """The checkpoint folder of one campaign (``RUN_DIR/checkpoint``).

    ``fingerprint`` identifies the configuration (resolved config, seed and plan); a checkpoint
    written under another fingerprint is refused.
    """

    def __init__(self, folder: Path, fingerprint: Any):
        self.folder = Path(folder)
        self.fingerprint = fingerprint
        self.files: dict[str, dict] = {}

    @property
    def state_path(self) -> Path:
        return self.folder / "state.json"

    def exists(self) -> bool:
        return self.state_path.exists()

    def evaluations_done(self) -> int:
        """Evaluations committed so far (0 without a checkpoint)."""
        return int(read_json(self.state_path)["evaluations_done"]) if self.exists() else 0

    def load(self, template: list) -> tuple[Any, list[dict[str, np.ndarray]]]:
        """``(carry leaves, records of the chunks done)`` verified against the commit record;
        ``(None, [])`` when nothing is saved."""
        if not self.exists():
            return None, []
        st = read_json(self.state_path)
        theirs, ours = st.get("fingerprint"), self.fingerprint
        if isinstance(theirs, dict) and isinstance(ours, dict) and \
                theirs.get("environment") != ours.get("environment") and \
                isinstance(theirs.get("environment"), dict) and \
                isinstance(ours.get("environment"), dict):
            te, oe = theirs["environment"], ours["environment"]
            k = next(k for k in sorted(set(te) | set(oe)) if te.get(k) != oe.get(k))
            raise CheckpointError(f"checkpoint {self.state_path} was written with {k} = "
                                  f"{te.get(k)} (here {oe.get(k)}); resume it with the same "
                                  "JAX settings and devices")
        if theirs != ours:
            raise CheckpointError(f"checkpoint {self.state_path} was written by another "
                                  "configuration or code (config.toml, the SUT's or "
                                  "jaxfalsify's source changed?)")
        n = st.get("chunks_done")
        files = st.get("files")
        if isinstance(n, bool) or not isinstance(n, int) or n < 1 or not isinstance(files, dict):
            raise CheckpointError(f"checkpoint {self.state_path}: bad chunks_done {n!r}")
        ident = identity(self.fingerprint)

        def load(name: str, chunk_key: str, chunk: int) -> dict:
            """A verified npz file of the record whose ``chunk_key`` must be ``chunk``."""
            entry, path = files.get(name), self.folder / name
            if entry is not None and (entry.get(chunk_key) != chunk
                                      or entry.get("run") != ident):
                raise CheckpointError(f"checkpoint file {path}: its record names another "
                                      "chunk or run")
            return load_npz_bytes(read_verified(path, entry), path)

        records = [load(f"records-{c:06d}.npz", "chunk", c) for c in range(n)]
        carry = restore_leaves(load(f"carry-{n:06d}.npz", "after_chunk", n), template,
                               self.folder / f"carry-{n:06d}.npz")
        self.files = {k: v for k, v in files.items() if k.startswith("records-")}
        return carry, records

    def save(self, chunk: int, carry: list, record: dict[str, np.ndarray],
             evaluations_done: int) -> None:
        """Commit chunk ``chunk`` (0-based): its records, the carry after it, then the record."""
        self.folder.mkdir(parents=True, exist_ok=True)
        ident = identity(self.fingerprint)
        rec_name, carry_name = f"records-{chunk:06d}.npz", f"carry-{chunk + 1:06d}.npz"
        self.files = {k: v for k, v in self.files.items() if k.startswith("records-")
                      and int(k[8:14]) < chunk}
        self.files[rec_name] = {"sha256": save_npz(self.folder / rec_name, record),
                                "chunk": chunk, "run": ident}
        leaves = {f"leaf_{i:04d}": np.asarray(x) for i, x in enumerate(carry)}
        files = {**self.files, carry_name: {"sha256": save_npz(self.folder / carry_name, leaves),
                                            "after_chunk": chunk + 1, "run": ident}}
        write_commit(self.state_path, {"chunks_done": chunk + 1,
                                       "evaluations_done": evaluations_done,
                                       "fingerprint": self.fingerprint, "files": files})
        (self.folder / f"carry-{chunk:06d}.npz").unlink(missing_ok=True)

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
