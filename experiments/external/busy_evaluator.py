"""A stand-in for an expensive external simulator: about 1 ms of CPU work per scenario (a busy
wait), robustness ``ped_speed - 1.5``. ``experiments/bench_evaluators.py`` measures the worker
pool's throughput with it against the ideal of one scenario per millisecond per worker."""

import time

import numpy as np

SECONDS_EACH = 0.001


def evaluate(scenarios: dict) -> np.ndarray:
    speed = np.asarray(scenarios["ped_speed"], np.float64)
    for _ in range(len(speed)):  # one scenario after another, as a simulator would
        end = time.perf_counter() + SECONDS_EACH
        while time.perf_counter() < end:
            pass
    return speed - 1.5
