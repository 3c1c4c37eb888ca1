"""The search benchmark suite (``jaxfalsify compare --suite experiments/suite/suite.toml``):
logical scenarios (entries: a space file and the SUT to search it with) x strategies x seeds,
each entry a :func:`jaxfalsify.jobs.compare.execute` comparison reported at every budget of the
suite, and ``suite.md``, the table of them all (:func:`load_suite`, :func:`execute_suite`,
:func:`suite_markdown`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from jaxfalsify import search
from jaxfalsify.base import config as cfg
from jaxfalsify.base.progress import Clock, Progress
from jaxfalsify.core import requirements
from jaxfalsify.engine.problem import SEED_LIMIT, check_int, check_once
from jaxfalsify.io import store
from jaxfalsify.io.files import write_atomic, write_json
from jaxfalsify.jobs.compare import DEFAULT_STRATEGIES, CompareConfig, execute
from jaxfalsify.jobs.compare_tables import (
    TIME_NOTE,
    budgets_markdown,
    plural,
    requirement_words,
    share_text,
)
from jaxfalsify.jobs.runs import timestamp
from jaxfalsify.scenario.space import check_name, load_space
from jaxfalsify.suts import registry as sut_lib

__all__ = ["load_suite", "execute_suite", "suite_markdown"]


@dataclasses.dataclass(frozen=True)
class SuiteEntry:
    """One logical scenario of a suite: a space file and the SUT to search it with."""

    space: str  # path (relative paths are resolved against the suite file)
    sut: str = "carla-tm"
    sut_params: Mapping[str, float] = dataclasses.field(default_factory=dict)
    space_seed: int = 0
    exclude: tuple[str, ...] = ()  # strategies not run on this entry (grid on a huge space)
    requirement: str = "collision"  # what is critical on this entry (compare's --requirement)
    requirement_params: Mapping[str, float] = dataclasses.field(default_factory=dict)


@dataclasses.dataclass(frozen=True)
class SuiteConfig:
    """A benchmark suite (``experiments/suite/suite.toml``): entries x strategies x seeds,
    reported at every budget."""

    name: str
    entries: tuple[SuiteEntry, ...]
    budgets: tuple[int, ...] = (250, 1000, 4000)
    seeds: int = 10
    strategies: tuple[str, ...] = DEFAULT_STRATEGIES
    jobs: int = 0  # strategies searched side by side (0: one per CPU core, at most 4)
    # options per strategy on every entry, e.g. {"reinforce/screened": {"ttc_weight": 0.05}}
    strategy_params: Mapping[str, Mapping[str, Any]] = dataclasses.field(default_factory=dict)
    batch: int | None = None  # scenarios per update of every strategy (None: each its own)

    def compare_config(self, entry: SuiteEntry) -> CompareConfig:
        names = tuple(n for n in self.strategies
                      if search.canonical(n) not in {search.canonical(x) for x in entry.exclude})
        return CompareConfig(strategies=names, seeds=self.seeds,
                             evaluations=max(self.budgets), space=entry.space,
                             space_seed=entry.space_seed, sut=entry.sut,
                             sut_params=dict(entry.sut_params), budgets=tuple(self.budgets),
                             strategy_params={s: dict(o) for s, o in self.strategy_params.items()
                                              if s in names},
                             jobs=self.jobs, batch=self.batch,
                             requirement=entry.requirement,
                             requirement_params=dict(entry.requirement_params))

    def check(self) -> None:
        if not self.entries:
            raise ValueError("suite: no [[entry]] given")
        for s in self.strategy_params:  # an entry excluding it drops its options there
            if s not in self.strategies:
                raise ValueError(f"strategy_params: {s!r} is not among the strategies "
                                 f"({', '.join(self.strategies)})")
        for b in self.budgets:
            check_int("suite budgets", b, 1, 10**9)
        check_once("suite budgets", self.budgets)
        seen: dict[tuple, int] = {}
        for k, e in enumerate(self.entries):
            try:  # the same search twice would only cost time (exclusions aside)
                key = (e.space, e.sut, e.space_seed,
                       tuple(sorted((n, float(v)) for n, v in e.sut_params.items())),
                       e.requirement,
                       tuple(sorted((n, float(v)) for n, v in e.requirement_params.items())))
            except (TypeError, ValueError):
                key = (k,)  # a malformed value: named by the entry's own check below
            if key in seen:
                raise ValueError(f"suite: entry[{k}] repeats entry[{seen[key]}] (space "
                                 f"{e.space}, SUT {e.sut}); give each search once")
            seen[key] = k
        for k, e in enumerate(self.entries):
            if e.exclude and not self.compare_config(e).strategies:
                raise ValueError(f"suite: entry[{k}].exclude leaves none of the strategies "
                                 f"({', '.join(self.strategies)}) to run")
            self.compare_config(e).check()


_SUITE_KEYS = {"name", "budgets", "seeds", "strategies", "strategy_params", "entry", "batch"}
_ENTRY_KEYS = {"space", "sut", "sut_params", "space_seed", "exclude", "requirement",
               "requirement_params"}


def _same_strategy(a: str, b: str) -> bool:
    """Whether two names are the same strategy (an alias and its registry name)."""
    try:
        return search.canonical(a) == search.canonical(b)
    except ValueError:  # an unknown name: itself only (named by the check that follows)
        return a == b


def entry_name(entry: SuiteEntry) -> str:
    """The name of a suite entry's space, as the suite's report heads its section (a TOML
    file's ``name``, e.g. ``aeb-9e6``, or a built-in space's name)."""

    return load_space(entry.space, entry.space_seed).name


def load_suite(path: Path | str, seeds: int | None = None,
               strategies: tuple[str, ...] | None = None, jobs: int = 0,
               entries: tuple[str, ...] | None = None,
               strategy_params: Mapping[str, Mapping[str, Any]] | None = None,
               batch: int | None = None) -> SuiteConfig:
    """A suite from its TOML file (one-line ValueError naming the bad key); ``seeds`` and
    ``strategies`` override the file's; ``jobs`` as in :class:`CompareConfig`; ``entries``
    keeps only the entries of these spaces (by :func:`entry_name`, in the file's order; a
    name matching no entry is refused); ``strategy_params`` (per strategy, on every entry)
    are merged over the file's ``[strategy_params."NAME"]`` tables, option by option (the
    file's tables of strategies that ``strategies`` leaves out are dropped); ``batch`` (or the
    file's ``batch``) sets every strategy's scenarios per update."""
    path = Path(path)
    doc = cfg.read_toml(path, "--suite")
    where = str(path)
    cfg.check_keys(doc, _SUITE_KEYS, where)
    tables = doc.get("entry")
    if not isinstance(tables, list) or not tables:
        raise ValueError(f"{where}: needs at least one [[entry]] table")
    out = []
    for k, e in enumerate(tables):
        key = f"{where}: entry[{k}]"
        if not isinstance(e, dict):
            raise ValueError(f"{key} must be a table")
        cfg.check_keys(e, _ENTRY_KEYS, key)
        if not isinstance(e.get("space"), str):
            raise ValueError(f"{key}.space must be a space name or a .toml path")
        sp = e["space"]
        if sp.endswith(".toml") and not Path(sp).is_absolute():
            sp = str((path.parent / sp).resolve())
        sut = e.get("sut", "carla-tm")
        if not isinstance(sut, str):
            raise ValueError(f"{key}.sut must be a SUT name or an import path")
        sut = sut_lib.recorded_spec(sut, path.parent)  # a file next to the suite, like the space
        sut_params = e.get("sut_params", {})
        if not isinstance(sut_params, dict):
            raise ValueError(f"{key}.sut_params must be a table of NAME = VALUE")
        try:
            resolved = sut_lib.resolve(sut)
        except ValueError:
            resolved = None  # an unknown SUT: named by the entry's check
        if resolved is not None and sut_params:
            sut_lib.with_params(resolved, sut_params, f"{key}.sut_params")
        exclude = e.get("exclude", [])
        if not isinstance(exclude, list) or not all(isinstance(x, str) for x in exclude):
            raise ValueError(f"{key}.exclude must be a list of strategy names")
        for x in exclude:
            try:
                search.canonical(x)
            except ValueError as err:
                raise ValueError(f"{key}.exclude: {err}") from None
        check_int(f"{key}.space_seed", e.get("space_seed", 0), 0, SEED_LIMIT - 1)
        req = e.get("requirement", "collision")
        if not isinstance(req, str):
            raise ValueError(f"{key}.requirement must be a requirement name or an import path")
        req_params = e.get("requirement_params", {})
        if not isinstance(req_params, dict):
            raise ValueError(f"{key}.requirement_params must be a table of NAME = VALUE")
        try:
            resolved_req = requirements.resolve(sut_lib.recorded_spec(req, path.parent))
        except ValueError as err:
            raise ValueError(f"{key}.requirement: {err}") from None
        requirements.with_params(resolved_req, req_params, f"{key}.requirement_params")
        out.append(SuiteEntry(sp, sut, sut_params,
                              e.get("space_seed", 0), tuple(exclude),
                              sut_lib.recorded_spec(req, path.parent), req_params))
    if entries is not None:
        known = [entry_name(e) for e in out]
        for name in entries:
            if name not in known:
                raise ValueError(f"--entries: no entry of space '{name}' in {where} "
                                 f"(entries: {', '.join(dict.fromkeys(known))})")
        out = [e for e, name in zip(out, known) if name in entries]

    budgets = doc.get("budgets", [250, 1000, 4000])
    if not isinstance(budgets, list) or not budgets:
        raise ValueError(f"{where}: budgets must be a list of evaluation counts")
    for b in budgets:
        check_int(f"{where}: budgets", b, 1, 10**9)
    check_once(f"{where}: budgets", budgets)
    names = doc.get("strategies", list(DEFAULT_STRATEGIES))
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise ValueError(f"{where}: strategies must be a list of strategy names "
                         f"(got {names!r:.60})")
    names = strategies or tuple(names)
    options = doc.get("strategy_params", {})
    if not isinstance(options, dict) or not all(isinstance(v, dict) for v in options.values()):
        raise ValueError(f'{where}: strategy_params must hold a table per strategy, e.g. '
                         f'[strategy_params."cem"] elite_frac = 0.2')
    # the file's tables must name the file's strategies (an alias counts: `reinforce` for
    # `reinforce/default`); those of strategies a narrower ``strategies`` leaves out are
    # dropped; the caller's options must name strategies that run. Keys become the names
    # the comparison runs under.
    def run_name(name, among, what=None):  # ``among``'s spelling of ``name``
        found = next((n for n in among if _same_strategy(name, n)), None)
        if found is None and what:
            raise ValueError(f"{what}: {name!r} is not among the strategies "
                             f"({', '.join(among)})")
        return found

    file_names = tuple(doc.get("strategies", list(DEFAULT_STRATEGIES)))
    merged: dict[str, dict] = {}
    for s, o in options.items():
        run_name(s, file_names, f"{where}: strategy_params")
        search.check_options(s, o, f'{where}: strategy_params."{s}"')  # named by file
        if (n := run_name(s, names)) is not None:
            merged.setdefault(n, {}).update(o)
    for s, o in (strategy_params or {}).items():
        if not isinstance(o, Mapping):
            raise ValueError(f"strategy_params[{s!r}] must map option names to values")
        merged.setdefault(run_name(s, names, "strategy_params"), {}).update(o)
    options = merged
    try:
        name = check_name(doc.get("name", path.stem))
    except ValueError as e:
        raise ValueError(f"{where}: {e}") from None
    file_batch = doc.get("batch")
    if file_batch is not None:
        check_int(f"{where}: batch", file_batch, 1, 10**6)
    if seeds is None and "seeds" in doc:
        check_int(f"{where}: seeds", doc["seeds"], 1, 10_000)
    suite = SuiteConfig(name, tuple(out),
                        tuple(sorted(budgets)), seeds or doc.get("seeds", 10), names,
                        jobs, options, batch or file_batch)
    suite.check()
    return suite


def execute_suite(config: SuiteConfig, out: Path | str | None, *, force: bool = False,
                  progress: Progress | None = None, stop=None,
                  startup_seconds: float = 0.0) -> dict:
    """Every entry of the suite as a comparison (its own folder under ``out``, named after
    the space), then ``suite.json`` and ``suite.md`` with a table per space. ``out`` None:
    a new folder ``runs/suite-<time>`` (``-2``, ... when taken; the summary's ``"out"``)."""
    config.check()
    progress = progress or Progress()
    clock = Clock(startup_seconds)
    if out is None:
        out, lk = store.open_new_folder(Path("runs") / f"suite-{timestamp()}", "suite")
    else:
        out = Path(out)
        lk = store.open_folder(out, "suite", force=force)
    try:
        entries = []  # every entry's folder checked before anything is written
        for k, e in enumerate(config.entries):
            c = config.compare_config(e)
            name = c.run_config(c.strategies[0]).build().space.name
            folder = out / f"{k + 1:02d}-{name}-{sut_lib.folder_name(e.sut)}"[:120]
            store.check_out(folder, "compare", force=force)
            entries.append((c, name, folder))
        lk.claim("suite")
        if force:  # the earlier summary waits in .earlier/ until this suite completes
            store.set_aside(out, "suite")
        out.mkdir(parents=True, exist_ok=True)
        options = {k: dict(v) for k, v in config.strategy_params.items()}
        write_atomic(out / "config.toml", cfg.dumps_toml({
            "kind": "suite", "name": config.name, "budgets": list(config.budgets),
            "seeds": config.seeds, "strategies": list(config.strategies),
            "strategy_params": options or None,
            "entry": None}) + "".join(
            "\n[[entry]]\n" + cfg.dumps_toml({"space": e.space, "sut": e.sut,
                                             "space_seed": e.space_seed,
                                             "exclude": list(e.exclude)})
            + ("" if not e.sut_params else "sut_params = { " + ", ".join(
                f"{k} = {float(v)!r}" for k, v in e.sut_params.items()) + " }\n")
            + ("" if e.requirement == "collision" else cfg.dumps_toml(
                {"requirement": e.requirement}))
            + ("" if not e.requirement_params else "requirement_params = { " + ", ".join(
                f"{k} = {float(v)!r}" for k, v in e.requirement_params.items()) + " }\n")
            for e in config.entries))
        results = []
        for k, (e, (c, name, folder)) in enumerate(zip(config.entries, entries)):
            progress.phase(f"suite entry {k + 1}/{len(config.entries)}: {name} x {e.sut}")
            res = execute(c, folder, force=force, progress=progress, stop=stop)
            results.append(res)
        summary = {"suite": config.name, "budgets": list(config.budgets),
                   "seeds": config.seeds, "strategies": list(config.strategies),
                   "strategy_params": options, "entries": results, "versions": cfg.versions()}
        with clock("writing"):
            write_json(out / "suite.json", summary, indent=2)
            write_atomic(out / "suite.md", suite_markdown(summary) + "\n")
            store.drop_earlier(out)
        summary["timing"] = clock.summary()
        summary["out"] = str(out)
        return summary
    finally:
        lk.release()


def suite_markdown(summary: dict) -> str:
    """A section per space: what it is, its ground truth, and the per-budget table."""
    jobs = max((r.get("jobs", 1) for r in summary["entries"]), default=1)
    parts = [f"# Search benchmark: {summary['suite']} ({summary['seeds']} seeds per strategy)",
             "", TIME_NOTE + (f" With {jobs} strategies side by side these seconds include "
                              "sharing the machine (--jobs 1 times each alone)."
                              if jobs > 1 else "")]
    options = summary.get("strategy_params") or {}
    if options:
        parts.append("Strategy options (every space): " + "; ".join(
            f"`{s}` " + ", ".join(f"{k}={v}" for k, v in o.items())
            for s, o in options.items()))
    for r in summary["entries"]:
        share = r.get("collision_share")
        if r.get("n_collisions") is not None:
            truth = (f"{plural(r['n_collisions'], 'collision')} of "
                     f"{plural(r['n_scenarios'], 'scenario')} (p = {share_text(share)})")
        else:
            truth = (f"{r['n_scenarios']:.3g} scenarios, too many to sweep; collision share "
                     f"estimated {share_text(share)} from {r['sampled']:,} uniform draws")
        extra = ""
        if r.get("global_max_reward") is not None:
            where = ("no collision anywhere in the space" if r["n_collisions"] == 0 else
                     "failures away from every edge (interior island)"
                     if r.get("failures_interior") else "failures touch an edge of the box")
            extra = (f"; global maximum {r['global_max_reward']:.4f} "
                     f"({plural(r['global_max_ties'], 'scenario')}); {where}")
        sp = ", ".join(f"{k}={v:g}" for k, v in r.get("sut_params", {}).items())
        req = requirement_words(r)
        if req:  # the entry's counts are of violations
            truth = f"critical: violating {req}; " + truth
        parts += ["", f"## {r['space']} x {r['sut']}{f' ({sp})' if sp else ''}"
                  f"{f', {req}' if req else ''}", "",
                  truth + extra + ".", "", budgets_markdown(r)]
    return "\n".join(parts)
