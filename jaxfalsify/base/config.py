"""Configuration I/O: resolved configs as TOML, JSON-safe values, package versions, and
``NAME=VALUE`` option lists (``--sut-param``, ``--strategy-param``)."""

from __future__ import annotations

import math
import os
import re
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "versions", "plain", "jsonable", "dumps_toml", "read_toml", "check_keys",
    "parse_number", "parse_assignments", "check_memory", "check_type", "number_text"
]


def versions() -> dict[str, str]:
    """Versions of the packages a result depends on."""
    out = {}
    for pkg in ("jaxfalsify", "jax", "jaxlib", "optax", "evosax", "numpy", "pyarrow"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def plain(x: Any) -> Any:
    """A NumPy scalar as a Python value; a float32 as the shortest decimal that is it."""
    if isinstance(x, np.float32):
        return float(str(x))
    return x.item() if hasattr(x, "item") and not isinstance(x, (str, bytes)) else x


def number_text(x: Any) -> str:
    """A number as an error message shows it: the shortest decimal that reads back as the same
    value (a float32 as float32), without a trailing ``.0`` (``14``, ``14.0000001``, ``0.1``,
    ``1e+30``); never rounded, so a value just outside a range is not shown inside it."""
    if isinstance(x, np.float32):
        s = str(x)
    else:
        try:
            s = repr(float(x))
        except (TypeError, ValueError, OverflowError):
            return repr(x)
    return s[:-2] if s.endswith(".0") else s


def jsonable(x: Any) -> Any:
    """Recursively convert to JSON-safe values: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.float32):  # the shortest decimal that is this float32: 0.2582, not
        x = float(str(x))  # 0.2581999897956848
    elif hasattr(x, "item") and not isinstance(x, (str, bytes)):
        x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _toml_value(v: Any) -> str:
    if isinstance(v, np.ndarray):  # an array as a (nested) list of its elements
        if v.ndim == 0:
            return _toml_value(v[()])
        return "[" + ", ".join(_toml_value(e) for e in v) + "]"
    if isinstance(v, np.generic):  # np.float64 is a float whose repr is 'np.float64(1.2)'
        v = plain(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write non-finite number {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(e) for e in v) + "]"
    raise ValueError(f"cannot write {type(v).__name__} to TOML")


def _toml_key(k: str) -> str:
    """A bare key where TOML allows one, else a quoted key (``"sut.ttc_full"``)."""
    k = str(k)
    return k if k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k) \
        else _toml_value(k)


def dumps_toml(doc: dict[str, Any], _prefix: str = "") -> str:
    """Minimal TOML writer for nested dicts of scalars and lists (what our configs hold)."""
    lines, tables = [], []
    for k, v in doc.items():
        if isinstance(v, dict):
            tables.append((k, v))
        elif v is not None:
            try:
                lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
            except ValueError as e:  # name the key
                raise ValueError(f"{_prefix}{k}: {e}") from None
    out = "\n".join(lines)
    for k, v in tables:
        name = f"{_prefix}{_toml_key(k)}"
        body = dumps_toml(v, name + ".")
        out = out.rstrip("\n") + ("\n\n" if out else "") + f"[{name}]\n" + body
    return out + ("\n" if out and not out.endswith("\n") else "")


MAX_TOML_BYTES = 64 << 20  # configs and spaces are a few kB; a guard against naming a data
# file (a Parquet file, a recording) by mistake, well above any TOML a person writes, comments
# included


def read_text_file(path: Path, what: str = "", limit: int = MAX_TOML_BYTES) -> str:
    """A small UTF-8 text file: regular files only (no folders, FIFOs or devices), at most
    ``limit`` bytes. One-line ValueError naming the file on any problem."""
    import stat

    path = Path(path)
    label = f"{what} {path}".strip()
    try:
        st = path.stat()
    except FileNotFoundError:
        raise ValueError(f"{label}: no such file") from None
    except OSError as e:
        raise ValueError(f"{label}: cannot read ({e.strerror})") from None
    if stat.S_ISDIR(st.st_mode):
        raise ValueError(f"{label}: is a folder, not a file")
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{label}: not a regular file")
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)
    except OSError as e:
        raise ValueError(f"{label}: cannot read ({e.strerror})") from None
    if len(data) > limit:
        raise ValueError(f"{label}: larger than {limit >> 20} MiB, the most a config, space or "
                         f"suite file may hold (a data file named by mistake?)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"{label}: not UTF-8 text") from None


def read_toml(path: Path, what: str = "") -> dict[str, Any]:
    """Parse a TOML file (see :func:`read_text_file`); one-line ValueError naming the file."""
    import tomllib

    text = read_text_file(path, what)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: malformed TOML: {str(e).splitlines()[0]}") from None
    except RecursionError:
        raise ValueError(f"{path}: malformed TOML: nested too deeply") from None


def check_keys(doc, allowed, where: str) -> None:
    """One-line ValueError naming the first key of ``doc`` not in ``allowed``."""
    unknown = set(doc) - set(allowed)
    if unknown:
        raise ValueError(f"{where}: unknown key '{sorted(unknown)[0]}' "
                         f"(allowed: {', '.join(sorted(allowed))})")


# a decimal number as a user types it: ASCII digits, no '_' separators (Python's float() and
# int() also read '1_0' and other scripts' digits, such as '٣'), or inf / nan (refused later
# by name)
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?"
                      r"|[+-]?(?:inf|infinity|nan)", re.IGNORECASE)


def parse_number(text: str) -> int | float | None:
    """``text`` (surrounding spaces ignored) as a number, an int when it is whole digits; None
    when it is not a decimal number written with ASCII digits."""
    t = text.strip()
    if not _DECIMAL.fullmatch(t):
        return None
    return int(t) if re.fullmatch(r"[+-]?[0-9]+", t) else float(t)


def parse_assignments(items: list[str] | None, flag: str, many: bool = False
                      ) -> dict[str, Any]:
    """``["NAME=VALUE", ...]`` -> ``{name: value}``: numbers where they parse (a list of them
    for ``NAME=V1,V2,...`` when ``many``), else the text. One-line ValueError naming the flag."""
    out: dict[str, Any] = {}
    for item in items or []:
        name, eq, text = item.partition("=")
        name = name.strip()
        if not eq or not name or not text.strip():
            raise ValueError(f"{flag} {item!r}: expected NAME=VALUE")
        if name in out:
            raise ValueError(f"{flag} {name} given twice")
        parts = [t.strip() for t in text.split(",")] if many else [text.strip()]
        vals = []
        for t in parts:
            v: Any = parse_number(t)
            if v is None:
                if len(parts) > 1:
                    raise ValueError(f"{flag} {name}={text!r}: {t!r} is not a number")
                v = t
            if isinstance(v, float) and not math.isfinite(v):
                raise ValueError(f"{flag} {name}={t}: not a finite number")
            vals.append(v)
        if many and len(vals) > 1 and len(set(vals)) != len(vals):
            raise ValueError(f"{flag} {name}={text}: repeated values")
        out[name] = vals if many and len(vals) > 1 else vals[0]
    return out


def available_memory() -> int:
    """Bytes of memory available to this process (``MemAvailable``; total memory elsewhere)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return 1 << 40


def check_memory(need: float, what: str, fix: str, share: float = 0.5) -> None:
    """ValueError (one line) when ``need`` bytes exceed ``share`` of the available memory,
    before anything is allocated."""
    have = available_memory()
    if need > share * have:
        raise ValueError(f"{what} needs about {need / 2**30:.1f} GiB, more than "
                         f"{share:.0%} of the {have / 2**30:.1f} GiB available; {fix}")


def check_type(value, cls: type, name: str) -> None:
    """One-line ValueError unless ``value`` is a ``cls`` (library entry points' arguments)."""
    if not isinstance(value, cls):
        raise ValueError(f"{name} must be a {cls.__module__.split('.')[-1]}.{cls.__name__} "
                         f"(got {type(value).__name__})")
