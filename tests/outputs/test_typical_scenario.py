"""The typical non-critical scenario (paper Table II's 'non-challenging') satisfies the paper's
requirement: the median reward among evaluations whose box gap never fell below epsilon
(oracle: rows picked by hand)."""

import numpy as np

from jaxfalsify.outputs import analysis


def _fields(reward, robustness, collision, nonfinite=None):
    n = len(reward)
    return {"reward": np.asarray(reward, np.float32),
            "robustness": np.asarray(robustness, np.float32),
            "collision": np.asarray(collision, bool),
            "nonfinite": np.zeros(n, bool) if nonfinite is None else np.asarray(nonfinite)}


def test_the_typical_scenario_never_clashes():
    # rows 0-2 clash without colliding (gap below 1 m), 3 collides, 4-6 satisfy the requirement
    f = _fields(reward=[0.0, 0.01, 0.02, 0.25, -0.05, -0.03, -0.04],
                robustness=[-0.1, -0.5, -0.9, -1.0, 3.0, 0.0, 12.0],
                collision=[False, False, False, True, False, False, False])
    assert analysis.typical_non_critical(f) == 6  # median of -0.05, -0.04, -0.03


def test_without_a_satisfying_scenario_it_is_the_median_non_collision():
    f = _fields(reward=[0.0, 0.01, 0.02, 0.25], robustness=[-0.1, -0.5, -0.9, -1.0],
                collision=[False, False, False, True])
    assert analysis.typical_non_critical(f) == 1
    assert analysis.typical_non_critical(_fields([0.2], [-1.0], [True])) is None


def test_fig9_rows_are_the_requirements_violations_when_the_run_names_one():
    """Oracle: a hand-built record where violations and collisions differ; Fig. 9's critical
    rows must come from the violations (a run with --requirement), the others from the
    evaluations that satisfy it."""
    from jaxfalsify.outputs.figures import fig10_rows

    n = 40
    collision = np.zeros(n, bool)
    collision[:5] = True
    violated = np.zeros(n, bool)
    violated[20:30] = True
    ep = {"collision": collision, "violated": violated, "nonfinite": np.zeros(n, bool)}
    rows = fig10_rows(ep, n=14, n_collisions=3)
    assert all(violated[r] for r in rows[:3])
    assert not any(violated[r] for r in rows[3:]) and len(rows) == 14
    del ep["violated"]  # a run without a requirement: collisions
    rows = fig10_rows(ep, n=14, n_collisions=3)
    assert all(collision[r] for r in rows[:3]) and not any(collision[r] for r in rows[3:])
