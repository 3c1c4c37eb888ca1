"""A sweep's running totals per calibration (:class:`Reducer`): counts of scenarios,
collisions, violations and non-finite rollouts, and the global maximum reward with its first
scenario and how many reach it, folded in chunk by chunk from rows or from device-side totals
(:func:`fold`)."""

from __future__ import annotations

import math

import numpy as np

from jaxfalsify.base import config as cfg
from jaxfalsify.engine.sweep_chunks import chunk_table
from jaxfalsify.engine.sweep_config import Calibrations
from jaxfalsify.scenario.space import Space

__all__ = ["Reducer", "fold"]


class Reducer:
    """Running totals of a sweep per calibration: counts and the global maximum reward (the
    first scenario on ties) and how many scenarios reach it."""

    FIELDS = ("n", "collisions", "nonfinite", "best_reward", "best_row", "best_ties",
              "violations")

    def __init__(self, **state):
        self.n = 0
        self.collisions = 0
        self.violations = 0  # of the sweep's requirement (rows with a "violated" column)
        self.nonfinite = 0
        self.best_reward = -math.inf
        self.best_row: dict | None = None
        self.best_ties = 0
        for k, v in state.items():
            setattr(self, k, -math.inf if k == "best_reward" and v is None else v)

    def state(self) -> dict:
        return {k: getattr(self, k) for k in self.FIELDS}

    def add(self, cols: dict[str, np.ndarray]):
        self.n += len(cols["scenario"])
        self.collisions += int(np.sum(cols["collision"]))
        if "violated" in cols:
            self.violations += int(np.sum(cols["violated"]))
        self.nonfinite += int(np.sum(cols["nonfinite"]))
        r = np.where(np.isnan(cols["reward"]), -np.inf, cols["reward"]).astype(np.float64)
        i = int(np.argmax(r))
        if r[i] > self.best_reward:
            self.best_reward = float(r[i])
            self.best_row = {k: cfg.plain(v[i]) for k, v in cols.items()}
            self.best_ties = int(np.sum(r == r[i]))
        elif r[i] == self.best_reward and math.isfinite(r[i]):
            self.best_ties += int(np.sum(r == r[i]))


def _add_reduced(reds: list[Reducer], space: Space, calib: Calibrations, b: int, e: int,
                 res: dict) -> None:
    """Fold one chunk's device-side totals (:func:`jaxfalsify.engine.sweep_chunks.reduce_chunk`)
    into the reducers: the same state :meth:`Reducer.add` reaches from the chunk's rows."""
    for c, red in enumerate(reds):
        red.n += e - b
        red.collisions += int(res["collisions"][c])
        red.nonfinite += int(res["nonfinite"][c])
        top = float(res["top"][c])
        if top > red.best_reward:
            i = int(res["best"][c])
            out = {k: np.repeat(v[c:c + 1, None], calib.count, axis=0)
                   for k, v in res["out"].items()}
            row = chunk_table(space, b + i, res["idx"][c:c + 1], out, calib)
            red.best_reward = top
            red.best_row = {k: cfg.plain(v[c]) for k, v in row.items()}
            red.best_ties = int(res["ties"][c])
        elif top == red.best_reward and math.isfinite(top):
            red.best_ties += int(res["ties"][c])


def _split_cols(cols: dict, calib: Calibrations) -> list[dict]:
    """A chunk's columns per calibration (calibration-major rows)."""
    if calib.count == 1:
        return [cols]
    n = len(cols["scenario"]) // calib.count
    return [{k: v[c * n:(c + 1) * n] for k, v in cols.items()} for c in range(calib.count)]


def fold(reds: list[Reducer], space: Space, calib: Calibrations, b: int, e: int, cols: dict,
         reduced: bool) -> None:
    """Add one chunk of :func:`jaxfalsify.engine.sweep_chunks.iter_sweep` (rows, or with
    ``reduced`` device-side totals) to the per-calibration reducers."""
    if reduced:
        _add_reduced(reds, space, calib, b, e, cols)
        return
    for red, part in zip(reds, _split_cols(cols, calib)):
        red.add(part)
