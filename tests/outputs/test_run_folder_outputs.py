"""The outputs of one run folder (a module-scoped run with figures): figures are non-trivial
images of the right size, the report's links resolve, replay recordings and OpenSCENARIO
exports read back with the simulated values (export helpers from test_openscenario_export)."""

import json
import re

import numpy as np
import pytest
from conftest import grid_run

from jaxfalsify.cli import main

SIZES = {"reward_per_evaluation.png": (500, 800), "distance_challenging.png": (500, 1200),
         "high_risk_second_half.png": (450, 500), "distance_14_scenarios.png": (500, 800),
         "failure_clusters.png": (500, 1200)}


@pytest.fixture(scope="module")
def run_with_figures(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig") / "run"
    assert main(["run", "--strategy", "cem", "--evaluations", "200", "--batch", "50",
                 "--out", str(out), "--quiet"]) == 0
    return out


def test_figures_are_nontrivial_images_of_the_right_size(run_with_figures):
    import matplotlib.image as mpimg

    figs = run_with_figures / "figures"
    for name, (h, w) in SIZES.items():
        img = mpimg.imread(figs / name)
        assert img.shape[:2] == (h, w), name
        rgb = img[..., :3].reshape(-1, 3)
        assert len(np.unique(rgb, axis=0)) > 20, f"{name} looks blank"
    for name in ("critical_regions.png", "search_distribution.png"):
        img = mpimg.imread(figs / name)
        assert img.shape[0] > 300 and img.shape[1] > 800, name
        assert len(np.unique(img[..., :3].reshape(-1, 3), axis=0)) > 50, name


def test_figure_content_units_values_and_drawing_order(run_with_figures):
    """What a safety engineer reads: axes carry units, ticks are the space's values (with its
    decimals), the colour scale is fitted to the data, collisions are drawn on top."""
    from jaxfalsify.engine.truth import ground_truth
    from jaxfalsify.outputs import analysis
    from jaxfalsify.outputs.figures import _plt, critical_region_figure, load_run, search_figure

    plt = _plt()
    sp, rc, _, ep = load_run(run_with_figures)
    truth = ground_truth(sp, rc.sut, dict(rc.sut_params))
    fig = critical_region_figure(plt, sp, truth, ep)
    axes = [ax for ax in fig.axes if ax.get_xlabel() and ax.images]
    assert len(axes) == 10  # every pair of the 5 parameters
    labels = {f"{n} [{u}]" for n, u in zip(sp.names, sp.units)}
    allowed = {n: {analysis.format_value(sp, p, v) for v in sp.table[p]}
               for p, n in enumerate(sp.names)}
    for ax in axes:
        assert ax.get_xlabel() in labels and ax.get_ylabel() in labels
        for tick_labels, axis_label in ((ax.get_xticklabels(), ax.get_xlabel()),
                                        (ax.get_yticklabels(), ax.get_ylabel())):
            name = axis_label.split(" [")[0]
            texts = [t.get_text() for t in tick_labels]
            assert texts and set(texts) <= allowed[name], (name, texts)
    # the colour scale ends at the largest pair share, not at 1
    im = axes[0].images[0]
    top = max(float(a.images[0].get_array().max()) for a in axes)
    assert im.norm.vmax == pytest.approx(top, rel=1e-6) and top < 1
    assert "ego_offset [m]" in labels and "ped_speed [m/s]" in labels
    plt.close(fig)
    fig = search_figure(plt, sp, ep, rc.strategy)
    ylabels = [ax.get_ylabel() for ax in fig.axes if ax.images]
    assert ylabels == [f"{n} [{u}]" for n, u in zip(sp.names, sp.units)]
    # each stretch's shares sum to 1 over a parameter's values
    freq = np.asarray([ax for ax in fig.axes if ax.images][0].images[0].get_array())
    np.testing.assert_allclose(freq.sum(0), 1.0, atol=1e-9)
    plt.close(fig)


def test_report_links_resolve_and_table_matches_summary(run_with_figures):
    import json

    text = (run_with_figures / "report.md").read_text()
    links = re.findall(r"\]\(([^)]+)\)", text)
    assert len(links) == 7
    for link in links:
        assert (run_with_figures / link).is_file(), link
    s = json.loads((run_with_figures / "summary.json").read_text())
    assert f"{s['best']['reward']:.4f}" in text
    assert f"jaxfalsify run --config {run_with_figures}/config.toml" in text
    k = s["n_failure_clusters"]
    assert (f"| failure clusters | {k} (largest: {s['failure_clusters'][0]['size']} of the "
            f"{s['n_distinct_critical']} distinct" if k else
            "| failure clusters | none (no collision) |") in text


def test_figures_command_regenerates_and_rejects_non_runs(run_with_figures, tmp_path, capsys):
    target = run_with_figures / "figures" / "reward_per_evaluation.png"
    target.unlink()
    assert main(["figures", str(run_with_figures)]) == 0
    assert target.is_file()
    assert main(["figures", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "is not a finished run folder" in err and len(err.splitlines()) == 1


def test_a_failure_while_drawing_leaves_every_figure_as_it_was(run_with_figures, monkeypatch,
                                                                capsys):
    """The figures are written as one set after all are drawn: the last one failing leaves
    the earlier ones byte for byte (none redrawn) and no temporary file behind."""
    from jaxfalsify.outputs import figures

    figs = run_with_figures / "figures"
    originals = {p: p.read_bytes() for p in figs.iterdir()}
    for p in originals:  # marked, so a redrawn figure (same bytes as before) would show
        p.write_bytes(b"earlier " + p.name.encode())
    before = {p.name: p.read_bytes() for p in figs.iterdir()}

    def broken(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(figures, "cluster_figure", broken)  # the last one drawn
    try:
        assert main(["figures", str(run_with_figures)]) == 1  # a failure, not bad input
        err = capsys.readouterr().err.strip()
        assert "No space left on device" in err and len(err.splitlines()) == 1
        assert {p.name: p.read_bytes() for p in figs.iterdir()} == before
    finally:  # the module's run folder, for the tests after this one
        for p, data in originals.items():
            p.write_bytes(data)


def _read_rrd(path):
    from rerun.chunk import RrdReader

    cols = {}
    for c in RrdReader(path).stream().to_chunks():
        rb = c.to_record_batch()
        cols.setdefault(c.entity_path, []).append(rb)
    return cols


def _column(batches, name):
    import pyarrow as pa

    out = []
    for rb in batches:
        if name in rb.schema.names:
            col = rb.column(name)
            if pa.types.is_duration(col.type) or pa.types.is_timestamp(col.type):
                col = col.cast(pa.int64())  # nanoseconds
            out.extend(col.to_pylist())
    return out


def test_replay_recording_reads_back_with_simulated_values(run_with_figures, tmp_path):
    import pyarrow.parquet as pq

    import jaxfalsify as jf

    f = tmp_path / "best.rrd"
    assert main(["replay", str(run_with_figures), "--save", str(f), "--scenarios", "3"]) == 0
    cols = _read_rrd(f)
    for ent in ("/world/road", "/world/crosswalk", "/world/ego", "/world/pedestrian",
                "/world/hazard_corridor", "/world/walker_grown_box", "/metrics/distance",
                "/metrics/rss_distance", "/metrics/epsilon",
                "/metrics/high_risk", "/metrics/ego_speed", "/info", "/training/reward",
                "/overlay/0/distance"):
        assert ent in cols, ent
    # the logged series are the simulation of the run's best scenario
    ep = pq.read_table(run_with_figures / "evaluations.parquet").to_pydict()
    sp = jf.load_space("paper")
    r = np.asarray(ep["reward"])
    best = int(np.argmax(r))
    idx = np.array([[ep[f"{n}_idx"][best] for n in sp.names]])
    tr = jf.simulate(sp.scenario(idx))
    v = np.asarray(tr.valid[0])
    dist = np.concatenate([np.ravel(x) for x in _column(cols["/metrics/distance"],
                                                         "Scalars:scalars")])
    np.testing.assert_allclose(dist, np.asarray(tr.distance[0])[v], atol=1e-6)
    times = np.asarray(_column(cols["/metrics/distance"], "sim_time")) / 1e9
    np.testing.assert_allclose(times, np.asarray(tr.t[0])[v], atol=1e-6)
    centers = [np.asarray(c)[0] for c in _column(cols["/world/ego"], "Boxes2D:centers")]
    ego_offset = sp.table[sp.names.index("ego_offset")][idx[0][sp.names.index("ego_offset")]]
    # the start (t = 0: ego_offset behind the base start), then the simulated steps
    np.testing.assert_allclose([c[0] for c in centers],
                               [-ego_offset, *np.asarray(tr.ego_x[0])[v]], atol=1e-5)
    rewards = np.concatenate([np.ravel(x) for x in _column(cols["/training/reward"],
                                                            "Scalars:scalars")])
    np.testing.assert_allclose(rewards, r, atol=1e-6)
    # each entity on its own timeline only
    for ent, own, other in (("/training/reward", "evaluation", "sim_time"),
                            ("/overlay/0/distance", "sim_time", "evaluation"),
                            ("/metrics/distance", "sim_time", "evaluation")):
        names = {n for rb in cols[ent] for n in rb.schema.names}
        assert own in names and other not in names, (ent, names)
    text = " ".join(str(x) for x in _column(cols["/info"], "TextDocument:text"))
    assert "ego_offset" in text and "reward" in text
    # values as declared: no float32 noise such as 0.25999999046325684
    import re

    assert not re.search(r"\d\.\d{9,}", text), text
    # each parameter written as Table II and critical.csv write it (declared decimals)
    from jaxfalsify.outputs import analysis

    for p, (n, unit) in enumerate(zip(sp.names, sp.units)):
        want = analysis.format_value(sp, p, ep[n][best])
        assert f"| {n} | {want} {unit} |" in text, (n, want)
    assert any(sp.parameters[p].decimals and "." in analysis.format_value(sp, p, ep[n][best])
               for p, n in enumerate(sp.names))  # the check above covers some decimals


def test_campaign_recording_holds_every_evaluation_and_the_sampling_distribution(
        run_with_figures, tmp_path, capsys):
    import pyarrow.parquet as pq

    import jaxfalsify as jf

    f = tmp_path / "campaign.rrd"
    assert main(["replay", str(run_with_figures), "--campaign", "--window", "50",
                 "--save", str(f)]) == 0
    cols = _read_rrd(f)
    ep = pq.read_table(run_with_figures / "evaluations.parquet").to_pydict()
    sp = jf.load_space("paper")
    rewards = np.concatenate([np.ravel(x) for x in _column(cols["/campaign/reward"],
                                                            "Scalars:scalars")])
    np.testing.assert_allclose(rewards, ep["reward"], atol=1e-6)
    assert _column(cols["/campaign/reward"], "evaluation") == ep["evaluation"]
    best = np.concatenate([np.ravel(x) for x in _column(cols["/campaign/best"],
                                                         "Scalars:scalars")])
    np.testing.assert_allclose(best, np.maximum.accumulate(ep["reward"]), atol=1e-6)
    for n in sp.names:
        vals = np.concatenate([np.ravel(x) for x in _column(cols[f"/campaign/params/{n}"],
                                                             "Scalars:scalars")])
        np.testing.assert_allclose(vals, ep[n], atol=1e-6)
    # the last bar chart of each parameter: the shares of its values among the last 50 draws,
    # counted here by a Python loop
    for p, n in enumerate(sp.names):
        bars = _column(cols[f"/campaign/probabilities/{n}"], "BarChart:values")
        last = bars[-1]  # one chart per row: a list of one {shape, names, buffer} tensor
        last = np.asarray(last[0]["buffer"] if isinstance(last, list) else last["buffer"],
                          np.float64)
        counts = [0] * len(sp.table[p])
        for i in ep[f"{n}_idx"][-50:]:
            counts[i] += 1
        np.testing.assert_allclose(last, np.asarray(counts) / 50, atol=1e-12)
        assert len(bars) == len(set(ep["update"]))  # one chart per update
    for ent, batches in cols.items():
        if ent.startswith("/campaign/"):
            names = {nm for rb in batches for nm in rb.schema.names}
            assert "sim_time" not in names, ent
    assert main(["replay", str(run_with_figures), "--campaign", "--scenario", "eval:1"]) == 2
    assert "no --scenario" in capsys.readouterr().err


def test_replay_bad_scenario_spec(run_with_figures, capsys):
    assert main(["replay", str(run_with_figures), "--scenario", "worst"]) == 2
    assert "expected best, critical:K or eval:N" in capsys.readouterr().err
    assert main(["replay", str(run_with_figures), "--scenario", "eval:99999"]) == 2
    assert main(["replay", str(run_with_figures), "--save", "x.txt"]) == 2
    capsys.readouterr()
    # ASCII digits, no leading zeros: eval:01 and eval:\u0661 (Arabic-Indic one) would name
    # eval:1's recording differently
    for spec in ("eval:01", "eval:\u0661", "critical:0", "eval:+1", "eval: 1"):
        before = sorted(p.name for p in run_with_figures.iterdir())
        assert main(["replay", str(run_with_figures), "--scenario", spec]) == 2
        assert "no leading zeros" in capsys.readouterr().err
        assert sorted(p.name for p in run_with_figures.iterdir()) == before


def test_export_validates_against_the_xsd_and_matches_the_trajectory(run_with_figures,
                                                                     tmp_path):
    import xml.etree.ElementTree as ET

    import pyarrow.parquet as pq
    from test_openscenario_export import schema

    import jaxfalsify as jf
    from jaxfalsify.outputs.export import X_OFFSET

    out = tmp_path / "osc"
    assert main(["export", str(run_with_figures), "--scenario", "critical", "--ego", "replay",
                 "--out", str(out)]) == 0
    xosc_files = sorted(out.glob("critical_*.xosc"))
    ep = pq.read_table(run_with_figures / "evaluations.parquet").to_pydict()
    sp = jf.load_space("paper")
    idx = np.stack([ep[f"{n}_idx"] for n in sp.names], -1)[np.asarray(ep["collision"])]
    assert len(xosc_files) == len({tuple(i) for i in idx}) > 0
    xsd = schema("xosc")
    for f in xosc_files + [out / "template.xosc", out / "logical.xosc",
                           out / "logical_stochastic.xosc"]:
        xsd.validate(str(f))  # raises if invalid
    # the distributions vary the controller-mode template, not the trajectories
    assert ET.parse(out / "logical.xosc").getroot().find(
        ".//ScenarioFile").attrib["filepath"] == "template.xosc"
    schema("xodr").validate(str(out / "crossing.xodr"))
    # the exported ego waypoints are the simulated trajectory of critical scenario 1
    root = ET.parse(xosc_files[0]).getroot()
    desc = root.find("FileHeader").attrib["description"]
    params = dict(kv.split("=") for kv in desc.split(": ", 1)[1].split(", "))
    tr = jf.simulate({k: float(v) for k, v in params.items()})
    v = np.asarray(tr.valid)
    polylines = root.findall(".//Polyline")
    ego_x = [float(p.find("Position/WorldPosition").attrib["x"]) - X_OFFSET
             for p in polylines[0].findall("Vertex")]
    times = [float(p.attrib["time"]) for p in polylines[0].findall("Vertex")]
    # the start at t = 0 (the Init's teleport), then the simulated steps
    w = jf.WORLD
    start_y = w.road_right + w.walker_base - float(params["ped_offset"]) - 1.0
    np.testing.assert_allclose(ego_x, [-float(params["ego_offset"]), *np.asarray(tr.ego_x)[v]],
                               atol=1e-4)
    np.testing.assert_allclose(times, [0.0, *np.asarray(tr.t)[v]], atol=1e-3)
    ped_y = [float(p.find("Position/WorldPosition").attrib["y"])
             for p in polylines[1].findall("Vertex")]
    np.testing.assert_allclose(ped_y, [start_y, *np.asarray(tr.ped_y)[v]], atol=1e-4)
    init = root.find(".//Init//Private[@entityRef='Ego']//WorldPosition").attrib
    assert float(init["x"]) - X_OFFSET == pytest.approx(-float(params["ego_offset"]))
    # the crosswalk object centred across the road (-9 .. 3 m: t = -3, width 12)
    cw = ET.parse(out / "crossing.xodr").getroot().find(".//object").attrib
    assert (float(cw["t"]), float(cw["width"])) == ((w.road_left + w.road_right) / 2,
                                                    w.road_left - w.road_right)
    # weather preset -> environment
    assert root.find(".//Environment") is not None


def _xosc_rows(out):
    """``[(file, row)]`` of the exported critical scenarios (row: evaluation - 1)."""
    import xml.etree.ElementTree as ET

    files = sorted(out.glob("critical_*.xosc"))
    return [(f, int(re.search(r"\(evaluation (\d+)\)",
                               ET.parse(f).getroot().find("FileHeader").attrib["description"])
                     .group(1)) - 1) for f in files]


def test_export_controller_parameters_reproduce_the_run(run_with_figures, tmp_path):
    """Controller mode: every critical scenario's file validates; its ParameterDeclarations
    are the space's values (with its decimals) and the actions' values map back to them; the
    declared values, simulated, give the outcome the run recorded for that row; the
    pedestrian's start speed, acceleration, target speed and start follow the closed form."""
    import xml.etree.ElementTree as ET

    import pyarrow.parquet as pq
    from test_openscenario_export import declarations, oracle_profile, schema, speed_events

    import jaxfalsify as jf
    from jaxfalsify.engine.rundir import load_run
    from jaxfalsify.outputs import analysis
    from jaxfalsify.outputs.export import X_OFFSET, value_of

    out = tmp_path / "osc"
    assert main(["export", str(run_with_figures), "--scenario", "critical",
                 "--out", str(out)]) == 0
    assert not (out / "template.xosc").exists()
    sp, rc, _, _ = load_run(run_with_figures)
    ep = pq.read_table(run_with_figures / "evaluations.parquet").to_pydict()
    rows = _xosc_rows(out)
    assert len(rows) == len(analysis.distinct_critical(*analysis.from_evaluations(
        {k: np.asarray(v) for k, v in ep.items()}, sp))) > 0
    xsd = schema("xosc")
    w = jf.WORLD
    scen = {n: [] for n in sp.names}
    for f, row in rows:
        xsd.validate(str(f))
        root = ET.parse(f).getroot()
        assert root.find(".//FollowTrajectoryAction/TimeReference/None") is not None
        assert len(root.findall(".//Polyline")) == 1  # the pedestrian's path only
        decl = declarations(root)
        texts = {p.attrib["name"]: p.attrib["value"] for p in root.iter("ParameterDeclaration")}
        for p, n in enumerate(sp.names):  # the run's row, with the space's decimals
            v = sp.table[p][ep[f"{n}_idx"][row]]
            assert texts[n] == analysis.format_value(sp, p, v) and decl[n] == v
            scen[n].append(decl[n])
        # the actions carry the declared values
        ego_s = value_of(root.find(".//Private[@entityRef='Ego']//LanePosition").attrib["s"],
                         decl)
        assert ego_s - X_OFFSET == pytest.approx(-decl["ego_offset"], abs=1e-12)
        ped_y = value_of(root.find(".//Private[@entityRef='Pedestrian']//WorldPosition")
                         .attrib["y"], decl)
        assert ped_y == pytest.approx(w.road_right + w.walker_base - decl["ped_offset"] - 1.0)
        ev = {e[0]: e for e in speed_events(root, decl)}
        ref, start, final = oracle_profile(decl["ped_speed"], decl["ped_accel"])
        accel = ev["ped_accelerates"][4] * w.dt
        assert accel == pytest.approx(decl["ped_accel"], abs=1e-12)
        if start > 0:
            assert ev["ped_start_speed"][3] + 5 * accel == pytest.approx(decl["ped_speed"])
            assert ev["ped_accelerates"][1] == pytest.approx(0.55)
        assert ev["ped_start_speed"][1] == 0.0 and ev["ped_start_speed"][3] == \
            pytest.approx(max(start, 0.0))
        assert ev["ped_accelerates"][3] == pytest.approx(final, abs=1e-9)
        assert ev["ped_accelerates"][3] == pytest.approx(max(ref), abs=1e-9)
        assert value_of(root.find(".//TraveledDistanceCondition").attrib["value"], decl) == \
            pytest.approx(w.end_x + decl["ego_offset"])
    # the declared values reproduce the run's outcomes
    o = jf.evaluate({n: np.asarray(v) for n, v in scen.items()}, sut=rc.sut,
                    sut_params=dict(rc.sut_params))
    r = [row for _, row in rows]
    np.testing.assert_array_equal(np.asarray(o.collision), np.asarray(ep["collision"])[r])
    np.testing.assert_allclose(np.asarray(o.min_distance), np.asarray(ep["min_distance"])[r],
                               atol=1e-6)
    assert np.all(np.asarray(o.collision))


def test_export_distribution_lists_the_space(run_with_figures, tmp_path):
    """logical.xosc: one deterministic DistributionSet per space parameter holding exactly its
    values, over the exported template; logical_stochastic.xosc: the declared distributions."""
    import xml.etree.ElementTree as ET

    from test_openscenario_export import schema

    from jaxfalsify.engine.rundir import load_run
    from jaxfalsify.outputs.export import write_distribution

    out = tmp_path / "osc"
    assert main(["export", str(run_with_figures), "--out", str(out)]) == 0
    sp, _, _, ep = load_run(run_with_figures)
    xsd = schema("xosc")
    xsd.validate(str(out / "logical.xosc"))
    xsd.validate(str(out / "logical_stochastic.xosc"))
    root = ET.parse(out / "logical.xosc").getroot()
    assert root.find(".//ScenarioFile").attrib["filepath"] == "best.xosc"
    assert (out / "best.xosc").exists()
    sets = {d.attrib["parameterName"]: [float(e.attrib["value"]) for e in d.iter("Element")]
            for d in root.iter("DeterministicSingleParameterDistribution")}
    assert list(sets) == list(sp.names)
    for n, vals in zip(sp.names, sp.exact_values):
        assert sets[n] == list(vals)
    # the template declares every parameter the distribution sets
    names = {p.attrib["name"] for p in ET.parse(out / "best.xosc").getroot()
             .iter("ParameterDeclaration")}
    assert set(sp.names) <= names
    st = ET.parse(out / "logical_stochastic.xosc").getroot().find(".//Stochastic")
    assert int(st.attrib["numberOfTestRuns"]) == len(ep["reward"])
    kinds = {d.attrib["parameterName"]: d[0] for d in st.iter("StochasticDistribution")}
    by_name = {p.name: p for p in sp.parameters}
    for n, el in kinds.items():
        par = by_name[n]
        if par.distribution == "normal":
            assert el.tag == "NormalDistribution"
            assert float(el.attrib["expectedValue"]) == par.args[0]
            assert float(el.attrib["variance"]) == pytest.approx(par.args[1] ** 2)
        elif par.distribution == "uniform":
            assert el.tag == "UniformDistribution"
            rng = el.find("Range").attrib
            assert (float(rng["lowerLimit"]), float(rng["upperLimit"])) == par.args
        else:
            assert el.tag == "ProbabilityDistributionSet"
            vals = [float(e.attrib["value"]) for e in el.iter("Element")]
            want = (list(range(int(par.args[0]), int(par.args[1]) + 1))
                    if par.distribution == "integers" else list(par.args))
            assert vals == want
    assert list(kinds) == list(sp.names)
    # the template applies every weather either distribution can set (the stochastic one
    # draws all 15 presets of the paper's range, the deterministic one the 10 drawn)
    events = {int(e.attrib["name"].split("_")[1]) for e in ET.parse(out / "best.xosc")
              .getroot().iter("Event") if e.attrib["name"].startswith("weather_")}
    drawn = {int(float(e.attrib["value"])) for e in kinds["weather"].iter("Element")}
    assert drawn == set(range(15)) and events == drawn >= set(sets["weather"])
    with pytest.raises(ValueError, match="deterministic or stochastic"):
        write_distribution(tmp_path / "x.xosc", sp, "best.xosc", "fuzzy")


def test_export_refuses_existing_output(run_with_figures, tmp_path, capsys):
    out = tmp_path / "osc"
    assert main(["export", str(run_with_figures), "--out", str(out)]) == 0
    assert main(["export", str(run_with_figures), "--out", str(out)]) == 2
    assert "--force" in capsys.readouterr().err
    assert main(["export", str(run_with_figures), "--scenario", "all", "--out",
                 str(tmp_path / "o2")]) == 2
    # any file an export would write counts, not only the road (a user's own best.xosc)
    own = tmp_path / "own"
    own.mkdir()
    (own / "best.xosc").write_text("mine")
    capsys.readouterr()
    assert main(["export", str(run_with_figures), "--out", str(own)]) == 2
    assert "already holds best.xosc" in capsys.readouterr().err
    assert (own / "best.xosc").read_text() == "mine" and len(list(own.iterdir())) == 1
    # a job's checkpoint folder (or below it) is the job's: its --force would remove it
    job = tmp_path / "job"
    job.mkdir()
    (job / "config.toml").write_text('kind = "run"\n')
    for inside in (job / "checkpoint", job / "checkpoint" / "osc",
                   job / "checkpoint-part-0-of-2"):
        assert main(["export", str(run_with_figures), "--out", str(inside)]) == 2
        assert "inside the checkpoint folder of the run" in capsys.readouterr().err
    assert sorted(p.name for p in job.iterdir()) == ["config.toml"]
    # another tool's config.toml above a folder named checkpoint: not a job, exported into
    proj = tmp_path / "proj"
    (proj / "checkpoint").mkdir(parents=True)
    (proj / "config.toml").write_text('name = "another tool"\n')
    assert main(["export", str(run_with_figures), "--out", str(proj / "checkpoint" / "x")]) == 0
    assert (proj / "checkpoint" / "x" / "best.xosc").is_file()


def test_replay_refuses_to_overwrite_a_saved_file_and_says_when_no_viewer(
        run_with_figures, tmp_path, capsys, monkeypatch):
    import rerun as rr

    f = tmp_path / "mine.rrd"
    f.write_text("precious")
    assert main(["replay", str(run_with_figures), "--save", str(f)]) == 2
    assert "--force" in capsys.readouterr().err and f.read_text() == "precious"
    assert main(["replay", str(run_with_figures), "--save", str(f), "--force"]) == 0
    assert f.stat().st_size > 1000

    def no_viewer(self, *a, **k):
        raise RuntimeError("Failed to find Rerun Viewer executable in PATH")

    monkeypatch.setattr(rr.RecordingStream, "spawn", no_viewer)
    capsys.readouterr()
    assert main(["replay", str(run_with_figures), "--spawn"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Rerun Viewer" in err[0] and "--save" in err[0]


def test_export_force_replaces_the_earlier_export(run_with_figures, tmp_path):
    """``--force`` replaces an earlier export's files (no stale critical_NNN.xosc beside the
    new best.xosc) and leaves the user's own files alone."""
    from jaxfalsify.engine.rundir import load_run
    from jaxfalsify.outputs import analysis

    sp, _, _, ep = load_run(run_with_figures)
    n_crit = len(analysis.distinct_critical(*analysis.from_evaluations(ep, sp)))
    out = tmp_path / "osc"
    assert main(["export", str(run_with_figures), "--scenario", "critical", "--out",
                 str(out)]) == 0
    assert len(list(out.glob("critical_*.xosc"))) == n_crit > 0
    (out / "notes.txt").write_text("mine\n")
    assert main(["export", str(run_with_figures), "--out", str(out), "--force"]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "best.xosc", "crossing.xodr", "logical.xosc", "logical_stochastic.xosc", "notes.txt"]
    assert (out / "notes.txt").read_text() == "mine\n"


def test_report_simulate_line_reproduces_the_best_scenario(run_with_figures, capsys):
    """report.md's `jaxfalsify simulate` line, run as written, gives the run's recorded
    outcome; with a SUT parameter away from its default the line carries it (and only it)."""
    import dataclasses
    import json
    import shlex

    import jaxfalsify as jf
    from jaxfalsify.engine.rundir import load_run
    from jaxfalsify.outputs import analysis
    from jaxfalsify.outputs.report import simulate_command

    sp, rc, _, ep = load_run(run_with_figures)
    row = analysis.best(ep)
    [line] = [x for x in (run_with_figures / "report.md").read_text().splitlines()
              if x.startswith("jaxfalsify simulate ")]
    assert line == simulate_command(sp, rc, ep, row)[0] and "--sut-param" not in line
    capsys.readouterr()
    assert main(shlex.split(line)[1:]) == 0
    got = json.loads(capsys.readouterr().out)["outcome"]
    assert got["reward"] == pytest.approx(ep["reward"][row], abs=1e-6)
    assert got["collision"] == bool(ep["collision"][row])

    changed = dataclasses.replace(rc, sut_params={**rc.sut_params, "walker_time": 2.5})
    [line] = simulate_command(sp, changed, ep, row)
    assert line.count("--sut-param") == 1 and line.endswith("--sut-param walker_time=2.5")
    assert main(shlex.split(line)[1:]) == 0
    got = json.loads(capsys.readouterr().out)["outcome"]
    oracle = jf.evaluate({n: ep[n][row] for n in sp.names}, sut="carla-tm",
                         sut_params={"walker_time": 2.5})
    assert got["min_distance"] == pytest.approx(float(oracle.min_distance), abs=1e-6)


def test_figures_and_recordings_are_readable_like_other_files(run_with_figures, tmp_path):
    """Files written through a temporary name get the mode a plain open() gives (umask),
    not mkstemp's 0600."""
    import os
    import stat

    mode = lambda p: stat.S_IMODE(os.stat(p).st_mode)  # noqa: E731
    umask = os.umask(0)
    os.umask(umask)
    want = 0o666 & ~umask
    assert mode(run_with_figures / "figures" / "reward_per_evaluation.png") == want
    assert mode(run_with_figures / "report.md") == want
    assert main(["replay", str(run_with_figures), "--scenario", "best",
                 "--save", str(tmp_path / "best.rrd")]) == 0
    assert mode(tmp_path / "best.rrd") == want


def test_python_dash_m_runs_the_cli():
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "jaxfalsify", "--version"], capture_output=True,
                       text=True)
    assert r.returncode == 0 and r.stdout.strip().endswith(__import__("jaxfalsify").__version__)


def test_export_writes_explicit_values_as_written(tmp_path):
    """A space's explicit ``values`` with more than 3 decimals: the exported critical
    scenario declares them as written (0.0125, not 0.013) and, simulated, still collides as
    the run's row did."""
    import xml.etree.ElementTree as ET

    import pyarrow.parquet as pq

    import jaxfalsify as jf

    run = grid_run(tmp_path, "vals", 'name = "vals"\n[parameters.ego_offset]\nvalues = [9]\n'
                   '[parameters.ped_offset]\nvalues = [3.5]\n'
                   '[parameters.ped_accel]\nvalues = [0.0075, 0.0125]\n'
                   '[parameters.ped_speed]\nvalues = [1.1335, 1.2375]\n', 4, "--no-figures")
    assert main(["export", str(run), "--scenario", "critical", "--out",
                 str(tmp_path / "x")]) == 0
    ep = pq.read_table(run / "evaluations.parquet").to_pydict()
    hits = [i for i, c in enumerate(ep["collision"]) if c]
    assert hits
    files = sorted((tmp_path / "x").glob("critical_*.xosc"))
    assert len(files) == len(hits)
    for f in files:
        decl = {p.attrib["name"]: p.attrib["value"]
                for p in ET.parse(f).getroot().iter("ParameterDeclaration")}
        assert decl["ped_accel"] in ("0.0075", "0.0125")
        assert decl["ped_speed"] in ("1.1335", "1.2375")
        o = jf.evaluate({n: float(decl[n]) for n in ("ego_offset", "ped_offset", "ped_accel",
                                                      "ped_speed")})
        assert bool(o.collision)


def test_a_run_where_everything_collided_shows_no_typical_scenario(tmp_path, monkeypatch):
    """Every evaluation a collision: the figures set nothing non-critical beside the best
    (the best was drawn twice, once labelled 'non-challenging (typical)' in green)."""
    import matplotlib.figure
    import pyarrow.parquet as pq

    seen = {}
    save = matplotlib.figure.Figure.savefig

    def record(fig, fname, **kw):
        seen[len(seen)] = ([a.get_title() for a in fig.axes],
                           [t.get_text() for a in fig.axes for t in a.get_xticklabels()])
        return save(fig, fname, **kw)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", record)
    run = grid_run(tmp_path, "allcol",
                   'name = "allcol"\n[parameters.ego_offset]\nvalues = [7]\n'
                   '[parameters.ped_accel]\nvalues = [0.035, 0.081]\n[parameters.ped_speed]\n'
                   'values = [1.133]\n[parameters.ped_offset]\nvalues = [3]\n', 2)
    assert all(pq.read_table(run / "evaluations.parquet").to_pydict()["collision"])
    titles = [t for ts, _ in seen.values() for t in ts]
    assert "challenging (best)" in titles and "non-challenging (typical)" not in titles
    bars = [ticks for ts, ticks in seen.values() if "challenging" in ticks]
    assert bars == [["challenging"]]


@pytest.mark.parametrize("damage, message", [
    ("summary_empty", "summary.json is damaged (no 'first_collision_evaluation')"),
    ("summary_not_json", "summary.json is damaged (Expecting value"),
    ("summary_best_null", "summary.json is damaged ('best' is null, expected an object"),
    ("summary_count_text", "damaged ('first_collision_evaluation' is \"x\", expected an "
     "integer or null)"),
    ("no_reward", "evaluations.parquet is damaged (no column 'reward')"),
    ("no_rows", "evaluations.parquet holds no evaluation"),
    ("index_out_of_range", "column 'ped_speed_idx' outside 0..24"),
    ("collision_text", "column 'collision' holds object values, expected true/false"),
    ("reward_text", "column 'reward' holds object values, expected numbers"),
    ("evaluation_float", "column 'evaluation' holds float64 values, expected integers"),
    ("rows_dropped", "its 'evaluation' column is not 1..100 in order"),
    ("rows_repeated", "its 400 rows are not the 200 evaluations summary.json counts"),
    ("best_outside", "summary.json is damaged ('best.evaluation' is 99999, not one of"),
    # hand-edited counts and best reward, against the evaluations (report.md showed them)
    ("count_edited", "summary.json does not match evaluations.parquet ('n_collisions' is -5; "
     "the evaluations give "),
    ("best_reward_edited", "summary.json does not match evaluations.parquet ('best.reward' "
     "is 99.0;"),
    # hand-edited rewards: one above the best, one NaN on a finite rollout
    ("reward_above_best", "summary.json does not match evaluations.parquet ('best.evaluation' "
     "is "),
    ("reward_nan", "evaluations.parquet is damaged: evaluation 4's reward is nan while its "
     "rollout is recorded as finite"),
])
def test_a_damaged_run_folder_gets_one_line_and_nothing_redrawn(run_with_figures, tmp_path,
                                                                 capsys, damage, message):
    """figures, replay and export of a damaged run: one line naming the file, exit 2, and the
    folder's figures untouched (they were half redrawn before the failure)."""
    import shutil

    import pyarrow as pa
    import pyarrow.parquet as pq

    run = tmp_path / "run"
    shutil.copytree(run_with_figures, run)
    eps = run / "evaluations.parquet"
    t = pq.read_table(eps)
    if damage == "summary_empty":
        (run / "summary.json").write_text("{}")
    elif damage == "summary_not_json":
        (run / "summary.json").write_text('{"best":')
    elif damage in ("best_outside", "count_edited", "best_reward_edited"):
        s = json.loads((run / "summary.json").read_text())
        if damage == "best_outside":
            s["best"]["evaluation"] = 99999
        elif damage == "count_edited":
            s["n_collisions"] = -5
        else:
            s["best"]["reward"] = 99.0
        (run / "summary.json").write_text(json.dumps(s))
    elif damage.startswith("summary_"):  # a field of the wrong type, the rest intact
        s = json.loads((run / "summary.json").read_text())
        s.update({"best": None} if damage == "summary_best_null" else
                 {"first_collision_evaluation": "x"})
        (run / "summary.json").write_text(json.dumps(s))
    elif damage == "no_reward":
        pq.write_table(t.drop(["reward"]), eps)
    elif damage == "no_rows":
        pq.write_table(t.slice(0, 0), eps)
    elif damage == "rows_dropped":
        pq.write_table(t.slice(0, 100), eps)
    elif damage == "rows_repeated":
        pq.write_table(pa.concat_tables([t, t]), eps)
    elif damage in ("reward_above_best", "reward_nan"):
        i = t.schema.get_field_index("reward")
        col = t.column(i).to_pylist()
        assert not t.column("nonfinite").to_pylist()[3]
        col[3] = max(col) + 1.0 if damage == "reward_above_best" else float("nan")
        pq.write_table(t.set_column(i, "reward", pa.array(col, t.schema.field(i).type)), eps)
    elif damage in ("collision_text", "reward_text", "evaluation_float"):
        name = {"collision_text": "collision", "reward_text": "reward",
                "evaluation_float": "evaluation"}[damage]
        i = t.schema.get_field_index(name)
        col = t.column(i).to_pylist()
        new = (pa.array([float(v) + 0.5 for v in col]) if damage == "evaluation_float"
               else pa.array([str(v) for v in col]))
        pq.write_table(t.set_column(i, name, new), eps)
    else:
        i = t.schema.get_field_index("ped_speed_idx")
        col = t.column(i).to_pylist()
        col[3] = 99  # the paper space has 25 speeds
        pq.write_table(t.set_column(i, "ped_speed_idx", pa.array(col, t.schema.field(i).type)),
                       eps)
    before = {f.name: f.read_bytes() for f in (run / "figures").iterdir()}
    for cmd in (["figures", str(run)], ["replay", str(run)],
                ["export", str(run), "--out", str(tmp_path / "x")]):
        capsys.readouterr()
        assert main(cmd) == 2, cmd
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], (cmd, err)
    assert {f.name: f.read_bytes() for f in (run / "figures").iterdir()} == before
    assert not (tmp_path / "x").exists() or not any((tmp_path / "x").iterdir())


def test_a_second_recording_of_the_same_scenario_keeps_its_timelines(run_with_figures,
                                                                      tmp_path):
    """Two recordings of one run's best scenario in one process (a notebook, or a test after
    another): rerun keeps a stream's time per recording id, so the second one's simulated
    metrics once carried the first one's last evaluation number as a second timeline."""
    from jaxfalsify.outputs.replay import record

    record(run_with_figures, "best", save=tmp_path / "first.rrd")  # ends on the evaluations
    cols = _read_rrd(record(run_with_figures, "best", save=tmp_path / "second.rrd"))
    for ent, own, other in (("/metrics/distance", "sim_time", "evaluation"),
                            ("/world/ego", "sim_time", "evaluation"),
                            ("/training/reward", "evaluation", "sim_time")):
        names = {n for rb in cols[ent] for n in rb.schema.names}
        assert own in names and other not in names, (ent, names)


def test_library_figures_and_replay_take_the_run_folders_lock(run_with_figures, tmp_path):
    """runs.redraw and replay.record (as the CLI's figures and replay) write into a run folder
    only under its lock: while another writer holds it they are refused in one line naming
    that writer's pid, and nothing is written; a recording saved elsewhere needs no lock."""
    import os

    from jaxfalsify.io import store
    from jaxfalsify.jobs import runs
    from jaxfalsify.outputs import replay

    out = run_with_figures
    before = sorted(os.listdir(out))
    holder = store.run_folder_lock(out, "replay")
    try:
        for call in (lambda: runs.redraw(out), lambda: replay.record(out, "best")):
            with pytest.raises(store.FolderError, match=f"process {os.getpid()}"):
                call()
            assert sorted(os.listdir(out)) == before
        elsewhere = replay.record(out, "best", save=tmp_path / "best.rrd")
        assert elsewhere.stat().st_size > 0
    finally:
        holder.release()
    files, report = runs.redraw(out)  # released: drawn
    assert report == out / "report.md" and all(f.parent == out / "figures" for f in files)
    with pytest.raises(ValueError, match="not a finished run folder"):
        store.run_folder_lock(tmp_path, "figures")


def test_a_run_folder_reads_back_as_its_own_files(run_with_figures):
    """``rundir.load_run`` gives a typed RunFolder whose fields are the folder's own files
    (oracle: summary.json and config.toml read directly, evaluations.parquet's row count in
    the summary), and it still unpacks as (space, config, summary, evaluations)."""
    import json
    import tomllib

    from jaxfalsify.engine.rundir import RunFolder, load_run

    folder = load_run(run_with_figures)
    assert isinstance(folder, RunFolder)
    assert folder.summary == json.loads((run_with_figures / "summary.json").read_text())
    cfg = tomllib.loads((run_with_figures / "config.toml").read_text())
    assert folder.config.seed == cfg["seed"] and folder.config.strategy == cfg["strategy"]
    assert len(folder.evaluations["evaluation"]) == folder.summary["evaluations"]
    assert folder.space.name == cfg["space"]["name"] == "paper"
    assert folder.space.names == tuple(cfg["space"]["parameters"])
    assert folder.space.shape == (10, 10, 25, 4, 10)  # the paper space's sample counts
    sp, rc, summary, ep = folder
    assert sp is folder.space and rc is folder.config and ep is folder.evaluations


def test_a_recording_that_fails_midway_still_ends_the_process(tmp_path):
    """An error while a recording is logged (a damaged value met halfway) is raised and the
    process ends: rerun's in-memory stream, left undrained while the error unwound, blocked
    the process forever on its last flush (a subprocess, so a hang cannot hold the suite)."""
    import subprocess
    import sys

    out = tmp_path / "never.rrd"
    code = (
        "import rerun as rr\n"
        "from pathlib import Path\n"
        "from jaxfalsify.outputs import replay\n"
        "rec = rr.RecordingStream('t', recording_id='x')\n"
        "def log():\n"
        "    for i in range(1000):\n"
        "        rec.set_time('step', sequence=i)\n"
        "        rec.log('x', rr.Points2D([[i, i]]))\n"
        "    raise ValueError('boom')\n"
        "try:\n"
        f"    replay._save(rec, Path({str(out)!r}), log)\n"
        "except ValueError as e:\n"
        "    print('raised', e)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert (r.returncode, r.stdout.strip()) == (0, "raised boom")
    assert not out.exists()
