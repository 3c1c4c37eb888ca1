"""One concern: the problem a job is given, described and validated in one place.

The problem a run, sweep or comparison is given, described and validated in one place: the
space (built-in name, TOML path or table) and its discretisation seed, the SUT and its
parameters, and for a run the strategy, its options, budget, batch and seed
(:class:`RunConfig`, built into a :class:`Built`), with the shared checks of seeds, counts and
tables that every job's configuration uses."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from jaxfalsify import search
from jaxfalsify.base import config as cfg
from jaxfalsify.base.pytree import check_ranges
from jaxfalsify.core import requirements
from jaxfalsify.engine import campaign
from jaxfalsify.io import cache
from jaxfalsify.scenario.space import (
    SUT_PREFIX,
    Space,
    is_sut_parameter,
    load_space,
    space_from_dict,
)
from jaxfalsify.suts import registry as sut_lib

__all__ = [
    "PAPER_BUDGET", "SEED_LIMIT", "check_int", "check_once", "build_space", "space_sut_names",
    "fixed_sut_params", "check_space_sut", "check_mapping", "Built", "Problem", "RunConfig",
    "CONFIG_KEYS", "build_requirement", "SETTINGS", "configure", "jax_settings"
]

PAPER_BUDGET = 4000
SEED_LIMIT = 2**64  # seeds are 64-bit (see sim.seed_key_data)


def check_int(key: str, v, minimum: int = 0, maximum: int | None = None) -> int:
    """``v`` as an int within bounds, or a one-line ValueError naming ``key``."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
        raise ValueError(f"{key} must be an integer (got {v!r})")
    if v < minimum or (maximum is not None and v > maximum):
        if maximum is None:
            raise ValueError(f"{key} must be at least {minimum} (got {v})")
        raise ValueError(f"{key} must be in {minimum}..{maximum} (got {v})")
    return int(v)


def check_once(key: str, values) -> None:
    """A one-line ValueError naming ``key`` and the first value ``values`` holds twice."""
    seen = set()
    for v in values:
        if v in seen:
            raise ValueError(f"{key}: {v} given twice")
        seen.add(v)


def build_space(space: Any, space_seed: int) -> Space:
    if isinstance(space, Space):
        return space
    if isinstance(space, Mapping):
        return space_from_dict(dict(space), space_seed)
    if isinstance(space, str):
        return load_space(space, space_seed)
    raise ValueError(f"space must be a name, a TOML path or a table (got {space!r})")


def space_sut_names(sp: Space) -> set[str]:
    """The SUT parameters a space varies (its ``sut.NAME`` dimensions), by SUT name."""

    return {n[len(SUT_PREFIX):] for n in sp.names if is_sut_parameter(n)}


def fixed_sut_params(params: Mapping[str, Any], sp: Space) -> dict[str, Any]:
    """``params`` without those the space sets per scenario (what a config or summary
    records: one value, or the values given, per parameter the space does not vary)."""
    varied = space_sut_names(sp)
    return {k: v for k, v in params.items() if k not in varied}


def check_space_sut(sp: Space, sut: sut_lib.SUT, given: Any = ()) -> None:
    """ValueError naming a space parameter ``sut.NAME`` the SUT does not have, one with a
    value outside the SUT's interval for it (its ``RANGES``, as ``--sut-param`` is checked),
    or one also given a value (``given``: the names of ``--sut-param``/``sut_params``), which
    the space's values would silently override."""

    known = sut_lib.param_names(sut)
    for n in sp.names:
        if is_sut_parameter(n) and n[len(SUT_PREFIX):] not in known:
            raise ValueError(f"space parameter {n}: the SUT '{sut.name}' has no parameter "
                             f"'{n[len(SUT_PREFIX):]}' (it has: {', '.join(known) or 'none'})")
        if is_sut_parameter(n) and n[len(SUT_PREFIX):] in given:
            raise ValueError(f"--sut-param {n[len(SUT_PREFIX):]}: the space already varies it "
                             f"(its parameter {n}); give its values in one place")
    import dataclasses

    if dataclasses.is_dataclass(sut.default_params):  # its values in the SUT's RANGES
        for n, vals in zip(sp.names, sp.exact_values):
            if is_sut_parameter(n):
                for v in (vals.min(), vals.max()):  # an interval holds all if these
                    check_ranges(sut.default_params, {n[len(SUT_PREFIX):]: float(v)},
                                 f"space parameter {n}: SUT '{sut.name}'")


def check_mapping(key: str, m) -> dict:
    if not isinstance(m, Mapping):
        raise ValueError(f"{key} must be a table of NAME = VALUE (got {m!r})")
    return dict(m)


@dataclasses.dataclass(frozen=True)
class Built:
    """A run's configuration, validated and built."""

    space: Space
    sut: sut_lib.SUT
    sut_params: Any
    strategy: search.Strategy
    strategy_params: Any
    plan: campaign.Plan
    requirement: Any = None  # the Requirement the search looks for (None: collisions)
    requirement_params: Any = None


@dataclasses.dataclass(frozen=True)
class Problem:
    """The problem every job is given, its fields declared once for every job's
    configuration (run, sweep, compare, estimate): the logical scenario and the system under
    test. ``sut_params``: name -> value (a sweep also takes lists: calibrations)."""

    space: Any = "paper"  # built-in name, TOML path, or a space description table
    space_seed: int = 0  # discretisation seed of the space
    sut: str = "carla-tm"  # registry name or import path module:attr
    sut_params: Mapping[str, Any] = dataclasses.field(default_factory=dict)

    def check_space_seed(self) -> None:
        check_int("space_seed", self.space_seed, 0, SEED_LIMIT - 1)

    def built_space(self) -> Space:
        """The space, its seed checked; one-line ValueError on a bad one."""
        self.check_space_seed()
        return build_space(self.space, self.space_seed)


@dataclasses.dataclass(frozen=True)
class RunConfig(Problem):
    """What a run needs. Defaults: the paper's space (space seed 0), ``carla-tm``,
    ``reinforce/default``, search seed 0, the strategy's default budget
    (:func:`jaxfalsify.search.default_evaluations`: 409,600 evaluations, 100 updates of 4096,
    for ``reinforce/default``; the paper's 4000 for ``reinforce/paper`` and the others)."""

    strategy: str = "reinforce/default"
    strategy_params: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    evaluations: int | None = None  # the budget, in evaluated scenarios (None: the strategy's)
    batch: int | None = None  # scenarios per update (None: the strategy's default)
    seed: int = 0  # search seed
    checkpoint_every: int | None = None  # updates between checkpoints (None: ~1/20 of the run)
    requirement: str = "collision"  # what is critical: a requirement's name or import path
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)
    evaluator: str = ""  # "": the built-in JAX SUT; "python": a user's own ask/tell loop
    # (jaxfalsify.Falsifier); "module:attr": a host function run by worker processes
    # (jaxfalsify.jobs.evaluators). With an evaluator, sut is "external" and the evaluator's
    # robustness says what is critical (robustness < 0)

    def build(self) -> Built:
        """Validate and build everything; ValueError (one line) on bad values."""
        if self.evaluator:
            return self._build_external()
        self._check_numbers()
        if not isinstance(self.sut, str) or not isinstance(self.strategy, str):
            raise ValueError("sut and strategy must be names")
        sp = self.built_space()
        given = check_mapping("sut_params", self.sut_params)
        sut, sut_params = sut_lib.make(self.sut, **given)
        check_space_sut(sp, sut, given)
        name = search.canonical(self.strategy)
        strat, strat_params = search.make(name, sp.shape, self.batch,
                                          **check_mapping("strategy_params",
                                                          self.strategy_params))
        evaluations = self.evaluations or search.default_evaluations(name)
        req, rparams = build_requirement(self.requirement, self.requirement_params)
        return Built(sp, sut, sut_params, strat, strat_params,
                     campaign.plan(evaluations, strat.batch, every=self.checkpoint_every),
                     req, rparams)

    def _check_numbers(self) -> None:
        check_int("seed", self.seed, 0, SEED_LIMIT - 1)
        self.check_space_seed()
        if self.evaluations is not None:
            check_int("evaluations", self.evaluations, 1, 10**9)
        if self.batch is not None:
            check_int("batch", self.batch, 1, 10**6)
        if self.checkpoint_every is not None:
            check_int("checkpoint_every", self.checkpoint_every, 1, 10**9)  # (updates)

    def _build_external(self) -> Built:
        """An external evaluator's run: the space, the strategy and the plan (no SUT, no
        requirement: the evaluator's robustness decides)."""
        check_evaluator(self.evaluator)
        self._check_numbers()
        if self.sut not in ("external", RunConfig.sut):
            raise ValueError(f"sut = {self.sut!r}: a run with an evaluator has no JAX SUT "
                             "(its evaluator is the system under test)")
        if self.sut_params:
            raise ValueError(f"sut_params {sorted(self.sut_params)[0]!r}: a run with an "
                             "evaluator has no JAX SUT to set parameters of")
        if self.requirement not in (RunConfig.requirement, "evaluator"):
            raise ValueError(f"requirement = {self.requirement!r}: with an evaluator, its "
                             "results decide what is critical (its collision flags, or "
                             "robustness < 0)")
        if self.requirement_params:
            raise ValueError(f"requirement_params {sorted(self.requirement_params)[0]!r}: with "
                             "an evaluator, its results decide what is critical")
        if not isinstance(self.strategy, str):
            raise ValueError("strategy must be a name")
        sp = self.built_space()
        bad = [n for n in sp.names if is_sut_parameter(n)]
        if bad:
            raise ValueError(f"space parameter '{bad[0]}': sut.NAME parameters set a JAX SUT's "
                             "parameters; an evaluator takes scenario parameters only")
        name = search.canonical(self.strategy)
        strat, strat_params = search.make(name, sp.shape, self.batch,
                                          **check_mapping("strategy_params",
                                                          self.strategy_params))
        evaluations = self.evaluations or search.default_evaluations(name)
        return Built(sp, None, None, strat, strat_params,
                     campaign.plan(evaluations, strat.batch, every=self.checkpoint_every))

    def resolved(self, built: Built | None = None) -> "RunConfig":
        """Every default filled in: the canonical strategy name, its batch and full options,
        the SUT's full parameters, the space's full description."""
        b = built or self.build()
        if self.evaluator:
            return dataclasses.replace(
                self, space=b.space.describe(), strategy=search.canonical(self.strategy),
                evaluator=sut_lib.recorded_spec(self.evaluator),
                sut="external", sut_params={}, batch=b.strategy.batch,
                evaluations=b.plan.evaluations, strategy_params=_strategy_options(b),
                requirement="evaluator", requirement_params={})
        return dataclasses.replace(
            self, space=b.space.describe(), strategy=search.canonical(self.strategy),
            sut=sut_lib.recorded_spec(self.sut), batch=b.strategy.batch,
            evaluations=b.plan.evaluations,
            sut_params=fixed_sut_params(sut_lib.params_dict(b.sut_params), b.space),
            strategy_params=_strategy_options(b),
            requirement=sut_lib.recorded_spec(self.requirement),
            requirement_params=sut_lib.params_dict(b.requirement_params))

    def to_toml(self) -> str:
        """``config.toml`` text (call on a :meth:`resolved` config)."""
        doc = {"kind": "run", "strategy": self.strategy, "sut": self.sut, "seed": self.seed,
               "evaluations": self.evaluations, "batch": self.batch,
               "space_seed": self.space_seed, "checkpoint_every": self.checkpoint_every,
               "sut_params": dict(self.sut_params),
               "strategy_params": dict(self.strategy_params),
               "requirement": self.requirement,
               "requirement_params": dict(self.requirement_params),
               **({"evaluator": self.evaluator} if self.evaluator else {}),
               "space": self.space if isinstance(self.space, Mapping) else self.space,
               "jax": jax_settings()}
        return cfg.dumps_toml(doc)

    @classmethod
    def from_toml(cls, path: Path, check_jax: bool = False) -> "RunConfig":
        """Read a run's ``config.toml``; unknown keys and wrong types give one-line errors.
        ``check_jax``: refuse (one line) a ``[jax]`` table whose settings are not this
        process's (the run's draws depend on them: :func:`jax_settings`)."""
        doc = cfg.read_toml(path, "--config")
        kind = doc.pop("kind", "run")
        if kind != "run":
            raise ValueError(f"{path}: kind = {str(kind)[:20]!r}, not a run's config")
        recorded = doc.pop("jax", {})
        if not isinstance(recorded, dict) or not all(isinstance(v, str)
                                                      for v in recorded.values()):
            raise ValueError(f"{path}: [jax] must be a table of the JAX settings as text")
        if check_jax:
            now = jax_settings()
            for k, v in recorded.items():
                if k not in now:
                    raise ValueError(f"{path}: [jax] {k}: not a setting a run records (one of "
                                     f"{', '.join(now)})")
                if now[k] != v:
                    how = f"unset {k.upper()}" if v == "None" else f"set {k.upper()}={v}"
                    raise ValueError(
                        f"{path}: the run had {k} = {v}, this process has {now[k]} (its draws "
                        f"depend on it: {how} to repeat the run, or delete the line from [jax] "
                        "to run with this process's setting)")
        return cls.from_dict(doc, where=str(path))

    @classmethod
    def from_dict(cls, doc: Mapping, where: str = "config") -> "RunConfig":
        """A run's configuration from ``config.toml``'s contents (its ``kind`` taken off); a
        ``[jax]`` table, the JAX settings the run recorded, is accepted and not a setting
        (:meth:`from_toml` checks it against this process's)."""
        doc = {k: v for k, v in doc.items() if k != "jax"}
        cfg.check_keys(doc, CONFIG_KEYS, where)
        for key in ("sut", "strategy", "requirement", "evaluator"):
            if key in doc and not isinstance(doc[key], str):
                raise ValueError(f"{where}: {key} must be a string (got {doc[key]!r})")
        for key in ("sut_params", "strategy_params", "requirement_params"):
            if key in doc and not isinstance(doc[key], dict):
                raise ValueError(f"{where}: [{key}] must be a table (got {doc[key]!r})")
        if "space" in doc and not isinstance(doc["space"], (str, dict)):
            raise ValueError(f"{where}: space must be a name, a path or a table")
        if isinstance(doc.get("space"), dict):  # the file's own [space] table, named by it
            try:
                build_space(doc["space"], 0)
            except ValueError as e:
                raise ValueError(f"{where}: [space] {e}") from None
        for key, lo, hi in (("seed", 0, SEED_LIMIT - 1), ("space_seed", 0, SEED_LIMIT - 1),
                            ("evaluations", 1, 10**9), ("batch", 1, 10**6),
                            ("checkpoint_every", 1, None)):
            if key in doc:  # the file named (build() checks the same, for flags too)
                check_int(f"{where}: {key}", doc[key], lo, hi)
        # the file's SUT, strategy and their options named by the file (a flag may replace
        # them later, but the file itself is wrong)
        try:
            if doc.get("evaluator"):
                check_evaluator(doc["evaluator"])
                sut = None
            else:
                sut = sut_lib.resolve(doc.get("sut", cls.sut))
            name = search.canonical(doc.get("strategy", cls.strategy))
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        if doc.get("sut_params") and sut is not None:
            sut_lib.with_params(sut, doc["sut_params"], f"{where}: [sut_params]")
        if doc.get("strategy_params"):
            search.check_options(name, doc["strategy_params"],
                                 f"{where}: [strategy_params] of '{name}'")
        return cls(**doc)


CONFIG_KEYS = {f.name for f in dataclasses.fields(RunConfig)}


def jax_settings() -> dict[str, str]:
    """The JAX settings a run's results depend on besides its configuration (the random
    draws' generator and its partitioning, matrix products' precision, dtype promotion), as
    text: what ``config.toml``'s ``[jax]`` table records (64-bit mode is always off)."""
    return {k: v for k, v in cache.program_settings().items() if k != "jax_enable_x64"}


def build_requirement(spec, params) -> tuple[Any, Any]:
    """``(Requirement or None, its parameters)`` of a run's or sweep's ``requirement`` and
    ``requirement_params``, checked (one-line ValueError); None for ``collision``: the
    rollout's own collision flags, no extra work."""
    if not isinstance(spec, str):
        raise ValueError("requirement must be a name or an import path")
    req = requirements.resolve(spec)
    rparams = requirements.with_params(req, check_mapping("requirement_params", params))
    requirements.check(req, rparams)
    return (None if req is requirements.REGISTRY["collision"] else req), rparams


def check_evaluator(spec) -> None:
    """ValueError (one line) unless ``spec`` is ``"python"`` or an import path
    ``module:attr`` (or ``path/to/file.py:attr``); the import itself is
    :func:`jaxfalsify.jobs.evaluators.load`'s."""
    if not isinstance(spec, str) or not spec:
        raise ValueError(f"evaluator must be 'python' or an import path module:attr "
                         f"(got {spec!r})")
    if spec == "python":
        return
    mod, sep, attr = spec.rpartition(":")
    if not sep or not mod or not attr.isidentifier():
        raise ValueError(f"evaluator '{spec}' is not an import path module:attr")


SETTINGS = ("space", "space_seed", "sut", "strategy", "evaluations", "batch", "seed",
            "checkpoint_every", "requirement", "evaluator")  # configure's keywords (run's flags)


def configure(config: RunConfig | Path | str | None = None, /, *,
              sut_params: Mapping[str, float] | None = None,
              strategy_params: Mapping[str, Any] | None = None,
              requirement_params: Mapping[str, float] | None = None,
              **settings) -> RunConfig:
    """The configuration ``jaxfalsify run [--config FILE] [flags]`` runs: ``config`` (a
    ``config.toml`` path, a :class:`RunConfig`, or None for the defaults) with ``settings``
    (any of :data:`SETTINGS`; None values ignored) in place of its own and ``sut_params`` /
    ``strategy_params`` merged over its own, name by name. What the config resolved for a
    strategy, SUT or space that a setting replaces is dropped (compared by what they name:
    ``reinforce`` is ``reinforce/default``, a SUT file by its absolute path), so the new one
    starts from its own defaults: another strategy's options and batch, another SUT's
    parameters, and parameters the new space varies itself (its ``sut.NAME`` dimensions).
    One-line ValueError for a setting that is not one."""
    unknown = sorted(set(settings) - set(SETTINGS))
    if unknown:
        raise ValueError(f"no run setting '{unknown[0]}' (one of {', '.join(SETTINGS)}, "
                         "sut_params, strategy_params, requirement_params)")
    settings = {k: v for k, v in settings.items() if v is not None}
    if config is None:
        rc = RunConfig()
    else:
        rc = config if isinstance(config, RunConfig) else RunConfig.from_toml(Path(config),
                                                                               check_jax=True)
        rc = _overridden(rc, settings)
    rc = dataclasses.replace(rc, **settings)
    if sut_params:
        rc = dataclasses.replace(rc, sut_params={**rc.sut_params, **sut_params})
    if strategy_params:
        rc = dataclasses.replace(rc, strategy_params={**rc.strategy_params, **strategy_params})
    if requirement_params:
        rc = dataclasses.replace(rc, requirement_params={**rc.requirement_params,
                                                         **requirement_params})
    return rc


def _overridden(rc: RunConfig, settings: dict) -> RunConfig:
    """``rc`` less what it resolved for the strategy, SUT or space that ``settings`` replace
    (see :func:`configure`)."""
    def same(a, b, canon):
        try:
            return canon(a) == canon(b)
        except ValueError:  # an unknown name: named when the run is built
            return a == b

    if "strategy" in settings and not same(settings["strategy"], rc.strategy,
                                           search.canonical):
        rc = dataclasses.replace(rc, strategy_params={}, batch=None)  # a batch setting
        # is applied after this
    if "sut" in settings and not same(settings["sut"], rc.sut, sut_lib.recorded_spec):
        rc = dataclasses.replace(rc, sut_params={})
    if "requirement" in settings and not same(settings["requirement"], rc.requirement,
                                              sut_lib.recorded_spec):
        rc = dataclasses.replace(rc, requirement_params={})
    if "space" in settings or "space_seed" in settings:
        if rc.sut_params:
            sp = build_space(settings.get("space", rc.space),
                             settings.get("space_seed", rc.space_seed))
            rc = dataclasses.replace(rc, sut_params=fixed_sut_params(rc.sut_params, sp))
        try:  # a strategy whose default batch fits the space (grid) resolves it anew
            cls = search.REGISTRY[search.canonical(rc.strategy)].cls
        except (ValueError, KeyError, AttributeError):
            cls = None
        if getattr(cls, "BATCH_AT_MOST_SIZE", False):
            rc = dataclasses.replace(rc, batch=None)  # a batch setting is applied after this
    return rc


def _strategy_options(b: Built) -> dict:
    s = b.strategy
    out = {f.name: getattr(s, f.name) for f in dataclasses.fields(s)
           if f.name not in ("shape", "batch")}
    out.update({k: float(getattr(b.strategy_params, k))
                for k in (f.name for f in dataclasses.fields(b.strategy_params))})
    return out
