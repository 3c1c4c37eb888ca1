"""The campaign hands ``reinforce/default`` the kinematic screen of the crossing world, and an
external evaluator's run does not. Oracle: the exact boundary-distribution mass of the space's
scenarios whose unbraked car would hit the walker (every scenario's gap computed, the mass
summed from the distribution's definition)."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

import jaxfalsify as jf
from jaxfalsify.core import screen
from jaxfalsify.engine import campaign
from jaxfalsify.jobs import runs
from jaxfalsify.search import discretised

SPACE = """name = "screen-test"
[parameters.ego_offset]
distribution = "uniform"
low = 20
high = 50
samples = 16
[parameters.ped_accel]
distribution = "uniform"
low = 0.0
high = 0.1
samples = 3
[parameters.ped_speed]
distribution = "uniform"
low = 0.2
high = 5.0
samples = 40
[parameters.ped_offset]
distribution = "uniform"
low = 2.0
high = 10.0
samples = 12
"""


def test_the_first_batch_is_screened_in_a_campaign_and_not_for_an_external_evaluator(tmp_path):
    path = tmp_path / "space.toml"
    path.write_text(SPACE)
    B, M = 2048, 8
    b = runs.RunConfig(space=str(path), sut="sensor-aeb", batch=B, evaluations=B).build()
    space = b.space
    every = np.asarray(space.unravel(np.arange(space.size)))
    drive = screen.unbraked_drive(b.sut, b.sut_params)
    gap = np.asarray(screen.conflict_gap(
        {k: jnp.asarray(v) for k, v in space.scenario(every).items()}, drive))
    # the campaign's per-value screen of the indices gives the same gaps
    np.testing.assert_array_equal(np.asarray(screen.for_space(
        space.layout, space.table_array, b.sut, b.sut_params)(jnp.asarray(every))), gap)
    mass = np.ones(space.size)
    for j, n in enumerate(space.shape):
        mass *= discretised.boundary_probs(n, 0.02)[every[:, j]]
    conflict = gap <= 0
    q = mass[conflict].sum()
    assert 0.01 < q < 0.2
    res = campaign.run(b.space, b.sut, b.sut_params, b.strategy, b.strategy_params, b.plan, 4)
    flat = np.asarray(space.ravel(res.indices))
    # the first two learners' halves: a slot holds a conflict when one of its M candidates
    # does; the other half are the boundary's draws
    screened, rest = conflict[flat[:B // 2]], conflict[flat[B // 2:]]
    want = 1 - (1 - q) ** M
    assert abs(screened.mean() - want) <= 5 * math.sqrt(want * (1 - want) / (B // 2))
    assert abs(rest.mean() - q) <= 5 * math.sqrt(q * (1 - q) / (B // 2))
    f = jf.Falsifier(str(path), strategy="reinforce/default", batch=B, evaluations=B, seed=4,
                     out=tmp_path / "ext")
    asked = f.ask()
    share = conflict[np.asarray(space.ravel(asked.indices))].mean()
    assert abs(share - q) <= 5 * math.sqrt(q * (1 - q) / B), (share, q)
