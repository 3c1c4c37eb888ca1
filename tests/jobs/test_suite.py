"""The search benchmark suite and what it needs: SUT parameters as dimensions of a logical
scenario, spaces too large to sweep (searched, with a sampled estimate instead of a ground
truth), and ``jaxfalsify compare --suite``."""

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import TINY_SPACE, run_campaign, space_file_fixture

import jaxfalsify as jf
from jaxfalsify.cli import main
from jaxfalsify.engine.truth import sweep_arrays
from jaxfalsify.jobs import compare, runs, suites

SUT_SPACE = TINY_SPACE + """[parameters.sut.ttc_full]
values = [0.5, 0.9, 2.0]
"""


sut_space = space_file_fixture(SUT_SPACE, "cal")


def test_sut_parameters_are_dimensions_of_a_space(sut_space):
    sp = jf.load_space(str(sut_space))
    assert sp.names[-1] == "sut.ttc_full" and sp.shape == (2, 2, 4, 2, 3)
    rows = sweep_arrays(sp, "sensor-aeb", fields=("min_distance", "collision"))
    got = rows["min_distance"].reshape(sp.shape)
    # oracle: each calibration evaluated on its own, with the SUT parameter set directly
    base = {n: np.asarray(v) for n, v in zip(sp.names[:4], np.meshgrid(
        *sp.values[:4], indexing="ij"))}
    for k, t in enumerate(sp.values[4]):
        want = jf.evaluate(base, sut="sensor-aeb", sut_params={"ttc_full": float(t)})
        np.testing.assert_array_equal(got[..., k], want.min_distance)
        # a scenario may carry its SUT parameter value itself
        same = jf.evaluate({**base, "sut.ttc_full": float(t)}, sut="sensor-aeb")
        np.testing.assert_array_equal(same.min_distance, want.min_distance)
    # the description round-trips through TOML (the run's config.toml)
    import tomllib

    from jaxfalsify.base import config

    doc = tomllib.loads(config.dumps_toml({"space": sp.describe()}))
    assert jf.scenario.space.space_from_dict(doc["space"]).table == sp.table
    # a SUT without that parameter: one line naming it, before anything runs
    with pytest.raises(ValueError, match="space parameter sut.ttc_full: the SUT 'carla-tm'"):
        runs.RunConfig(space=str(sut_space), sut="carla-tm").build()
    with pytest.raises(ValueError, match="one finite value per call"):
        jf.evaluate({**base, "sut.ttc_full": np.arange(16.0).reshape(2, 2, 4)},
                    sut="sensor-aeb")
    # given both in the scenario and in sut_params: refused, not one silently winning
    with pytest.raises(ValueError, match=r"sut.ttc_full given twice \(in the scenario and in "
                                         r"sut_params\)"):
        jf.evaluate({**base, "sut.ttc_full": 2.0}, sut="sensor-aeb",
                    sut_params={"ttc_full": 2.4})


HUGE = """name = "huge"
[parameters.ego_offset]
distribution = "uniform"
low = 5
high = 40
samples = 2000
[parameters.ped_speed]
distribution = "uniform"
low = 0.5
high = 3.0
samples = 5000
[parameters.ped_offset]
distribution = "uniform"
low = 0.0
high = 10.0
samples = 1000
"""


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_a_space_too_large_to_sweep_is_searched_with_a_sampled_estimate(tmp_path,
                                                                        monkeypatch):
    path = tmp_path / "huge.toml"
    path.write_text(HUGE)
    sp = jf.load_space(str(path))
    assert sp.size == 10**10
    with pytest.raises(ValueError, match="too many to sweep"):
        sweep_arrays(sp)
    assert main(["sweep", "--space", str(path), "--out", str(tmp_path / "s"),
                 "--quiet"]) == 2
    assert not (tmp_path / "s").exists()
    res = run_campaign(sp, "reinforce/screened", batch=32, evaluations=64, seed=1)
    assert res.indices.shape == (64, 3) and np.all(res.indices < np.array(sp.shape))
    # compare: no ground truth; the share is estimated from a uniform sample, whose
    # Clopper-Pearson interval holds the estimate
    monkeypatch.setattr(compare, "TRUTH_SAMPLE", 8192)
    out = compare.execute(compare.CompareConfig(strategies=("random",), seeds=2,
                                                evaluations=64, space=str(path),
                                                overhead=False), tmp_path / "c")
    assert out["n_collisions"] is None and out["sampled"] == 8192
    lo, hi = out["collision_share_ci95"]
    assert lo <= out["collision_share"] <= hi and out["global_max_reward"] is None
    assert out["rows"][0]["seeds_reaching_global_max"] is None
    assert "estimated from 8,192 uniform scenarios" in (tmp_path / "c" / "compare.md").read_text()


def test_a_suites_relative_paths_are_the_suite_files(tmp_path, monkeypatch):
    """A suite entry's space and SUT file, given relative, are found next to the suite file
    from any working folder; the entry's folder is named by the SUT file's stem."""
    import shutil

    from jaxfalsify.jobs.suites import load_suite
    from jaxfalsify.suts import registry as sut_lib

    sub = (tmp_path / "sub").resolve()
    sub.mkdir()
    (sub / "tiny.toml").write_text(TINY_SPACE)
    shutil.copy(Path(__file__).parents[2] / "experiments" / "example_aeb.py", sub / "mine.py")
    (sub / "suite.toml").write_text('strategies = ["random"]\n[[entry]]\nspace = "tiny.toml"\n'
                                    'sut = "mine.py:AEB"\n')
    monkeypatch.chdir(tmp_path)
    entry = load_suite("sub/suite.toml").entries[0]
    assert entry.space == str(sub / "tiny.toml") and entry.sut == f"{sub / 'mine.py'}:AEB"
    assert "ttc_brake" in sut_lib.param_names(sut_lib.resolve(entry.sut))
    assert sut_lib.folder_name(entry.sut) == "mine-AEB"


def test_the_shipped_suite_loads_with_every_space_and_sut():
    """experiments/suite/suite.toml, as shipped: every entry's space file builds (shape from
    its own TOML's sample counts), its SUT and calibration resolve and are in range, and the
    suite spans at least 6 spaces and 2 SUTs."""
    import tomllib

    from jaxfalsify.suts import registry as sut_lib

    path = Path(__file__).parents[2] / "experiments" / "suite" / "suite.toml"
    suite = suites.load_suite(str(path))
    raw = tomllib.loads(path.read_text())["entry"]
    assert len(suite.entries) == len(raw) >= 6
    assert len({e.sut for e in suite.entries}) >= 2
    for entry, doc in zip(suite.entries, raw):
        assert Path(entry.space).name == doc["space"]
        space_doc = tomllib.loads(Path(entry.space).read_text())
        space = jf.load_space(entry.space)
        assert space.name == Path(entry.space).stem == space_doc["name"]
        specs = [spec for name, spec in space_doc["parameters"].items() if name != "sut"]
        specs += list(space_doc["parameters"].get("sut", {}).values())
        assert space.shape == tuple(spec.get("samples", len(spec.get("values", ())))
                                    for spec in specs)
        sut, params = sut_lib.make(entry.sut, **dict(entry.sut_params))
        for name, value in entry.sut_params.items():
            assert float(getattr(params, name)) == value


def test_suite_entries_picks_spaces_by_name(tmp_path, capsys):
    """``--entries`` / ``load_suite(entries=...)`` keeps the entries of the named spaces (the
    name a space file declares, not its file name), in the file's order with their own SUTs;
    a name matching none is refused in one line naming it and the suite's names, before
    anything is written, and ``--entries`` needs ``--suite``."""
    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    (tmp_path / "other.toml").write_text(TINY_SPACE.replace('name = "tiny"', 'name = "tiny2"'))
    suite = tmp_path / "suite.toml"
    suite.write_text('strategies = ["random"]\n[[entry]]\nspace = "tiny.toml"\n'
                     '[[entry]]\nspace = "other.toml"\nsut = "sensor-aeb"\n'
                     'sut_params = { ttc_full = 1.5 }\n[[entry]]\nspace = "tiny.toml"\n'
                     'sut = "none"\n')
    full = suites.load_suite(suite).entries
    picked = suites.load_suite(suite, entries=("tiny2",)).entries
    assert picked == (full[1],) and dict(picked[0].sut_params) == {"ttc_full": 1.5}
    both = suites.load_suite(suite, entries=("tiny2", "tiny")).entries
    assert both == full  # the file's order, every entry of a named space
    with pytest.raises(ValueError, match=r"no entry of space 'other' .*entries: tiny, tiny2\)"):
        suites.load_suite(suite, entries=("other",))
    capsys.readouterr()
    out = tmp_path / "o"
    assert main(["compare", "--suite", str(suite), "--entries", "tiny2,nope", "--out",
                 str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'nope'" in err[0] and not out.exists()
    assert main(["compare", "--entries", "tiny2", "--out", str(out)]) == 2
    assert "needs --suite" in capsys.readouterr().err and not out.exists()


@pytest.mark.slow  # heavy: kept out of the default run, in .ci/run's slow pass
def test_compare_suite_end_to_end(tmp_path, capsys):
    space = tmp_path / "tiny.toml"
    space.write_text(TINY_SPACE)
    suite = tmp_path / "suite.toml"
    suite.write_text('name = "t"\nbudgets = [16, 48]\nseeds = 2\nstrategies = ["random", '
                     '"cem"]\n[[entry]]\nspace = "tiny.toml"\n[[entry]]\nspace = "tiny.toml"\n'
                     'sut = "sensor-aeb"\nsut_params = { ttc_full = 1.5 }\nexclude = ["cem"]\n')
    assert main(["compare", "--suite", str(suite), "--out", str(tmp_path / "o"),
                 "--strategy-param", "cem:elite_frac=0.5", "--quiet"]) == 0
    doc = json.loads((tmp_path / "o" / "suite.json").read_text())
    import tomllib  # the option, recorded in the suite's and the entry's config.toml

    assert tomllib.loads((tmp_path / "o" / "config.toml").read_text())[
        "strategy_params"] == {"cem": {"elite_frac": 0.5}} == doc["strategy_params"]
    first_dir = next(p for p in (tmp_path / "o").iterdir() if p.name.startswith("01-"))
    assert tomllib.loads((first_dir / "config.toml").read_text())[
        "strategy_params"] == {"cem": {"elite_frac": 0.5}}
    assert [e["sut"] for e in doc["entries"]] == ["carla-tm", "sensor-aeb"]
    assert [r["strategy"] for r in doc["entries"][1]["rows"]] == ["random"]  # cem excluded
    first = doc["entries"][0]
    assert [b["budget"] for b in first["budgets"]] == [16, 48]
    # the 16-evaluation figures are those of the first 16 evaluations of the same seeds
    for b16, b48 in zip(first["budgets"][0]["rows"][0]["per_seed"],
                        first["budgets"][1]["rows"][0]["per_seed"]):
        f48 = b48["first_collision"]
        assert b16["first_collision"] == (f48 if f48 is not None and f48 <= 16 else None)
    md = (tmp_path / "o" / "suite.md").read_text()
    assert "## tiny x sensor-aeb (ttc_full=1.5)" in md and "uniform random (analytic)" in md
    # bad suites and flags: one line, exit 2, nothing written
    bad = tmp_path / "bad.toml"
    bad.write_text('[[entry]]\nspace = "tiny.toml"\nsuts = "x"\n')
    capsys.readouterr()
    assert main(["compare", "--suite", str(bad), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown key 'suts'" in err[0]
    assert main(["compare", "--suite", str(suite), "--space", "paper",
                 "--out", str(tmp_path / "b")]) == 2
    assert not (tmp_path / "b").exists()
    # a suite that stopped after its first entries, rerun with other flags: refused by an
    # entry's folder before anything (the suite's config.toml included) is rewritten
    (tmp_path / "o" / "suite.json").unlink()
    config = (tmp_path / "o" / "config.toml").read_bytes()
    capsys.readouterr()
    assert main(["compare", "--suite", str(suite), "--seeds", "3", "--out",
                 str(tmp_path / "o")]) == 2
    assert "already holds compare.json" in capsys.readouterr().err
    assert (tmp_path / "o" / "config.toml").read_bytes() == config


def test_suite_strategy_options_from_the_file_and_the_command_line(tmp_path, capsys):
    """A suite's ``[strategy_params."NAME"]`` tables and ``--strategy-param`` (merged over
    them, option by option) reach every entry's comparison, except an entry excluding that
    strategy; options of a strategy the suite does not run, or not tables, are refused in
    one line before anything is written."""
    (tmp_path / "tiny.toml").write_text(TINY_SPACE)
    suite = tmp_path / "suite.toml"
    suite.write_text('strategies = ["random", "cem"]\n[strategy_params."cem"]\n'
                     'elite_frac = 0.2\nsmoothing = 0.5\n[[entry]]\nspace = "tiny.toml"\n'
                     '[[entry]]\nspace = "tiny.toml"\nsut = "none"\nexclude = ["cem"]\n')
    s = suites.load_suite(suite, strategy_params={"cem": {"elite_frac": 0.4}})
    assert s.strategy_params == {"cem": {"elite_frac": 0.4, "smoothing": 0.5}}
    first, second = (s.compare_config(e) for e in s.entries)
    assert first.strategy_params == {"cem": {"elite_frac": 0.4, "smoothing": 0.5}}
    assert second.strategies == ("random",) and second.strategy_params == {}
    built = first.run_config("cem").build()
    assert np.isclose(float(built.strategy_params.elite_frac), 0.4)
    assert np.isclose(float(built.strategy_params.smoothing), 0.5)
    with pytest.raises(ValueError, match="strategy_params: 'anneal' is not among"):
        suites.load_suite(suite, strategy_params={"anneal": {"decay": 0.9}})
    # the file's options of a strategy left out by --strategies go with it
    assert suites.load_suite(suite, strategies=("random",)).strategy_params == {}
    # a table naming no strategy of the file is refused, not dropped; an alias is the same
    # strategy (the options are keyed by the name the comparison runs under)
    typo = tmp_path / "typo.toml"
    typo.write_text('strategies = ["random", "cem"]\n[strategy_params."cme"]\nelite_frac = 0.2\n'
                    '[[entry]]\nspace = "tiny.toml"\n')
    with pytest.raises(ValueError, match=r"typo.toml: strategy_params: 'cme' is not among"):
        suites.load_suite(typo)
    alias = tmp_path / "alias.toml"
    alias.write_text('strategies = ["reinforce/screened"]\n[strategy_params."reinforce/screened"]\n'
                     'kappa = 0.5\n[[entry]]\nspace = "tiny.toml"\n')
    got = suites.load_suite(alias, strategy_params={"reinforce/screened": {"lr": 0.01}})
    assert got.strategy_params == {"reinforce/screened": {"kappa": 0.5, "lr": 0.01}}
    built = got.compare_config(got.entries[0]).run_config("reinforce/screened").build()
    assert np.isclose(float(built.strategy_params.kappa), 0.5)
    bad = tmp_path / "bad.toml"
    bad.write_text('strategy_params = { cem = 3 }\n[[entry]]\nspace = "tiny.toml"\n')
    with pytest.raises(ValueError, match="strategy_params must hold a table per strategy"):
        suites.load_suite(bad)
    capsys.readouterr()
    out = tmp_path / "o"
    assert main(["compare", "--suite", str(suite), "--strategy-param", "cem:elite_frac=2",
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "elite_frac" in err[0] and not out.exists()
    # a bad option or value in the file's table is named by the file and the table
    for line, what in (("elite_frac = 7.0", "elite_frac=7.0 is outside"),
                       ("elit = 0.2", "no option 'elit'")):
        wrong = tmp_path / "wrong.toml"
        wrong.write_text(f'strategies = ["random", "cem"]\n[strategy_params."cem"]\n{line}\n'
                         '[[entry]]\nspace = "tiny.toml"\n')
        assert main(["compare", "--suite", str(wrong), "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and 'wrong.toml: strategy_params."cem": ' + what in err[0], err
        assert not out.exists()


def test_the_shipped_spaces_load_with_their_stated_sizes():
    """experiments/spaces/*.toml, as shipped: each builds under its file's name, with the shape
    of its own TOML's sample counts, and the size its description states (to its one or two
    significant figures)."""
    import math
    import re
    import tomllib

    folder = Path(__file__).parents[2] / "experiments" / "spaces"
    files = sorted(folder.glob("*.toml"))
    assert len(files) >= 4
    for path in files:
        doc = tomllib.loads(path.read_text())
        space = jf.load_space(str(path))
        assert space.name == path.stem == doc["name"]
        specs = [spec for name, spec in doc["parameters"].items() if name != "sut"]
        specs += list(doc["parameters"].get("sut", {}).values())
        assert space.shape == tuple(spec.get("samples", len(spec.get("values", ())))
                                    for spec in specs)
        stated = re.search(r"(\d+(?:\.\d+)?)e(\d+) concrete scenarios",
                           doc.get("description", ""))
        if stated:
            mantissa, exp = stated.groups()
            size = math.prod(space.shape)
            assert size / 10 ** int(exp) == pytest.approx(float(mantissa),
                                                           abs=0.5 * 10 ** -len(
                                                               mantissa.partition(".")[2]))
