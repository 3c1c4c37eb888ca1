"""A sweep in memory: every scenario's outcome as arrays (:func:`sweep_arrays`), and the
ground truth that searches are measured against (:func:`ground_truth`), kept per (space, SUT)
pair in the per-user cache, so figures and comparisons sweep a space once per machine.
"""

from __future__ import annotations

import zipfile

import jax
import numpy as np

from jaxfalsify.core import requirements, sim
from jaxfalsify.engine.sweep_chunks import DEFAULT_CHUNK, iter_sweep, violated_fn
from jaxfalsify.engine.sweep_config import calibrations
from jaxfalsify.io import cache
from jaxfalsify.io.files import save_npz
from jaxfalsify.scenario.space import Space
from jaxfalsify.suts import registry as sut_lib

__all__ = ["sweep_arrays", "TRUTH_FIELDS", "ground_truth"]


def sweep_arrays(space: Space, sut="carla-tm", sut_params=None, world: sim.World = sim.WORLD,
                 chunk: int = DEFAULT_CHUNK, fields=None) -> dict[str, np.ndarray]:
    """The whole sweep in memory (small spaces, tests, ground truth): ``fields`` (default
    all columns) ``(N,)`` in scenario order. ``sut_params`` as in
    :func:`jaxfalsify.engine.sweep_config.calibrations`."""
    s = sut_lib.resolve(sut)
    calib = calibrations(s, sut_params or {})
    parts = []
    for _, _, cols in iter_sweep(space, calib, world, chunk):
        parts.append({k: v for k, v in cols.items() if fields is None or k in fields})
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


TRUTH_FIELDS = ("collision", "reward", "nonfinite")


def _violation_truth(space: Space, s, sut_params, world, req, req_params) -> dict:
    """:func:`ground_truth`'s arrays with ``collision`` the requirement's violations, chunk by
    chunk (only the three arrays are kept)."""
    calib = calibrations(s, sut_params or {})
    violated = violated_fn(req)
    parts: dict[str, list] = {k: [] for k in TRUTH_FIELDS}
    for _, _, cols in iter_sweep(space, calib, world, DEFAULT_CHUNK):
        parts["collision"].append(violated(cols, req_params))
        parts["reward"].append(np.asarray(cols["reward"]))
        parts["nonfinite"].append(np.asarray(cols["nonfinite"], bool))
    return {k: np.concatenate(v) for k, v in parts.items()}


def ground_truth(space: Space, sut="carla-tm", sut_params=None,
                 world: sim.World = sim.WORLD, requirement=None,
                 requirement_params=None) -> dict[str, np.ndarray]:
    """``{collision, reward, nonfinite}`` ``(N,)`` of every scenario, from the per-user cache
    (keyed by the space's values, the SUT, its parameters, the world and the simulator's
    source) or swept once and stored there. With a ``requirement`` (a name, an import path
    or a :class:`jaxfalsify.core.requirements.Requirement`; ``requirement_params`` a table of its
    parameters or their pytree), ``collision`` holds its violations instead (robustness < 0 on
    a finite rollout), what a run with that requirement calls critical."""
    import hashlib

    s = sut_lib.resolve(sut)
    params = sut_lib.with_params(s, sut_params)
    code = sut_lib.cache_key(s)  # None (a closure, no source file): never cached
    if requirement is not None:  # a name, an import path or a Requirement; its parameters
        requirement = requirements.resolve(requirement)  # as a table or a pytree
        requirement_params = requirements.with_params(requirement, requirement_params)
        if requirement is requirements.REGISTRY["collision"]:
            requirement = None  # the plain ground truth
    # the space by its parameters in their order (which numbers the scenarios) and the exact
    # float32 values; the code by jaxfalsify's whole source, the SUT's (its module and every
    # user module loaded: helpers), the jax version and the backend (float32 results differ)
    values = hashlib.sha256(b"".join(v.tobytes() for v in space.values)).hexdigest()
    key = cache.key_of({"names": list(space.names), "shape": list(space.shape),
                        "values": values, "sut": code,
                        "params": sut_lib.params_dict(params), "world": repr(world),
                        "code": cache.code_hash(), "jax": jax.__version__,
                        "backend": jax.default_backend(),
                        "prng": str(jax.config.jax_default_prng_impl),
                        **({} if requirement is None else {
                            "requirement": requirements.cache_key(requirement),
                            "requirement_params": sut_lib.params_dict(requirement_params)})})
    path = cache.folder() / "truth" / f"{key}.npz"
    use = cache.enabled() and code is not None and (
        requirement is None or requirements.cache_key(requirement) is not None)
    if use and path.is_file():
        try:
            with np.load(path) as z:
                got = {k: z[k] for k in TRUTH_FIELDS}
                mine = "key" in z.files and str(z["key"]) == key  # an entry of another space
                # or SUT put under this name (each file intact) is swept again, never used
            if mine and all(len(v) == space.size for v in got.values()):
                return got
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            pass  # a damaged entry (a flipped bit fails the zip's CRC) is swept again
        cache.stale(path)
    given = None if params is None else dict(sut_lib.params_dict(params))
    got = (sweep_arrays(space, s, given, world, fields=TRUTH_FIELDS) if requirement is None
           else _violation_truth(space, s, given, world, requirement, requirement_params))
    if use:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            save_npz(path, {**got, "key": np.array(key)})
        except OSError:
            pass
    return got
