"""What a sweep is asked to do: its configuration (:class:`SweepConfig`, read from and written
to ``config.toml``) and the SUT calibrations it expands to (:func:`calibrations`).

A *calibration sweep* gives SUT parameters several values (``sut_params={"ttc_full": [0.8,
1.0, 1.2]}``): every combination of values is a calibration (:class:`Calibrations`).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from pathlib import Path
from typing import Any, Mapping

import jax
import numpy as np

from jaxfalsify.base import config as cfg
from jaxfalsify.core import sim
from jaxfalsify.engine.problem import (
    SEED_LIMIT,
    Problem,
    build_requirement,
    check_int,
    check_mapping,
    fixed_sut_params,
)
from jaxfalsify.scenario.space import Space
from jaxfalsify.suts import registry as sut_lib

__all__ = ["Calibrations", "calibrations", "SweepConfig", "default_out"]

ROWS = ("all", "collisions", "none")


@dataclasses.dataclass(frozen=True)
class Calibrations:
    """The SUT parameter sets of a sweep: every combination of the swept values."""

    sut: sut_lib.SUT
    instances: tuple  # parameter pytrees, one per calibration
    swept: tuple[tuple[str, tuple[float, ...]], ...]  # (name, values) with several values

    @property
    def count(self) -> int:
        return len(self.instances)

    def stacked(self):
        if self.instances[0] is None:
            return np.zeros((self.count,), np.float32)  # no parameters: vmap over a dummy
        return jax.tree.map(lambda *xs: np.asarray(xs, np.float32), *self.instances)

    def columns(self) -> dict[str, np.ndarray]:
        """The swept parameters' value per calibration as given, ``{name: (C,) float64}``
        (the simulator computes with their float32 roundings)."""
        return {name: np.asarray([sut_lib.params_dict(p)[name] for p in self.instances],
                                 np.float64) for name, _ in self.swept}

    def describe(self, c: int) -> dict[str, float]:
        return {name: float(v[c]) for name, v in self.columns().items()}


def calibrations(sut: sut_lib.SUT, sut_params: Mapping[str, Any]) -> Calibrations:
    """Expand ``{name: value or [values]}`` into the calibrations: C order over the swept
    parameters in the SUT's declared order (the last declared parameter fastest), whatever
    order they are given in, so a sweep and its resume (whose ``config.toml`` lists them in
    declared order) number the calibrations alike. One-line ValueError naming a bad name or
    value, or values a swept parameter repeats in float32 (the simulator's precision)."""
    order = {n: i for i, n in enumerate(sut_lib.param_names(sut))}
    items = sorted(dict(sut_params).items(), key=lambda kv: order.get(kv[0], len(order)))
    fixed, swept = {}, []
    for name, v in items:  # sorted is stable: unknown names keep their order, at the end
        if isinstance(v, np.ndarray) and v.ndim == 1:  # an array of values, like a list
            v = v.tolist()
        if isinstance(v, (list, tuple)):
            v = [cfg.plain(x) if isinstance(x, np.generic) else x for x in v]
            if len(v) == 0:
                raise ValueError(f"sut_params.{name}: an empty list of values")
            if len(v) == 1:
                fixed[name] = v[0]
            else:
                swept.append((name, tuple(v)))
        else:  # a NumPy scalar as the Python number it is (np.float32 1.2 as 1.2)
            fixed[name] = cfg.plain(v) if isinstance(v, (np.generic, np.ndarray)) \
                and np.ndim(v) == 0 else v
    count = math.prod(len(vals) for _, vals in swept)
    if count > 4096:  # before building them
        raise ValueError(f"sut_params: {count} calibrations; at most 4096 per sweep")
    for name, vals in swept:  # each value checked (a bad one named) before the float32 test
        for x in vals:
            sut_lib.with_params(sut, {**fixed, name: x}, where="sut_params")
        as32 = np.asarray(vals, np.float64).astype(np.float32)
        if len(set(as32.tolist())) != len(vals):
            raise ValueError(f"sut_params.{name}: values {list(vals)} repeat in float32 (the "
                             "simulator's precision): the calibrations would be identical")
    instances = []
    for combo in itertools.product(*(vals for _, vals in swept)):
        over = {**fixed, **{n: c for (n, _), c in zip(swept, combo)}}
        instances.append(sut_lib.with_params(sut, over, where="sut_params"))
    sut_lib.check_traceable(sut, instances[0])
    return Calibrations(sut, tuple(instances),
                        tuple((n, tuple(float(x) for x in vals)) for n, vals in swept))


@dataclasses.dataclass(frozen=True)
class SweepConfig(Problem):
    """What a sweep needs (``sut_params``: a value or a list of values each)."""

    seed: int = 0  # the SUT's randomness (sensor noise); deterministic SUTs ignore it
    chunk: int | None = None  # most scenarios (x calibrations) per compiled call; None:
    # the backend's default (sim.default_chunk), resolved by execute once any distributed
    # runtime is up (choosing it starts JAX's backend); config.toml records the value
    rows: str = "all"  # all, collisions or none (summary only)
    requirement: str = "collision"  # also count its violations (a "violated" column; rows =
    # "collisions" then keeps the violations)
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)

    def requirement_of(self):
        """``(Requirement, its parameters)``, or ``(None, None)`` for collisions; one-line
        ValueError for a bad name or parameter."""
        req, params = build_requirement(self.requirement, self.requirement_params)
        return (None, None) if req is None else (req, params)

    def build(self) -> tuple[Space, Calibrations]:
        self.check_space_seed()
        check_int("seed", self.seed, 0, SEED_LIMIT - 1)
        if self.chunk is not None:
            check_int("chunk", self.chunk, 1, 1 << 24)
        if self.rows not in ROWS:
            raise ValueError(f"rows must be one of {', '.join(ROWS)} (got {self.rows!r})")
        if not isinstance(self.sut, str):
            raise ValueError(f"sut must be a name (got {self.sut!r})")
        sp = self.built_space()
        sut = sut_lib.resolve(self.sut)
        self.requirement_of()
        return sp, calibrations(sut, check_mapping("sut_params", self.sut_params))

    def resolved(self) -> "SweepConfig":
        """This config with the default chunk chosen for JAX's backend and a SUT file path
        made absolute (:func:`jaxfalsify.suts.registry.recorded_spec`)."""
        return dataclasses.replace(self, chunk=self.chunk or sim.default_chunk(),
                                   sut=sut_lib.recorded_spec(self.sut),
                                   requirement=sut_lib.recorded_spec(self.requirement))

    def full_sut_params(self, space: Space) -> dict[str, Any]:
        """Every SUT parameter: its default, or the value (list of values) given; without
        those ``space`` varies (its ``sut.NAME`` dimensions)."""

        defaults = sut_lib.params_dict(sut_lib.resolve(self.sut).default_params)
        return fixed_sut_params({**defaults, **dict(self.sut_params)}, space)

    def to_toml(self, space: Space, processes: int = 1) -> str:
        doc = {"kind": "sweep", "sut": self.sut, "space_seed": self.space_seed,
               "seed": self.seed, "chunk": self.chunk, "rows": self.rows,
               "processes": processes, "sut_params": self.full_sut_params(space),
               **({"requirement": self.requirement,
                   "requirement_params": dict(self.requirement_params)}
                  if self.requirement != "collision" else {}),
               "space": space.describe()}
        return cfg.dumps_toml(doc)

    @classmethod
    def from_toml(cls, path: Path) -> tuple["SweepConfig", int]:
        """``(config, processes)`` from a sweep's ``config.toml``."""
        doc = cfg.read_toml(path)
        if doc.pop("kind", None) != "sweep":
            raise ValueError(f"{path} is not a sweep's config")
        processes = doc.pop("processes", 1)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(doc) - known
        if unknown:
            raise ValueError(f"{path}: unknown key '{sorted(unknown)[0]}'")
        try:
            return cls(**doc), int(processes)
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: {e}") from None


def default_out(space: Space, sut_name: str, space_seed: int) -> Path:
    sut = sut_lib.folder_name(sut_name)
    return Path("sweeps") / f"{space.name}-{sut}-s{space_seed}"  # names hold no / (check_name)
