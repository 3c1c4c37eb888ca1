import os
import tempfile

# one per-user cache for the whole test session, its subprocesses and its pytest-xdist
# workers (they inherit the controller's environment), never the user's own
if "JAXFALSIFY_TEST_SESSION_CACHE" not in os.environ:
    os.environ["JAXFALSIFY_TEST_SESSION_CACHE"] = tempfile.mkdtemp(
        prefix="jaxfalsify-test-cache-")
os.environ["JAXFALSIFY_CACHE_DIR"] = os.environ["JAXFALSIFY_TEST_SESSION_CACHE"]
# runs draw every figure in their own process: the suite keeps every core busy already
# (tests/outputs/test_figure_process.py turns the second process on)
os.environ["JAXFALSIFY_FIGURE_PROCESS"] = "0"

import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxfalsify as jf  # noqa: E402

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


def space_file_fixture(text: str, name: str):
    """A module-scoped fixture: ``text`` (a space's TOML) written to ``<tmp>/<name>.toml``,
    its path returned (``small_space = space_file_fixture(SMALL, "small")`` in a module)."""
    @pytest.fixture(scope="module")
    def space_file(tmp_path_factory):
        path = tmp_path_factory.mktemp("space") / f"{name}.toml"
        path.write_text(text)
        return path

    return space_file


def grid_run(folder, name: str, space_text: str, evaluations: int, *flags: str):
    """Write a space's TOML to ``folder/<name>.toml`` and run ``jaxfalsify run --strategy
    grid`` on it (``--quiet``, extra ``flags``) into ``folder/run``; that run folder."""
    from jaxfalsify.cli import main

    space = folder / f"{name}.toml"
    space.write_text(space_text)
    run = folder / "run"
    assert main(["run", "--space", str(space), "--strategy", "grid", "--evaluations",
                 str(evaluations), "--out", str(run), "--quiet", *flags]) == 0
    return run


@pytest.fixture(scope="module")
def table_ii():
    """Trajectories and outcomes of the paper's Table II scenarios (batched: [challenging, non])."""
    sc = {k: np.array([TABLE_II_CHALLENGING[k], TABLE_II_NON_CHALLENGING[k]])
          for k in TABLE_II_CHALLENGING}
    return sc, jf.simulate(sc), jf.evaluate(sc)


@pytest.fixture(scope="session")
def paper_sweep():
    """The exhaustive sweep of the paper space (100,000 scenarios, default SUT)."""
    from jaxfalsify.engine.truth import sweep_arrays
    return sweep_arrays(jf.load_space("paper"))


def run_campaign(space, strategy="random", batch=16, evaluations=64, seed=0, sut="carla-tm",
                 every=None, **drive_kw):
    """A campaign through the library (``campaign.run``) with a registry strategy."""
    from jaxfalsify import search
    from jaxfalsify.engine import campaign
    from jaxfalsify.suts import registry as sut_lib

    s, sp_ = sut_lib.make(sut)
    strat, params = search.make(strategy, space.shape, batch)
    return campaign.run(space, s, sp_, strat, params,
                        campaign.plan(evaluations, batch, every=every), seed, **drive_kw)


_EVENTS: list | None = None


def _on_event(event: str, duration: float, **kw) -> None:
    if _EVENTS is not None and event in ("/jax/core/compile/jaxpr_trace_duration",
                                         "/jax/core/compile/backend_compile_duration"):
        _EVENTS.append(event)


import jax.monitoring  # noqa: E402

jax.monitoring.register_event_duration_secs_listener(_on_event)


@pytest.fixture
def compile_events():
    """``with compile_events() as events:`` collects JAX's public tracing and backend-compile
    events inside the block (an empty list: nothing was traced or compiled)."""
    import contextlib

    @contextlib.contextmanager
    def collect():
        global _EVENTS
        _EVENTS = []
        try:
            yield _EVENTS
        finally:
            _EVENTS = None

    return collect
