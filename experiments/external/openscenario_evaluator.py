"""An external evaluator that hands each asked scenario to a runner as OpenSCENARIO and reads
the robustness back: the shape of a CARLA ScenarioRunner or esmini integration.

    jaxfalsify run --evaluator experiments/external/openscenario_evaluator.py:evaluate \\
        --evaluations 64 --workers 2 --out runs/openscenario-external

For every scenario ``evaluate`` writes ``$XOSC_DIR/scenario_<n>.xosc`` (default
``openscenario-asked/``), the project's controller-mode export of the paper's crossing
(``jaxfalsify.outputs.export.write_controller_scenario``: the concrete values in its
``ParameterDeclarations``, the ego's start, route and launch request, the pedestrian's path and
speed profile as expressions of them) beside the road ``crossing.xodr``. Then:

* with ``$XOSC_RUNNER`` set, it runs that command with ``{xosc}`` replaced by the file, and takes
  the last line the command prints as the robustness (e.g. a wrapper around
  ``scenario_runner.py --openscenario {xosc}`` or ``esmini --headless --osc {xosc}`` that
  prints the minimum distance between the boxes less 1 m);
* without it, it reads the parameter declarations back from the file and evaluates them with
  the project's NumPy reference simulator (a stand-in runner: neither CARLA nor esmini is
  installable here), so the round trip file -> values -> robustness is exercised.
"""

import os
import shlex
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from jaxfalsify.core.reference import reference_evaluate
from jaxfalsify.core.sim import WORLD
from jaxfalsify.outputs import export
from jaxfalsify.scenario.space import KNOWN_PARAMETERS, load_space

SPACE = load_space("paper")
REQUEST = export.ego_request("carla-tm", {}, WORLD)
_count = [0]


def write(values: dict, folder: Path) -> Path:
    """One concrete scenario ``{name: value}`` as ``folder/scenario_<n>.xosc``."""
    folder.mkdir(parents=True, exist_ok=True)
    road = folder / "crossing.xodr"
    if not road.exists():
        export.write_road(road, WORLD)
    _count[0] += 1
    path = folder / f"scenario_{os.getpid()}_{_count[0]:06d}.xosc"
    text = {n: f"{v:.10g}" for n, v in values.items()}
    for n in export.used_parameters(SPACE):
        text.setdefault(n, f"{KNOWN_PARAMETERS[n]['default']:g}")
    return export.write_controller_scenario(path, road.name, SPACE, text, REQUEST, WORLD,
                                            path.stem)


def declared(path: Path) -> dict[str, float]:
    """The ``ParameterDeclarations`` of an ``.xosc`` file, as numbers."""
    root = ET.parse(path).getroot()
    return {p.get("name"): float(p.get("value"))
            for p in root.iter("ParameterDeclaration")}


def run_one(path: Path) -> float:
    runner = os.environ.get("XOSC_RUNNER")
    if runner:
        cmd = [a.replace("{xosc}", str(path)) for a in shlex.split(runner)]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
        return float(out.strip().splitlines()[-1])
    params = {k: np.array([v]) for k, v in declared(path).items() if k in KNOWN_PARAMETERS}
    return float(reference_evaluate(params, sut="carla-tm")["robustness"][0])


def evaluate(scenarios: dict) -> np.ndarray:
    folder = Path(os.environ.get("XOSC_DIR", "openscenario-asked"))
    n = len(next(iter(scenarios.values())))
    return np.array([run_one(write({k: float(v[i]) for k, v in scenarios.items()}, folder))
                     for i in range(n)])
