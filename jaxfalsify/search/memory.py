"""What a search remembers of the scenarios it evaluated: 32-bit hashes of them
(:class:`NoRepeats`, so a deterministic SUT is not asked the same scenario twice) and the best
distinct ones (:func:`top_distinct`). Pieces :mod:`jaxfalsify.search.reinforce_ar` is composed
of; pure functions over their own state, usable by any strategy."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jaxfalsify.base import pytree

__all__ = ["scenario_hash", "equals_an_earlier", "top_distinct", "MemoryState", "NoRepeats"]


def scenario_hash(indices: jax.Array) -> jax.Array:
    """A 32-bit hash ``(...)`` uint32 of index vectors ``(..., P)`` (FNV-1a over the indices;
    two distinct scenarios share a hash with probability ~2^-32, which at worst makes a new
    scenario look evaluated)."""
    h = jnp.full(indices.shape[:-1], 2166136261, jnp.uint32)
    for p in range(indices.shape[-1]):
        h = (h ^ indices[..., p].astype(jnp.uint32)) * jnp.uint32(16777619)
    return h


def equals_an_earlier(eq: jax.Array) -> jax.Array:
    """``(n,)`` bool from pairwise equality ``eq (n, n)``: item i equals some item j < i."""
    return jnp.any(eq & jnp.tril(jnp.ones(eq.shape, bool), -1), axis=-1)


def top_distinct(indices: jax.Array, signal: jax.Array, k: int, hit: jax.Array | None = None):
    """The ``k`` best distinct rows of ``indices (N, P)`` by ``signal (N,)`` (best first; a
    row seen twice counts once; ``-inf`` rows last): ``(indices (k, P), signal (k,))``, and
    their entries of ``hit (N,)`` (collided) as a third element when it is given."""
    order = jnp.argsort(-signal, stable=True)
    idx, sig = indices[order], signal[order]
    same = jnp.all(idx[:, None, :] == idx[None, :, :], axis=-1)
    earlier = jnp.tril(same, k=-1)  # an equal row earlier in the order (better or equal)
    sig = jnp.where(jnp.any(earlier, axis=-1), -jnp.inf, sig)
    second = jnp.argsort(-sig, stable=True)[:k]
    if hit is None:
        return idx[second], sig[second]
    return idx[second], sig[second], hit[order][second] & jnp.isfinite(sig[second])


@pytree.dataclass
class MemoryState:
    hashes: jax.Array  # (M,) uint32, hashes of the evaluated scenarios (a ring buffer)
    written: jax.Array  # () int32, hashes written so far (slot = written % M)


@dataclasses.dataclass(frozen=True)
class NoRepeats:
    """The last ``size`` evaluated scenarios, as hashes in a ring buffer: :meth:`evaluated`
    tells which candidates were evaluated before, :meth:`remember` adds the asked ones."""

    size: int

    def init(self) -> MemoryState:
        return MemoryState(jnp.zeros(self.size, jnp.uint32), jnp.int32(0))

    def evaluated(self, st: MemoryState, h: jax.Array) -> jax.Array:
        """``h (N,)`` uint32 -> ``(N,)`` bool: among the remembered hashes."""
        filled = jnp.arange(self.size) < st.written
        return jnp.any((h[:, None] == st.hashes[None, :]) & filled[None, :], axis=-1)

    def remember(self, st: MemoryState, h: jax.Array) -> MemoryState:
        """Write hashes ``h (B,)`` into the ring buffer."""
        slots = (st.written + jnp.arange(h.shape[0])) % self.size
        return MemoryState(st.hashes.at[slots].set(h),
                           jnp.minimum(st.written + h.shape[0], 2**30))
