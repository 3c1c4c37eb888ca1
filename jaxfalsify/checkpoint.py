"""Checkpoints of long work: a campaign's carry and records, a sweep's progress.

A checkpoint is a folder written only through atomic renames, in an order that keeps it
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


def write_json(path: Path, doc: dict) -> None:
    from jaxfalsify.config import write_atomic

    write_atomic(path, json.dumps(doc, indent=1) + "\n")


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
