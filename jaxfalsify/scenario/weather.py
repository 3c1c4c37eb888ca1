"""CARLA weather presets, indexed as the original code did (presets sorted by name).

The `weather` scenario parameter is an integer index 0..14 into this table. Values are the
CARLA 0.9.10-era presets (CARLA's ``LibCarla/source/carla/rpc/WeatherParameters.cpp``); fog
density and wetness are 0 in all of them. ``Default`` (index 4) takes the map's default;
Town05's default is a clear noon, so we use ClearNoon's values for it.

Weather is a *visual* setting in CARLA: the Traffic Manager does not see it and tyre friction is
unchanged. Only perception-based systems under test (``sensor-aeb``) react to it.
"""

import numpy as np

__all__ = ["PRESETS", "N_PRESETS", "TABLE"]

# name, cloudiness [%], precipitation [%], precipitation deposits [%], sun altitude [deg]
PRESETS: tuple[tuple[str, float, float, float, float], ...] = (
    ("ClearNoon", 15.0, 0.0, 0.0, 75.0),
    ("ClearSunset", 15.0, 0.0, 0.0, 15.0),
    ("CloudyNoon", 80.0, 0.0, 0.0, 75.0),
    ("CloudySunset", 80.0, 0.0, 0.0, 15.0),
    ("Default", 15.0, 0.0, 0.0, 75.0),
    ("HardRainNoon", 90.0, 60.0, 100.0, 75.0),
    ("HardRainSunset", 80.0, 60.0, 100.0, 15.0),
    ("MidRainSunset", 80.0, 30.0, 50.0, 15.0),
    ("MidRainyNoon", 80.0, 30.0, 50.0, 75.0),
    ("SoftRainNoon", 70.0, 15.0, 50.0, 75.0),
    ("SoftRainSunset", 90.0, 15.0, 50.0, 15.0),
    ("WetCloudyNoon", 80.0, 0.0, 50.0, 75.0),
    ("WetCloudySunset", 90.0, 0.0, 50.0, 15.0),
    ("WetNoon", 20.0, 0.0, 50.0, 75.0),
    ("WetSunset", 20.0, 0.0, 50.0, 15.0),
)

NAMES: tuple[str, ...] = tuple(p[0] for p in PRESETS)
N_PRESETS = len(PRESETS)

# (15, 4) float32: cloudiness, precipitation, deposits [%], sun altitude [deg].
TABLE = np.array([p[1:] for p in PRESETS], dtype=np.float32)


def name(index: int) -> str:
    """Preset name for a weather index (0..14)."""
    return NAMES[int(index)]
