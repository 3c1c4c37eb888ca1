"""The compiled campaign against an eager loop written here: ask, then tell the batch's outcomes,
update by update, with the keys split as the campaign documents. The campaign tells each batch
at the start of the next update and runs its first chunk as a single update; the strategy must
still see the same asks and tells in the same order, so every batch the loop asks equals the
batch the campaign recorded."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import TINY_SPACE

import jaxfalsify as jf
from jaxfalsify import search
from jaxfalsify.core import screen, sim
from jaxfalsify.engine import campaign
from jaxfalsify.suts import registry as sut_lib


@pytest.mark.parametrize("strategy", [
    "cem", "cmaes", pytest.param("reinforce/default", marks=pytest.mark.slow)])
def test_the_campaign_asks_what_an_eager_ask_tell_loop_asks(tmp_path, strategy):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SPACE)
    space = jf.load_space(str(path))
    batch, evaluations, seed = 8, 8 * 7 - 3, 5  # 7 updates, the last one short of the budget
    sut, sut_params = sut_lib.make("carla-tm")
    strat, params = search.make(strategy, space.shape, batch)
    p = campaign.plan(evaluations, batch, every=3)  # chunks of 1, 3 and 3 updates
    assert [p.updates_in(c) for c in range(p.n_chunks)] == [1, 3, 3]
    r = campaign.run(space, sut, sut_params, strat, params, p, seed)

    # the eager loop: the campaign's key split (init splits the seed's key into the
    # strategy's, the evaluations' and the loop's; each update splits the loop's key into
    # the next one, the ask's and the tell's), the outcomes taken from the campaign's records
    k_init, _, key = jax.random.split(sim.seed_key(seed), 3)
    state = strat.init(k_init, params)
    # the campaign's kinematic screen of the first batch (the world and SUT as it traces them)
    screen_of = screen.for_space(space.layout, space.table_array, sut,
                                 sim.as_float32(sut_params), sim.as_float32(sim.WORLD))
    ask = jax.jit(lambda k, s: strat.ask_screened(k, s, params, screen_of))
    tell = jax.jit(lambda k, s, i, rew, rob, v: strat.tell_outcome(
        k, s, i, rew, rob, v, params, ttc=jnp.full(batch, jnp.inf)))
    n = p.n_updates * batch  # the records padded past the budget (those rows never count)
    idx_all = np.zeros((n, len(space.shape)), np.int32)
    idx_all[:r.n] = r.indices
    f = {k: np.zeros(n, v.dtype) for k, v in r.fields.items()}
    for k, v in r.fields.items():
        f[k][:r.n] = v
    for u in range(p.n_updates):
        key, k_ask, k_tell = jax.random.split(key, 3)
        idx, state = ask(k_ask, state)
        rows = slice(u * batch, (u + 1) * batch)
        kept = np.arange(u * batch, (u + 1) * batch) < evaluations
        np.testing.assert_array_equal(np.asarray(idx)[kept], idx_all[rows][kept],
                                      err_msg=f"update {u}")
        counted = kept & ~f["nonfinite"][rows]
        rew = np.where(np.isnan(f["reward"][rows]) | ~kept, -np.inf, f["reward"][rows])
        rob = np.where(counted & np.isfinite(f["robustness"][rows]), f["robustness"][rows],
                       np.inf)
        state = tell(k_tell, state, idx, rew.astype(np.float32), rob.astype(np.float32),
                     f["collision"][rows] & counted)
