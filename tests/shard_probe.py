"""Subprocess helper for test_sharding.py: evaluate, sweep and search on the devices this
process has (XLA_FLAGS may force several host devices) and save the results."""

import sys

import jax
import numpy as np

import jaxfalsify as jf
from jaxfalsify.sweep import sweep_arrays

sys.path.insert(0, str(__import__("pathlib").Path(__file__).parent))
from conftest import random_scenarios, run_campaign  # noqa: E402

out = {"devices": np.array(jax.local_device_count())}
o = jf.evaluate(random_scenarios(1003, seed=5), chunk_size=256)
out.update({f"eval_{k}": np.asarray(v) for k, v in vars(o).items()})
sp = jf.load_space(sys.argv[2]) if len(sys.argv) > 2 else jf.load_space("paper")
rows = sweep_arrays(sp, chunk=600)
out.update({f"sweep_{k}": v for k, v in rows.items()})
for name in ("cem", "reinforce"):
    res = run_campaign(sp, name, batch=40, evaluations=120, seed=3)
    out[f"{name}_indices"] = res.indices
    out[f"{name}_reward"] = res.fields["reward"]
np.savez(sys.argv[1], **out)
