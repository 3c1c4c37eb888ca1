"""Per-user caches: JAX's persistent compilation cache, and ground-truth sweeps for figures.

Both live under one folder: ``$JAXFALSIFY_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxfalsify``,
else ``~/.cache/jaxfalsify``. ``JAXFALSIFY_NO_CACHE=1`` (or ``jaxfalsify --no-cache``) turns
both off. If ``JAX_COMPILATION_CACHE_DIR`` is set, JAX's own setting is respected and the
compilation cache goes there.

The compilation cache keys on the compiled program (its HLO), the jax/jaxlib versions and the
backend, so a stale entry cannot be used by mistake; space values, SUT and strategy
parameters are traced arguments, so another space seed or calibration hits the same entry.

Every entry carries what it was built from: an exported program's seal is the SHA-256 of its
key and its bytes, a ground truth stores its key beside its arrays. An entry that fails the
check (damaged, or another configuration's file put under this name) is rebuilt, never used.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import sys
from pathlib import Path

from jaxfalsify.io.files import write_atomic

__all__ = [
    "enabled", "folder", "enable_compilation_cache", "program_settings", "check_settings",
    "check_backend", "backend_error",
    "check_xla_flags", "check_no_cache_setting", "key_of", "PACKAGE", "package_files",
    "code_hash", "user_code_hash",
    "source_hash", "stale", "Program", "exported_jit"
]

MIN_COMPILE_SECONDS = 0.1  # cache every compilation longer than this


NO_CACHE_OFF = ("", "0", "false", "no")  # JAXFALSIFY_NO_CACHE values that keep the cache
NO_CACHE_ON = ("1", "true", "yes")  # ... and those that turn it off


def enabled() -> bool:
    return os.environ.get("JAXFALSIFY_NO_CACHE", "").strip().lower() in NO_CACHE_OFF


def check_no_cache_setting() -> None:
    """One-line ValueError for a ``JAXFALSIFY_NO_CACHE`` that is neither on nor off (any value
    but the off ones turns the cache off: ``maybe`` would, silently)."""
    v = os.environ.get("JAXFALSIFY_NO_CACHE", "")
    if v.strip().lower() not in NO_CACHE_OFF + NO_CACHE_ON:
        raise ValueError(f"JAXFALSIFY_NO_CACHE={v!r}: use 1 (no cache) or 0 (the cache)")


def folder() -> Path:
    env = os.environ.get("JAXFALSIFY_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "jaxfalsify"


_ENABLED_AT: str | None = None


def enable_compilation_cache() -> str | None:
    """Point JAX's persistent compilation cache at the per-user folder (idempotent); returns
    the folder in use, or None when caching is off or the folder cannot be created."""
    global _ENABLED_AT
    import jax

    if not enabled():
        if _ENABLED_AT is not None:
            jax.config.update("jax_enable_compilation_cache", False)
            _ENABLED_AT = None
        return None
    path = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(folder() / "jax")
    if _ENABLED_AT == path:
        return path
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_enable_compilation_cache", True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    _ENABLED_AT = path
    return path


# JAX settings that change what a traced program computes (random draws, dtypes, matmul
# precision, key layout): every cached program and ground truth is keyed by them, and a
# run's checkpoint fingerprint holds them (a resume under other settings is refused)
TRACING_SETTINGS = ("jax_threefry_partitionable", "jax_enable_x64",
                    "jax_default_matmul_precision", "jax_default_prng_impl",
                    "jax_numpy_dtype_promotion")

X64_ERROR = ("jaxfalsify runs in float32: unset JAX_ENABLE_X64 (jax_enable_x64 is on; "
             "jaxfalsify's programs assume 32-bit integers and floats)")


def program_settings() -> dict[str, str]:
    """The current values of :data:`TRACING_SETTINGS` (as strings)."""
    import jax

    return {n: str(getattr(jax.config, n, None)) for n in TRACING_SETTINGS}


def check_settings() -> None:
    """ValueError (one line) if JAX is set up in a way jaxfalsify does not support: 64-bit
    mode (``JAX_ENABLE_X64``; every program and result is float32/int32)."""
    import jax

    if getattr(jax.config, "jax_enable_x64", False):
        raise ValueError(X64_ERROR)


def check_backend() -> None:
    """ValueError (one line) if JAX's backend cannot start (e.g. ``JAX_PLATFORMS`` naming a
    platform this machine lacks): called before a job's folder is touched. It starts the
    backend, so not where ``jax.distributed.initialize`` must come first."""
    import jax

    try:
        jax.devices()
    except RuntimeError as e:
        raise ValueError(backend_error(e)) from None


def backend_error(e: BaseException) -> str:
    """One line for JAX's error when its backend cannot start, naming ``JAX_PLATFORMS``."""
    return (f"JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS', '')!r}: "
            f"{str(e).splitlines()[0][:200] if str(e) else type(e).__name__}")


def check_xla_flags() -> None:
    """Refuse (ValueError, one line) an ``XLA_FLAGS`` that XLA would end the process for (an
    unknown flag is a fatal error inside XLA, which no Python code can catch): the flags are
    tried once in a short child process, and a setting that passed is remembered in the cache
    (keyed by the flags and the jaxlib version), so only a new setting costs that second."""
    flags = os.environ.get("XLA_FLAGS", "").strip()
    if not flags:
        return
    import subprocess

    import jaxlib

    mark = folder() / "xla_flags" / hashlib.sha256(
        f"{jaxlib.__version__}\n{flags}".encode()).hexdigest()[:32] if enabled() else None
    if mark is not None and mark.is_file():
        return
    probe = subprocess.run([sys.executable, "-c", "import jax; jax.devices('cpu')"],
                           env={**os.environ, "JAX_PLATFORMS": "cpu"},
                           capture_output=True, text=True, timeout=300)
    if probe.returncode != 0:
        said = [ln for ln in probe.stderr.splitlines() if "XLA_FLAGS" in ln or "flag" in ln]
        why = (said or probe.stderr.strip().splitlines()[-1:] or ["XLA refused them"])[-1]
        why = why.split("] ", 1)[-1].strip()  # without the log line's prefix
        raise ValueError(f"XLA_FLAGS={flags!r}: {why[:200]} (set in the environment: fix or "
                         "unset it)")
    if mark is not None:
        try:
            mark.parent.mkdir(parents=True, exist_ok=True)
            mark.write_text(flags + "\n")
        except OSError:
            pass


def key_of(doc) -> str:
    """A stable content hash of a JSON-able description (cache file names), and of the JAX
    settings that change traced programs (:func:`program_settings`): a program or ground
    truth cached under other settings is never reused."""
    doc = {"doc": doc, "jax_settings": program_settings()}
    text = json.dumps(doc, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:24]


# ----------------------------------------------------------------------------- exported programs
_CODE_HASH: str | None = None


PACKAGE = Path(__file__).resolve().parents[1]  # the jaxfalsify folder (this file: io/cache.py)


def package_files() -> list[Path]:
    """Every source file of jaxfalsify, sorted: what :func:`code_hash` covers."""
    return sorted(PACKAGE.rglob("*.py"))


def code_hash() -> str:
    """Hash of jaxfalsify's own source (memoised): a program exported by other code is never
    reused."""
    global _CODE_HASH
    if _CODE_HASH is None:
        h = hashlib.sha256()
        for f in package_files():
            h.update(f.relative_to(PACKAGE).as_posix().encode())
            h.update(f.read_bytes())
        _CODE_HASH = h.hexdigest()[:16]
    return _CODE_HASH


@functools.lru_cache(maxsize=1)
def _installed_roots() -> tuple[str, ...]:
    """Folders of the Python installation (standard library, site-packages) and of
    jaxfalsify itself: code there is identified by versions and :func:`code_hash`."""
    import site
    import sys
    import sysconfig

    roots = {sys.prefix, sys.base_prefix, sys.exec_prefix, str(PACKAGE)}
    roots |= {p for k in ("stdlib", "platstdlib", "purelib", "platlib")
              if (p := sysconfig.get_paths().get(k))}
    roots |= set(getattr(site, "getsitepackages", lambda: [])())
    roots.add(getattr(site, "getusersitepackages", lambda: "")() or sys.prefix)
    return tuple(os.path.realpath(r) + os.sep for r in roots if r)


def _user_file(module) -> str | None:
    """A loaded module's source file if it is the user's (outside the Python installation and
    jaxfalsify), resolved; else None."""
    f = getattr(module, "__file__", None)
    if isinstance(f, str) and f.endswith(".py"):
        real = os.path.realpath(f)
        if not real.startswith(_installed_roots()):
            return real
    return None


def user_code_hash(*objs) -> str | None:
    """Hash of the user's code a program may run: the source files of every loaded module
    outside the Python installation and jaxfalsify (a SUT's module and any helper module it
    imports, a strategy's), with the qualified names of ``objs`` (functions or classes). None
    if one of ``objs`` has no source file (nothing to key on: such programs are not cached).
    Conservative: editing any such module gives a new key, never a stale program."""
    import inspect
    import sys

    h = hashlib.sha256()
    for o in objs:
        try:
            src = inspect.getsourcefile(o)
        except (TypeError, OSError):
            return None
        if not src or not Path(src).is_file():  # python -c, a REPL, a notebook cell
            return None
        h.update(f"{o.__module__}.{o.__qualname__}".encode())
    files = {f for m in list(sys.modules.values()) if (f := _user_file(m))}
    for f in sorted(files):
        try:
            data = Path(f).read_bytes()
        except OSError:
            continue
        h.update(f.encode())
        h.update(data)
    return h.hexdigest()[:16]


def _user_module_sources(objs) -> list[bytes]:
    """The source of every user module (outside the Python installation and jaxfalsify) that
    ``objs``' modules reach through their namespaces (an imported module, or a function or
    class imported from one), transitively; ``objs``' own modules excluded."""
    import sys
    import types

    start = [sys.modules.get(getattr(o, "__module__", None) or "") for o in objs]
    todo = [m for m in start if m is not None]
    seen = {id(m) for m in todo}
    found: dict[str, bytes] = {}
    while todo:
        m = todo.pop()
        for v in list(vars(m).values()):
            try:
                name = None if isinstance(v, types.ModuleType) else getattr(v, "__module__", None)
            except Exception:  # noqa: BLE001 - an object whose attributes raise
                continue
            dep = v if isinstance(v, types.ModuleType) else \
                sys.modules.get(name if isinstance(name, str) else "")
            f = None if dep is None or id(dep) in seen else _user_file(dep)
            if f is None:
                continue
            seen.add(id(dep))
            todo.append(dep)
            try:
                found[f] = Path(f).read_bytes()
            except OSError:
                pass
    own = {_user_file(m) for m in start if m is not None}
    return [data for f, data in found.items() if f not in own]


def source_hash(*objs) -> str:
    """Hash of jaxfalsify's source and of the files defining ``objs`` (a user's SUT
    functions, a strategy class; their qualified names too, not their folders), for a
    checkpoint's fingerprint: a
    run or sweep resumed after that code changed is refused instead of joining two versions'
    results. Objects without a source file count by their qualified names only."""
    import inspect

    h = hashlib.sha256(code_hash().encode())
    for o in objs:  # (not the module's name: a SUT loaded from a file path is named after
        # the path, which moves with the project folder while its bytes stay)
        h.update(str(getattr(o, "__qualname__", "")).encode())
        try:
            f = inspect.getsourcefile(o)
            if f and not os.path.realpath(f).startswith(_installed_roots()):
                h.update(Path(f).read_bytes())
        except (TypeError, OSError):
            pass
    # and the user modules they use (a helper the SUT imports, and what that imports), by
    # their bytes alone, so a moved project still resumes
    for data in sorted(hashlib.sha256(d).digest() for d in _user_module_sources(objs)):
        h.update(data)
    return h.hexdigest()[:16]


def stale(path: Path) -> None:
    """Say (one line on stderr) that the cache entry ``path`` was not used: it is damaged or
    holds another configuration's entry, and is being rebuilt."""
    print(f"jaxfalsify: cache entry {path} is damaged or was built for another configuration;"
          " rebuilding it", file=sys.stderr, flush=True)


class Program:
    """A compiled program: ``call(*args)`` and the shapes/dtypes of its arguments
    (``in_avals``, a pytree like the arguments)."""

    def __init__(self, call, in_avals):
        self.call = call
        self.in_avals = in_avals

    def __call__(self, *args):
        return self.call(*args)


SEAL = b"jaxfalsify-export-1\n"  # an exported program's file: SEAL, SHA-256 of the rest, rest


def exported_jit(fn, name: str, static: dict | None, key_args: tuple, example_args):
    """``jax.jit(fn)`` whose lowered program is kept in the per-user cache with
    ``jax.export``: a later process deserialises it (milliseconds) instead of tracing and
    lowering ``fn`` again (seconds), and XLA's persistent cache supplies the executable.

    ``fn``'s arguments and results must be standard containers (lists, tuples, dicts) of
    arrays. The program is keyed by ``static`` (everything else ``fn`` depends on: its
    configuration), the shapes and dtypes of ``key_args`` (the arguments that determine all
    others' shapes), jaxfalsify's code, the jax version, the backend and the JAX settings
    that change tracing (:func:`program_settings`, through :func:`key_of`); ``example_args()``
    builds the full example arguments only when the program must be exported. Falls back to
    plain ``jax.jit`` when caching is off, ``static`` is None (e.g. a SUT without a source
    file), on several devices, or if the program cannot be exported.
    """
    import jax

    check_settings()  # (a 64-bit program fails to trace, or silently computes otherwise)

    def plain():
        ex = example_args()
        return Program(jax.jit(fn), jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), ex))

    if static is None or not enabled() or jax.local_device_count() > 1:
        return plain()
    leaves, tree = jax.tree.flatten(key_args)
    key = key_of({"name": name, "static": static, "tree": str(tree),
                  "avals": [(tuple(x.shape), str(x.dtype)) for x in leaves],
                  "code": code_hash(), "jax": jax.__version__,
                  "backend": jax.default_backend(),
                  "prng": str(jax.config.jax_default_prng_impl)})  # key data's shape
    path = folder() / "exports" / f"{name}-{key}.bin"
    from jax import export

    exp = None
    if path.is_file():
        try:
            blob = path.read_bytes()
            data = blob[len(SEAL) + 32:]
            # the seal covers the key too: an entry of another configuration put under this
            # name (each file intact) fails it like a damaged one, and is rebuilt
            if blob[:len(SEAL)] == SEAL and blob[len(SEAL):len(SEAL) + 32] == \
                    hashlib.sha256(key.encode() + data).digest():
                exp = export.deserialize(bytearray(data))
        except Exception:  # noqa: BLE001 - a damaged cache entry is rebuilt
            exp = None
        if exp is None:
            stale(path)
    if exp is None:
        try:
            exp = export.export(jax.jit(fn))(*example_args())
            data = exp.serialize()
        except Exception:  # noqa: BLE001 - not exportable: compile it directly
            return plain()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            data = bytes(data)
            write_atomic(path, SEAL + hashlib.sha256(key.encode() + data).digest() + data)
        except OSError:
            pass
    avals = jax.tree.unflatten(exp.in_tree, list(exp.in_avals))[0]
    return Program(jax.jit(exp.call), avals)
