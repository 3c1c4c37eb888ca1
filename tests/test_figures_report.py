"""Figures and report of a run folder: files exist, are non-trivial images of the right size,
and the report's links resolve."""

import re

import numpy as np
import pytest

from jaxfalsify.cli import main

SIZES = {"reward_per_episode.png": (450, 800), "distance_challenging.png": (450, 1200),
         "high_risk_second_half.png": (450, 500), "distance_14_scenarios.png": (450, 800)}


@pytest.fixture(scope="module")
def run_with_figures(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig") / "run"
    assert main(["run", "--strategy", "cem", "--episodes", "200", "--batch", "50",
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
    img = mpimg.imread(figs / "critical_regions.png")
    assert img.shape[0] > 300 and img.shape[1] > 800
    assert len(np.unique(img[..., :3].reshape(-1, 3), axis=0)) > 50


def test_report_links_resolve_and_table_matches_summary(run_with_figures):
    import json

    text = (run_with_figures / "report.md").read_text()
    links = re.findall(r"\]\(([^)]+)\)", text)
    assert len(links) == 5
    for link in links:
        assert (run_with_figures / link).is_file(), link
    s = json.loads((run_with_figures / "summary.json").read_text())
    assert f"{s['best']['reward']:.4f}" in text
    assert f"jaxfalsify run --config {run_with_figures}/config.toml" in text


def test_figures_command_regenerates_and_rejects_non_runs(run_with_figures, tmp_path, capsys):
    target = run_with_figures / "figures" / "reward_per_episode.png"
    target.unlink()
    assert main(["figures", str(run_with_figures)]) == 0
    assert target.is_file()
    assert main(["figures", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "is not a run folder" in err and len(err.splitlines()) == 1
