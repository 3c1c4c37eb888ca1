"""Requirements: each built-in's robustness against a NumPy computation of its STL formula
(*always signal >= threshold*: the minimum over the episode's steps) on the trajectories of
random scenarios, simulated step by step; a user's requirement by import path; bad
requirements named in one line."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import random_scenarios

import jaxfalsify as jf
from jaxfalsify.core import requirements as req_lib

W = jf.WORLD


@pytest.fixture(scope="module")
def rollouts():
    sc = random_scenarios(300, seed=11)
    out = jf.evaluate(sc, sut="sensor-aeb")
    traj = jf.simulate(sc, sut="sensor-aeb")
    return out, traj


def _always(signal, valid):
    """min over the valid steps of ``signal`` (inf where none)."""
    return np.where(valid, signal, np.inf).min(axis=1)


def _robustness(name, out, **given):
    req = req_lib.resolve(name)
    return np.asarray(req_lib.robustness(req, out, req_lib.with_params(req, given)))


def test_clash_is_always_box_gap_at_least_epsilon(rollouts):
    out, t = rollouts
    valid = np.asarray(t.valid)
    start = np.asarray(out.min_distance)  # the first state counts too (it is never the min)
    want = np.minimum(_always(np.asarray(t.distance), valid), start) - 1.5
    np.testing.assert_allclose(_robustness("clash", out, epsilon=1.5), want, atol=1e-5)
    assert (want < 0).any() and (want > 0).any()


def test_collision_is_contact_and_otherwise_the_smallest_gap(rollouts):
    out, t = rollouts
    valid = np.asarray(t.valid)
    hit = (np.asarray(t.collided) & valid).any(axis=1)
    gap = np.minimum(_always(np.asarray(t.distance), valid), np.asarray(out.min_distance))
    want = np.where(hit, -1.0, gap)
    np.testing.assert_allclose(_robustness("collision", out), want, atol=1e-5)
    assert hit.any() and (~hit).any()


def test_ttc_is_always_time_to_collision_at_least_the_threshold(rollouts):
    out, t = rollouts
    want = np.minimum(_always(np.asarray(t.ttc), np.asarray(t.valid)), 1000.0) - 2.0
    np.testing.assert_allclose(_robustness("ttc", out, min_ttc=2.0), want, atol=1e-4)
    assert (want < 0).any() and (want > 0).any()


def test_rss_is_the_safe_distance_while_the_pedestrian_is_ahead(rollouts):
    out, t = rollouts
    ego_x, ped_x = np.asarray(t.ego_x), np.asarray(t.ped_x)
    ahead = ped_x + W.ped_length / 2 > ego_x + W.ego_length / 2
    margin = np.asarray(t.centre_distance) - np.asarray(t.rss_distance)
    want = np.minimum(_always(margin, np.asarray(t.valid) & ahead), 1000.0) - 0.5
    np.testing.assert_allclose(_robustness("rss", out, margin=0.5), want, atol=1e-4)
    # its violations are the paper's high-risk steps
    np.testing.assert_array_equal(want + 0.5 < 0, np.asarray(out.high_risk_steps) > 0)


def test_a_users_requirement_by_import_path(tmp_path, rollouts, monkeypatch):
    out, _ = rollouts
    (tmp_path / "reqs.py").write_text(
        "from jaxfalsify.core.requirements import Requirement, TTCParams\n\n\n"
        "def gap(outcome, params):\n    return outcome.min_distance - 0.25\n\n\n"
        "CLOSE = Requirement('close', lambda o, p: o.min_ttc - p.min_ttc, TTCParams(3.0))\n"
        "import jax.numpy as jnp\nNOT_ONE = lambda o, p: o.min_distance * jnp.ones(2)\n"
        "RAISES = lambda o, p: 1 / 0\n")
    monkeypatch.chdir(tmp_path)
    np.testing.assert_allclose(_robustness("reqs.py:gap", out),
                               np.asarray(out.min_distance) - 0.25, atol=1e-6)
    close = req_lib.resolve("reqs.py:CLOSE")
    assert close.name == "reqs.py:CLOSE" and req_lib.param_names(close) == ("min_ttc",)
    got = np.asarray(req_lib.robustness(close, out,
                                        req_lib.with_params(close, {"min_ttc": 1})))
    np.testing.assert_allclose(got, np.asarray(out.min_ttc) - 1.0, atol=1e-6)
    with pytest.raises(ValueError, match="must return one number per scenario"):
        req_lib.check(req_lib.resolve("reqs.py:NOT_ONE"), None)
    with pytest.raises(ValueError, match="fails on an example outcome: ZeroDivisionError"):
        req_lib.check(req_lib.resolve("reqs.py:RAISES"), None)


@pytest.mark.parametrize("spec, says", [
    ("nope", "unknown requirement 'nope'"),
    ("missing.py:f", "no such file missing.py"),
    ("jaxfalsify.core.requirements:CAP", "is a float, not a Requirement"),
])
def test_bad_requirements_are_named(spec, says):
    with pytest.raises(ValueError, match=says):
        req_lib.resolve(spec)


def test_bad_requirement_parameters_are_named():
    clash = req_lib.resolve("clash")
    with pytest.raises(ValueError, match="has no parameter 'eps'"):
        req_lib.with_params(clash, {"eps": 1.0})
    with pytest.raises(ValueError, match=r"epsilon=-1.0 is outside \[0, inf\)"):
        req_lib.with_params(clash, {"epsilon": -1.0})
