"""Evaluate, sweep and search on the devices this process has (XLA_FLAGS may force several
host devices) and save the results: run as a subprocess by test_many_devices.py, and imported by it
for the one-device reference."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1]))  # conftest


def probe(space_path: str) -> dict:
    import jax
    from conftest import random_scenarios, run_campaign

    import jaxfalsify as jf
    from jaxfalsify.engine.truth import sweep_arrays

    out = {"devices": np.array(jax.local_device_count())}
    o = jf.evaluate(random_scenarios(1003, seed=5), chunk_size=256)
    out.update({f"eval_{k}": np.asarray(v) for k, v in vars(o).items()})
    sp = jf.load_space(space_path)
    rows = sweep_arrays(sp, chunk=600)
    out.update({f"sweep_{k}": v for k, v in rows.items()})
    for name in ("cem", "reinforce"):
        res = run_campaign(sp, name, batch=40, evaluations=120, seed=3)
        out[f"{name}_indices"] = res.indices
        out[f"{name}_reward"] = res.fields["reward"]
    return out


if __name__ == "__main__":
    np.savez(sys.argv[1], **probe(sys.argv[2]))
