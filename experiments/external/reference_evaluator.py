"""The project's NumPy reference simulator (``jaxfalsify.core.reference``: float64, a Python loop
over time steps) as an external evaluator: what a team's own simulator looks like to
``jaxfalsify run --evaluator``.

    jaxfalsify run --evaluator experiments/external/reference_evaluator.py:evaluate \\
        --evaluations 400 --workers 2 --out runs/reference-external

``evaluate`` takes a batch ``{parameter: (n,) values}`` and returns the paper requirement's
robustness (minimum distance between the boxes less 1 m: negative is a clash), the collision
flags, the paper's reward and the minimum distance and time-to-collision. ``slow`` adds a fixed
cost per scenario (a stand-in for an expensive simulator: the pool's throughput benchmark).
"""

import time

import numpy as np

from jaxfalsify.core.reference import reference_evaluate
from jaxfalsify.core.sim import WORLD


def evaluate(scenarios: dict) -> dict:
    return _outputs(reference_evaluate(scenarios, sut="carla-tm"))


def _outputs(out: dict) -> dict:
    return {"robustness": out["robustness"], "collision": out["collision"],
            "reward": out["reward"], "min_distance": out["min_distance"],
            "final_distance": out["final_distance"], "min_ttc": out["min_ttc"]}


def with_trajectories(scenarios: dict) -> dict:
    """``evaluate`` with each scenario's trajectory (time, the distance between the boxes, the
    ego's position and speed, the walker's position; NaN after its end): the run folder keeps
    them in ``trajectories.npz`` and draws the distance figure from them."""
    out = reference_evaluate(scenarios, sut="carla-tm", record=True)
    valid = out["valid"].astype(bool)

    def hist(a):
        return np.where(valid, a, np.nan)

    t = np.broadcast_to((np.arange(valid.shape[1]) + 1) * float(WORLD.dt), valid.shape)
    return {**_outputs(out), "trajectory": {
        "t": hist(t), "distance": hist(out["distance"]), "ego_x": hist(out["ego_x"]),
        "ego_speed": hist(out["ego_speed"]), "ped_y": hist(out["ped_y"])}}


def slow(scenarios: dict, seconds_each: float = 0.001) -> dict:
    """``evaluate`` made to take about ``seconds_each`` per scenario (busy wait, one core)."""
    n = len(next(iter(scenarios.values())))
    end = time.perf_counter() + seconds_each * n
    out = evaluate(scenarios)
    while time.perf_counter() < end:
        pass
    return out


def busy(scenarios: dict) -> np.ndarray:
    """Robustness only, after about 1 ms of work per scenario (the throughput row)."""
    return slow(scenarios)["robustness"]
