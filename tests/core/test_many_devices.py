"""Many devices, one process: results on 4 forced host devices equal those on 1 device
(evaluation, sweep, and search strategies' proposal batches): discrete outcomes and indices
exactly, floats to a few ulp (XLA:CPU vectorises a 64-row shard and a 256-row chunk
differently, which can move the last bit of a square root; CI saw one 1-ulp difference in
1003 final distances)."""

import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from conftest import TINY_SPACE

HERE = Path(__file__).parent
# the tiny CLI space with a third ego offset and three weathers (144 scenarios)
SPACE = (TINY_SPACE.replace("values = [7, 9]", "values = [5, 7, 9]", 1)
         + "[parameters.weather]\nvalues = [0, 8, 6]\n")


def _start_probe(tmp_path, devices):
    space = tmp_path / "space.toml"
    space.write_text(SPACE)
    out = tmp_path / f"probe{devices}.npz"
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.Popen([sys.executable, str(HERE / "shard_probe.py"), str(out), str(space)],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, out


@pytest.fixture(scope="module")
def probes(tmp_path_factory):
    """The probe on 4 forced host devices (a subprocess) and on this process's one device."""
    from shard_probe import probe

    tmp = tmp_path_factory.mktemp("shard")
    proc, out = _start_probe(tmp, 4)
    one = probe(str(tmp / "space.toml"))
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err[-2000:]
    return one, dict(np.load(out))


pytestmark = [
    pytest.mark.slow,  # ~30 s: four forced host devices compile everything again
    # the forced devices are CPUs: this process's one device must be a CPU too (float32 last
    # bits differ between a GPU and the CPU)
    pytest.mark.skipif(jax.default_backend() != "cpu", reason="forced host devices are CPUs")]


def test_four_devices_were_used(probes):
    one, four = probes
    assert int(one["devices"]) == 1 and int(four["devices"]) == 4


@pytest.mark.parametrize("prefix", ["eval_", "sweep_", "cem_", "reinforce_"])
def test_sharded_equals_unsharded(probes, prefix):
    one, four = probes
    keys = [k for k in one if k.startswith(prefix)]
    assert keys
    for k in keys:
        if np.issubdtype(one[k].dtype, np.floating):
            np.testing.assert_allclose(four[k], one[k], rtol=4e-6, atol=1e-6, err_msg=k)
        else:
            np.testing.assert_array_equal(four[k], one[k], err_msg=k)
