import numpy as np
import pytest

import jaxfalsify as jf

# a 32-scenario space (Table I values around Table II) for CLI tests
TINY_SPACE = """name = "tiny"
[parameters.ego_offset]
values = [7, 9]
[parameters.ped_accel]
values = [0.007, 0.076]
[parameters.ped_speed]
values = [1.0, 1.237, 1.5, 1.808]
[parameters.ped_offset]
values = [3.5, 4.0]
"""

TABLE_II_CHALLENGING = dict(ego_offset=9.0, ped_accel=0.007, ped_speed=1.237, ped_offset=3.5,
                            weather=8.0)
TABLE_II_NON_CHALLENGING = dict(ego_offset=7.0, ped_accel=0.076, ped_speed=1.808,
                                ped_offset=3.5, weather=8.0)


def random_scenarios(n, seed=0, extended=False):
    """Continuous random concrete scenarios in (and slightly around) the paper's ranges."""
    rng = np.random.default_rng(seed)
    sc = dict(ego_offset=rng.uniform(0.5, 11.0, n), ped_accel=rng.uniform(0.0, 0.11, n),
              ped_speed=np.clip(rng.normal(1.46, 0.3, n), 0.3, 3.0),
              ped_offset=rng.uniform(2.5, 5.0, n),
              weather=rng.integers(0, 15, n).astype(np.float64))
    if extended:
        sc["ped_speed_change"] = rng.choice([0.5, -0.5, 0.75, -0.75, 0.0], n)
        sc["ped_change_step"] = rng.integers(0, 80, n).astype(np.float64)
    return sc


@pytest.fixture(scope="module")
def table_ii():
    """Trajectories and outcomes of the paper's Table II scenarios (batched: [challenging, non])."""
    sc = {k: np.array([TABLE_II_CHALLENGING[k], TABLE_II_NON_CHALLENGING[k]])
          for k in TABLE_II_CHALLENGING}
    return sc, jf.simulate(sc), jf.evaluate(sc)


@pytest.fixture(scope="session")
def paper_sweep():
    """The exhaustive sweep of the paper space (100,000 scenarios, default SUT)."""
    from jaxfalsify.sweep import sweep_arrays
    return sweep_arrays(jf.space("paper"))
