"""Logical scenario spaces: named parameters with distributions, discretised into concrete values.

One concern: logical scenario spaces and their discretisation
(definition, TOML, index <-> value maps).

A *logical scenario* is a set of parameters with ranges or distributions (the paper's Table I).
Discretising it with a seed draws each parameter's concrete value set once, as the original code
did (draws rounded to 3 decimals, then kept for the whole run). A *concrete scenario* is one value
per parameter, addressed by an integer index vector ``(P,)`` into those value sets. The space is
their Cartesian product, enumerated in C order (the last parameter varies fastest).

A discretised space splits, for compilation, into its :class:`Layout` (parameter names and
value counts: static, fixes shapes) and its value table ``(P, max_n)`` float32 (traced): another
space seed, or other values of the same counts, reuse the compiled code.

Everything here is host-side setup except :class:`Layout`'s methods, which are vectorised jnp
code usable under ``jit``.
"""

from __future__ import annotations

import dataclasses
import math
import zlib
from pathlib import Path
from typing import Any, Iterator

import jax.numpy as jnp
import numpy as np

from jaxfalsify.base.config import check_keys, number_text, read_toml
from jaxfalsify.base.pytree import FLOAT32_MAX
from jaxfalsify.scenario import weather

__all__ = [
    "KNOWN_PARAMETERS", "MAX_SIZE", "SUT_PREFIX", "is_sut_parameter", "decimal_grid",
    "uniform", "Layout", "Space", "space_from_dict", "check_name", "load_space",
    "check_scenario_values", "Parameter", "DISTRIBUTIONS", "BUILTIN", "MAX_SAMPLES",
    "MAX_SEARCH_SIZE", "normal", "integers", "values", "build"
]

# Scenario parameters the simulator understands: unit, default, allowed domain, integer-valued.
# A space need not declare all of them; undeclared ones take the default.
KNOWN_PARAMETERS: dict[str, dict[str, Any]] = {
    "ego_offset": dict(unit="m", default=5.0, domain=(0.0, 50.0), integer=False,
                       doc="how far behind its base start the ego starts"),
    "ped_accel": dict(unit="m/s per step", default=0.0, domain=(0.0, 1.0), integer=False,
                      doc="pedestrian speed increment per 0.1 s step (the original's "
                      "'acceleration')"),
    "ped_speed": dict(unit="m/s", default=1.46, domain=(0.0, 5.0), integer=False,
                      doc="pedestrian nominal walking speed"),
    "ped_offset": dict(unit="m", default=3.5, domain=(0.0, 20.0), integer=False,
                       doc="the pedestrian starts ped_offset + 1 m back (towards the kerb) "
                           "from its base spawn point, which lies 4.5 m (World.walker_base) "
                           "inside the right kerb: 3.5 starts at the kerb"),
    "weather": dict(unit="preset", default=0.0, domain=(0.0, weather.N_PRESETS - 1.0),
                    integer=True, doc="CARLA weather preset index (name-sorted)"),
    "ped_speed_change": dict(unit="m/s", default=0.0, domain=(-3.0, 3.0), integer=False,
                             doc="speed change during a six-step window (extended space)"),
    "ped_change_step": dict(unit="step", default=0.0, domain=(0.0, 299.0), integer=True,
                            doc="first step of the speed-change window (extended space)"),
}

DISTRIBUTIONS = ("uniform", "normal", "integers", "values")
MAX_SAMPLES = 100_000  # concrete values per parameter (search heads cost O(values))
MAX_SIZE = 2**31 - 1  # concrete scenarios a sweep enumerates (int32 scenario numbers)
MAX_SEARCH_SIZE = 10**18  # concrete scenarios a space may have (searched, never enumerated)
SUT_PREFIX = "sut."  # a space parameter named sut.NAME sets the SUT's parameter NAME


def is_sut_parameter(name: str) -> bool:
    """Whether a space parameter is a SUT parameter (``sut.NAME``: a calibration searched or
    swept like a scenario parameter)."""
    return name.startswith(SUT_PREFIX)


def parameter_spec(name: str) -> dict[str, Any]:
    """The spec of a known parameter, or of a SUT parameter (no unit here: the SUT's
    parameter docs give it; any finite value)."""
    if is_sut_parameter(name):
        return dict(unit="", default=None, domain=(-math.inf, math.inf), integer=False,
                    doc=f"the SUT's parameter {name[len(SUT_PREFIX):]}")
    return KNOWN_PARAMETERS[name]


def check_name_known(name: str, key: str) -> None:
    """ValueError unless ``name`` is a known scenario parameter or ``sut.NAME``."""
    if is_sut_parameter(name):
        rest = name[len(SUT_PREFIX):]
        if not rest.isidentifier():
            raise ValueError(f"{key}: {rest!r} is not a SUT parameter name")
        return
    if name not in KNOWN_PARAMETERS:
        raise ValueError(f"{key}: unknown parameter {name!r} "
                         f"(known: {', '.join(KNOWN_PARAMETERS)}, or sut.NAME for a SUT "
                         "parameter)")
_PARAM_KEYS = {"unit", "distribution", "low", "high", "mean", "sd", "samples", "values", "decimals"}
_TOP_KEYS = {"name", "description", "parameters"}


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One logical-scenario parameter.

    Attributes:
      name: a key of ``KNOWN_PARAMETERS``.
      distribution: ``uniform`` (low, high), ``normal`` (mean, sd), ``integers`` (low, high,
        inclusive, drawn without replacement) or ``values`` (explicit list).
      args: the distribution's arguments, or the explicit values.
      samples: how many concrete values to draw.
      decimals: rounding of continuous draws (the original rounds to 3).
    """

    name: str
    distribution: str
    args: tuple[float, ...]
    samples: int
    decimals: int = 3

    @property
    def unit(self) -> str:
        return parameter_spec(self.name)["unit"]

    def discretise(self, seed: int) -> np.ndarray:
        """Concrete value set ``(samples,)`` float64, sorted ascending; deterministic in seed."""
        rng = np.random.default_rng([int(seed), zlib.crc32(self.name.encode())])
        d, a, n = self.distribution, self.args, self.samples
        if d == "values":
            out = np.asarray(a, dtype=np.float64)
        elif d == "uniform":  # rounded draws stay in the declared range (the grid's ends)
            lo, hi = decimal_grid(a[0], a[1], self.decimals)
            out = np.clip(np.round(rng.uniform(a[0], a[1], n), self.decimals), lo, hi)
        elif d == "normal":
            out = np.round(rng.normal(a[0], a[1], n), self.decimals)
        else:  # integers, inclusive, without replacement
            count = int(a[1]) - int(a[0]) + 1
            if count <= 1_000_000:
                out = rng.choice(np.arange(int(a[0]), int(a[1]) + 1), size=n, replace=False)
            else:  # a huge range: draw positions without materialising it
                out = int(a[0]) + rng.choice(count, size=n, replace=False)
            out = out.astype(np.float64)
        return np.sort(out)

    def describe(self) -> dict[str, Any]:
        """TOML-ready description (the inverse of parsing)."""
        d: dict[str, Any] = {"unit": self.unit, "distribution": self.distribution}
        if self.distribution == "values":
            d["values"] = list(self.args)
        else:
            keys = ("mean", "sd") if self.distribution == "normal" else ("low", "high")
            args = [int(a) for a in self.args] if self.distribution == "integers" else self.args
            d.update(zip(keys, args))
            d["samples"] = self.samples
            if self.distribution != "integers":
                d["decimals"] = self.decimals
        return d


def decimal_grid(low: float, high: float, decimals: int) -> tuple[float, float]:
    """The smallest and largest multiple of ``10**-decimals`` in ``[low, high]`` as the floats
    ``np.round(x, decimals)`` gives (exact decimal arithmetic on the shortest repr of each
    bound, so 0.29 counts as a multiple of 0.01); ``low > high`` when there is none."""
    from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

    def snap(x: float, how) -> float:
        k = Decimal(repr(float(x))).scaleb(decimals).to_integral_value(rounding=how)
        return float(k.scaleb(-decimals))

    return snap(low, ROUND_CEILING), snap(high, ROUND_FLOOR)


def uniform(name: str, low: float, high: float, samples: int, decimals: int = 3) -> Parameter:
    return make_parameter(name, "uniform", (low, high), samples, decimals)


def normal(name: str, mean: float, sd: float, samples: int, decimals: int = 3) -> Parameter:
    return make_parameter(name, "normal", (mean, sd), samples, decimals)


def integers(name: str, low: int, high: int, samples: int) -> Parameter:
    return make_parameter(name, "integers", (low, high), samples)


def values(name: str, vals: list[float]) -> Parameter:
    return make_parameter(name, "values", tuple(vals), len(vals))


def make_parameter(name: str, distribution: str, args: tuple, samples: int,
                   decimals: int = 3, where: str = "") -> Parameter:
    """Validated :class:`Parameter`; raises ``ValueError`` naming the offending key."""
    key = where or f"parameters.{name}"
    check_name_known(name, key)
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"{key}.distribution: unknown distribution {distribution!r} "
                         f"(one of {', '.join(DISTRIBUTIONS)})")
    names = {"uniform": ("low", "high"), "normal": ("mean", "sd"),
             "integers": ("low", "high")}.get(distribution)
    for i, a in enumerate(args):
        at = f"{key}.{names[i]}" if names and i < len(names) else f"{key}.values[{i}]"
        if isinstance(a, bool) or not isinstance(a, (int, float)):
            raise ValueError(f"{at}: {a!r} is not a number")
        try:
            finite = math.isfinite(a) and abs(float(a)) <= FLOAT32_MAX
        except OverflowError:  # an int beyond float64
            finite = False
        if not finite:
            raise ValueError(f"{at}: {str(a)[:40]} is not finite in float32 (the "
                             "simulator's precision)")
    if distribution == "values" and len(args) == 0:
        raise ValueError(f"{key}.values is empty")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples <= 0:
        raise ValueError(f"{key}.samples must be a positive integer (got {samples!r})")
    if samples > MAX_SAMPLES:
        raise ValueError(f"{key}.samples={samples} exceeds {MAX_SAMPLES:,} values per parameter")
    if isinstance(decimals, bool) or not isinstance(decimals, int) or not 0 <= decimals <= 9:
        raise ValueError(f"{key}.decimals must be an integer in 0..9 (got {decimals!r})")
    if distribution == "values":
        if len(set(np.asarray(args, np.float32).tolist())) != len(args):  # as simulated
            raise ValueError(f"{key}.values has duplicates (in float32, the simulator's "
                             f"precision): {list(args)}")
    elif distribution == "normal":
        if args[1] <= 0:
            raise ValueError(f"{key}.sd must be > 0 (got {args[1]})")
    else:
        low, high = args
        if not (low < high or (distribution == "integers" and low == high)):
            raise ValueError(f"{key}: empty or inverted range low={low} high={high}")
        if distribution == "uniform":
            g_lo, g_hi = decimal_grid(low, high, decimals)
            if g_lo > g_hi:
                raise ValueError(f"{key}: no multiple of {10.0 ** -decimals:g} (decimals="
                                 f"{decimals}) lies in [{number_text(low)}, "
                                 f"{number_text(high)}]; widen the range or raise decimals")
        if distribution == "integers":
            if low != int(low) or high != int(high):
                raise ValueError(f"{key}: integers needs integer low/high (got {low}, {high})")
            if max(abs(low), abs(high)) > 2**24:
                raise ValueError(f"{key}: integers needs |low|, |high| <= {2**24:,} (exact in "
                                 f"float32; got {number_text(low)}, {number_text(high)})")
            if samples > int(high) - int(low) + 1:
                raise ValueError(f"{key}.samples={samples} exceeds the {int(high) - int(low) + 1} "
                                 f"integers in [{int(low)}, {int(high)}]")
    return Parameter(name, distribution, tuple(float(a) for a in args), int(samples), decimals)


@dataclasses.dataclass(frozen=True)
class Layout:
    """The static part of a space: parameter names and value counts (hashable; fixes shapes).

    Its methods take the space's value ``table`` ``(P, max_n)`` float32 as a (traced) argument.
    """

    names: tuple[str, ...]
    shape: tuple[int, ...]

    @property
    def size(self) -> int:
        return math.prod(self.shape)

    def decode(self, indices, table) -> dict[str, jnp.ndarray]:
        """Index vectors ``(..., P)`` int -> ``{name: values (...)}`` float32 (jit-safe)."""
        idx = jnp.asarray(indices)
        table = jnp.asarray(table, jnp.float32)
        picked = jnp.take_along_axis(jnp.broadcast_to(table, idx.shape[:-1] + table.shape),
                                     idx[..., None], axis=-1)[..., 0]
        return {n: picked[..., p] for p, n in enumerate(self.names)}

    def scenario(self, indices, table) -> dict[str, jnp.ndarray]:
        """Like :meth:`decode`, with undeclared known parameters filled by their defaults."""
        out = self.decode(indices, table)
        shape = jnp.shape(indices)[:-1]
        for n, spec in KNOWN_PARAMETERS.items():
            if n not in out:
                out[n] = jnp.full(shape, spec["default"], jnp.float32)
        return out

    def unravel(self, flat) -> jnp.ndarray:
        """Flat scenario numbers ``(...)`` -> index vectors ``(..., P)`` int32 (C order)."""
        flat = jnp.asarray(flat, jnp.int32)
        out = []
        for n in reversed(self.shape):
            out.append(flat % n)
            flat = flat // n
        return jnp.stack(out[::-1], axis=-1)

    def ravel(self, indices) -> jnp.ndarray:
        """Index vectors ``(..., P)`` -> flat scenario numbers ``(...)`` int32."""
        idx = jnp.asarray(indices, jnp.int32)
        flat = jnp.zeros(idx.shape[:-1], jnp.int32)
        for p, n in enumerate(self.shape):
            flat = flat * n + idx[..., p]
        return flat


@dataclasses.dataclass(frozen=True)
class Space:
    """A discretised logical scenario: the product of per-parameter value sets.

    Hashable, so it can be a static argument or closed over by jitted functions.

    Attributes:
      name: the built-in name or the TOML file's path/name.
      seed: the discretisation seed.
      parameters: the declared parameters, in enumeration order.
      table: per-parameter concrete values, as tuples of floats (use :attr:`values`).
    """

    name: str
    seed: int
    parameters: tuple[Parameter, ...]
    table: tuple[tuple[float, ...], ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(p.unit for p in self.parameters)

    @property
    def values(self) -> list[np.ndarray]:
        """Per-parameter concrete values, float32 arrays ``(n_p,)`` (what the simulator sees)."""
        return [np.asarray(v, dtype=np.float32) for v in self.table]

    @property
    def exact_values(self) -> list[np.ndarray]:
        """Per-parameter concrete values as drawn and rounded to their declared decimals,
        float64 ``(n_p,)``: what every output file shows (``0.036``, not float32's
        ``0.035999998``)."""
        return [np.asarray(v, dtype=np.float64) for v in self.table]

    @property
    def shape(self) -> tuple[int, ...]:
        """Number of values per parameter ``(P,)``."""
        return tuple(len(v) for v in self.table)

    @property
    def size(self) -> int:
        """Number of concrete scenarios."""
        return math.prod(self.shape)

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Continuous relaxation of the index space: ``(low, high)`` float32 ``(P,)``.

        Index ``i`` of parameter ``p`` is the point ``i``; a strategy working in this box rounds
        to the nearest integer (``jnp.rint``) and clips to ``[0, n_p - 1]``.
        """
        return np.zeros(len(self.shape), np.float32), np.asarray(self.shape, np.float32) - 1

    @property
    def value_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Smallest and largest concrete value per parameter, float32 ``(P,)``."""
        return (np.asarray([min(v) for v in self.table], np.float32),
                np.asarray([max(v) for v in self.table], np.float32))

    @property
    def layout(self) -> Layout:
        """The static part (names, value counts) for compiled code."""
        return Layout(self.names, self.shape)

    @property
    def table_array(self) -> np.ndarray:
        """Value table ``(P, max_n)`` float32, each row padded with its last value."""
        width = max(self.shape)
        return np.asarray([list(v) + [v[-1]] * (width - len(v)) for v in self.table],
                          dtype=np.float32)

    def check_indices(self, indices) -> np.ndarray:
        """``indices`` as an int64 array ``(..., P)``; one-line ValueError for another last axis,
        non-integers or an index outside ``[0, n_p)`` (naming the parameter)."""
        idx = np.asarray(indices)
        if idx.ndim < 1 or idx.shape[-1] != len(self.shape):
            raise ValueError(f"index vectors of space '{self.name}' have {len(self.shape)} "
                             f"entries ({', '.join(self.names)}); got shape {idx.shape}")
        if idx.size and not np.issubdtype(idx.dtype, np.integer):
            if not (np.issubdtype(idx.dtype, np.floating) and np.all(idx == np.round(idx))):
                raise ValueError(f"space '{self.name}': indices must be whole numbers")
        idx = idx.astype(np.int64)
        for p, (name, n) in enumerate(zip(self.names, self.shape)):
            bad = (idx[..., p] < 0) | (idx[..., p] >= n)
            if np.any(bad):
                raise ValueError(f"space '{self.name}': index {int(idx[..., p][bad].flat[0])} of "
                                 f"{name} is outside 0..{n - 1}")
        return idx

    def decode(self, indices) -> dict[str, np.ndarray]:
        """Index vectors ``(..., P)`` int -> ``{name: values (...)}`` float32 (host-side NumPy;
        use :meth:`Layout.decode` under ``jit``). ValueError for an index outside its range."""
        idx = self.check_indices(indices)
        table = self.table_array
        return {n: table[p][idx[..., p]] for p, n in enumerate(self.names)}

    def scenario(self, indices) -> dict[str, np.ndarray]:
        """Like :meth:`decode`, with undeclared known parameters filled by their defaults."""
        out = self.decode(indices)
        shape = np.shape(indices)[:-1]
        for n, spec in KNOWN_PARAMETERS.items():
            if n not in out:
                out[n] = np.full(shape, spec["default"], np.float32)
        return out

    def unravel(self, flat) -> np.ndarray:
        """Flat scenario numbers ``(...)`` -> index vectors ``(..., P)`` int32 (C order; NumPy)."""
        return np.stack(np.unravel_index(np.asarray(flat, np.int64), self.shape),
                        axis=-1).astype(np.int32)

    def ravel(self, indices) -> np.ndarray:
        """Index vectors ``(..., P)`` -> flat scenario numbers ``(...)`` int64 (NumPy)."""
        idx = self.check_indices(indices)
        return np.ravel_multi_index(tuple(np.moveaxis(idx, -1, 0)), self.shape)

    def values_at(self, indices) -> dict[str, float]:
        """``{name: value}`` of one index vector ``(P,)`` (host-side, float64 of the table)."""
        idx = self.check_indices(indices)
        return {n: float(self.table[p][int(idx[p])]) for p, n in enumerate(self.names)}

    def nearest(self, scenario: dict[str, float]) -> np.ndarray:
        """Index vector ``(P,)`` of the concrete values nearest to ``scenario`` (host-side)."""
        return np.asarray([int(np.argmin(np.abs(np.asarray(v) - float(scenario[n]))))
                           for n, v in zip(self.names, self.table)], np.int32)

    def chunks(self, chunk_size: int, start: int = 0) -> Iterator[tuple[int, int]]:
        """``(begin, end)`` flat ranges covering ``[start, size)`` in steps of chunk_size."""
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive (got {chunk_size})")
        for b in range(start, self.size, chunk_size):
            yield b, min(b + chunk_size, self.size)

    def describe(self) -> dict[str, Any]:
        """TOML-ready description; ``space_from_dict(describe())`` rebuilds the same space."""
        return {"name": self.name,
                "parameters": {p.name: p.describe() for p in self.parameters}}


def build(name: str, parameters: list[Parameter], seed: int) -> Space:
    """Discretise parameters into a :class:`Space`, checking each value's domain."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer (got {seed!r})")
    if not parameters:
        raise ValueError(f"space '{name}': no parameters declared")
    names = [p.name for p in parameters]
    dup = {n for n in names if names.count(n) > 1}
    if dup:
        raise ValueError(f"space '{name}': parameter declared twice: {sorted(dup)}")
    size = math.prod(p.samples for p in parameters)
    if size > MAX_SEARCH_SIZE:  # checked before anything is drawn or allocated
        raise ValueError(f"space '{name}' has {size:.3g} scenarios; at most "
                         f"{MAX_SEARCH_SIZE:.0e} supported")
    table = []
    for p in parameters:
        vals = p.discretise(int(seed))
        spec = parameter_spec(p.name)
        lo, hi = spec["domain"]
        bad = vals[(vals < lo) | (vals > hi) | ~(np.abs(vals) <= FLOAT32_MAX)]
        if bad.size:
            raise ValueError(f"parameters.{p.name}: value {number_text(bad[0])} outside the "
                             f"allowed [{lo:g}, {hi:g}] {spec['unit']}; narrow the distribution")
        if spec["integer"] and np.any(vals != np.round(vals)):
            raise ValueError(f"parameters.{p.name}: values must be integers "
                             f"(got {number_text(vals[vals != np.round(vals)][0])})")
        table.append(tuple(float(v) for v in vals))
    return Space(name, int(seed), tuple(parameters), tuple(table))


def _paper_parameters() -> list[Parameter]:
    # Table I of the paper, as the original code discretised it
    # (dkarunakaran/scenario_based_falsification).
    return [
        integers("ego_offset", 1, 10, 10),
        uniform("ped_accel", 0.0, 0.1, 10),
        normal("ped_speed", 1.46, 0.24, 25),
        values("ped_offset", [3.0, 3.5, 4.0, 4.5]),
        integers("weather", 0, 14, 10),
    ]


BUILTIN = {
    "paper": _paper_parameters,
    "paper-extended": lambda: _paper_parameters() + [
        values("ped_speed_change", [0.5, -0.5, 0.75, -0.75]),
        values("ped_change_step", [20, 30, 40, 50, 60]),
    ],
}


def parse_parameter(name: str, spec: Any, where: str) -> Parameter:
    """Validate one TOML parameter table into a :class:`Parameter`."""
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: expected a table, got {type(spec).__name__}")
    check_keys(spec, _PARAM_KEYS, where)
    check_name_known(name, where)
    unit = spec.get("unit", parameter_spec(name)["unit"])
    if unit != parameter_spec(name)["unit"]:
        raise ValueError(f"{where}.unit: '{name}' is in {parameter_spec(name)['unit']!r}, "
                         f"not {unit!r}")
    if "distribution" in spec and not isinstance(spec["distribution"], str):
        raise ValueError(f"{where}.distribution: must be a string (one of "
                         f"{', '.join(DISTRIBUTIONS)})")
    if "decimals" in spec and ("values" in spec or spec.get("distribution") == "integers"):
        raise ValueError(f"{where}.decimals applies to uniform and normal draws only")
    if "values" in spec:
        dist = spec.get("distribution", "values")
        if dist != "values":
            raise ValueError(f"{where}: 'values' given with distribution '{dist}'")
        extra = set(spec) & {"low", "high", "mean", "sd"}
        if extra:
            raise ValueError(f"{where}.{sorted(extra)[0]} does not apply to explicit 'values'")
        vals = spec["values"]
        if not isinstance(vals, list):
            raise ValueError(f"{where}.values must be a list (got {vals!r})")
        if "samples" in spec:
            n = spec["samples"]
            if isinstance(n, bool) or not isinstance(n, int) or n <= 0:
                raise ValueError(f"{where}.samples must be a positive integer (got {n!r})")
            if n != len(vals):
                raise ValueError(f"{where}.samples={n} disagrees with {len(vals)} values")
        return make_parameter(name, "values", tuple(vals), len(vals), where=where)
    if "distribution" not in spec:
        raise ValueError(f"{where}: needs 'distribution' ({', '.join(DISTRIBUTIONS)}) or 'values'")
    dist = spec["distribution"]
    need = {"uniform": ("low", "high"), "normal": ("mean", "sd"),
            "integers": ("low", "high")}.get(dist)
    if dist == "values":
        raise ValueError(f"{where}.values is missing (distribution 'values' lists them: "
                         "values = [1.0, 2.5, 4.0])")
    if need is None:
        raise ValueError(f"{where}.distribution: unknown distribution {dist!r} "
                         f"(one of {', '.join(DISTRIBUTIONS)})")
    for k in need + ("samples",):
        if k not in spec:
            raise ValueError(f"{where}.{k} is missing (distribution '{dist}' needs "
                             f"{', '.join(need)}, samples)")
    extra = (set(spec) & {"low", "high", "mean", "sd"}) - set(need)
    if extra:
        raise ValueError(f"{where}.{sorted(extra)[0]} does not apply to distribution '{dist}'")
    return make_parameter(name, dist, tuple(spec[k] for k in need), spec["samples"],
                          spec.get("decimals", 3), where=where)


def space_from_dict(doc: dict[str, Any], seed: int = 0, default_name: str = "custom") -> Space:
    """Build a space from a parsed TOML document (see README, 'Your own logical scenario')."""
    unknown = set(doc) - _TOP_KEYS
    if unknown:
        raise ValueError(f"unknown top-level key {sorted(unknown)[0]!r} "
                         f"(allowed: {', '.join(sorted(_TOP_KEYS))})")
    if "description" in doc and not isinstance(doc["description"], str):
        raise ValueError(f"description must be a string (got "
                         f"{type(doc['description']).__name__} {doc['description']!r:.40})")
    params = doc.get("parameters")
    if not isinstance(params, dict) or not params:
        raise ValueError("'parameters' table is missing or empty")
    flat = {}
    for n, s in params.items():  # [parameters.sut.NAME] tables: SUT parameters
        if n == "sut" and isinstance(s, dict) and s and all(isinstance(v, dict)
                                                           for v in s.values()):
            items = [(SUT_PREFIX + k, v) for k, v in s.items()]
        else:
            items = [(n, s)]
        for k, v in items:
            if not k.isprintable():  # every message names the key: keep it one line
                raise ValueError(f"parameters: {k!r} is not a parameter name (known: "
                                 f"{', '.join(KNOWN_PARAMETERS)}, or sut.NAME)")
            if k in flat:  # [parameters."sut.X"] and [parameters.sut.X] both
                raise ValueError(f"parameters.{k}: declared twice (as [parameters.\"{k}\"] "
                                 f"and [parameters.sut.{k[len(SUT_PREFIX):]}])")
            flat[k] = v
    parsed = [parse_parameter(n, s, f"parameters.{n}") for n, s in flat.items()]
    return build(check_name(doc.get("name", default_name)), parsed, seed)


def check_name(name: Any) -> str:
    """A space's name: 1-64 printable characters, no path separators (it names folders)."""
    if not isinstance(name, str):
        raise ValueError(f"name must be a string (got {type(name).__name__} {name!r:.40})")
    if not 1 <= len(name) <= 64 or not name.isprintable() or "/" in name or "\\" in name \
            or name in (".", ".."):
        raise ValueError(f"name {name[:40]!r}: use 1-64 printable characters without / or \\")
    return name


def load_space(name_or_path: str | Path | Space, seed: int = 0) -> Space:
    """A built-in space by name (``paper``, ``paper-extended``) or a user TOML file.

    Raises ``ValueError`` with a one-line message naming the bad key or value.
    """
    if isinstance(name_or_path, Space):
        return name_or_path
    key = str(name_or_path)
    if key in BUILTIN:
        return build(key, BUILTIN[key](), seed)
    path = Path(key)
    if path.suffix != ".toml" or not path.exists():
        raise ValueError(f"unknown space '{key[:80]}': not a built-in ({', '.join(BUILTIN)}) "
                         f"nor an existing .toml file")

    doc = read_toml(path, "--space")
    try:
        return space_from_dict(doc, seed, default_name=path.stem[:64] or "custom")
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def check_scenario_values(scenario: dict[str, float]) -> dict[str, float]:
    """One concrete scenario, validated like a space's values (known names, finite, inside
    each parameter's domain, integers where integer) and completed with the defaults."""
    full = {}
    for name, spec in KNOWN_PARAMETERS.items():
        v = scenario.get(name, spec["default"])
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise ValueError(f"{name}={v!r} is not a number")
        v = float(v)
        lo, hi = spec["domain"]
        if not math.isfinite(v):
            raise ValueError(f"{name}={v} is not finite")
        if not lo <= v <= hi:
            raise ValueError(f"{name}={number_text(v)} outside the allowed [{lo:g}, {hi:g}] "
                             f"{spec['unit']}")
        if spec["integer"] and v != round(v):
            raise ValueError(f"{name}={number_text(v)} must be an integer ({spec['doc']})")
        full[name] = v
    unknown = set(scenario) - set(KNOWN_PARAMETERS)
    if unknown:
        raise ValueError(f"unknown parameter '{sorted(unknown)[0]}' "
                         f"(known: {', '.join(KNOWN_PARAMETERS)})")
    return full
