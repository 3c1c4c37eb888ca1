"""Every job folder's ``status.json`` through one lifecycle (:mod:`jaxfalsify.engine.lifecycle`):
the states and their fields read back from the file, the error text of a failure, and a
failure that cannot be written leaving the job's own error to its caller."""

import json

import pytest

from jaxfalsify.engine import lifecycle
from jaxfalsify.io.store import shell_path


def _read(out):
    return json.loads((out / "status.json").read_text())


def test_states_and_fields(tmp_path):
    st = lifecycle.Status(tmp_path, "sweep", evaluator="python")
    st.running(scenarios=12)
    assert _read(tmp_path) == {"state": "running", "evaluator": "python", "scenarios": 12,
                               "resume": f"jaxfalsify sweep --resume {shell_path(tmp_path)}"}
    st.interrupted(scenarios_done=5)
    assert _read(tmp_path)["state"] == "interrupted"
    assert _read(tmp_path)["scenarios_done"] == 5
    st.complete(scenarios=12)
    assert _read(tmp_path) == {"state": "complete", "evaluator": "python", "scenarios": 12}
    with pytest.raises(ValueError, match="one of running, interrupted, failed, complete"):
        st.write("done")


def test_a_failure_says_what_raised_in_one_bounded_line(tmp_path):
    st = lifecycle.Status(tmp_path, "estimate")
    st.failed(ValueError("x" * 1000), scenarios_done=3)
    doc = _read(tmp_path)
    assert doc["state"] == "failed" and doc["scenarios_done"] == 3
    assert doc["error"] == ("ValueError: " + "x" * 1000)[:lifecycle.ERROR_CHARS]
    assert len(doc["error"]) == 300
    assert not lifecycle.sut_raised(ValueError("callback"))


def test_a_failure_that_cannot_be_written_is_not_raised_over_the_jobs_own(tmp_path):
    gone = tmp_path / "gone"  # no such folder: writing status.json fails with an OSError
    lifecycle.Status(gone, "run").failed(RuntimeError("the job's own error"))
    assert not gone.exists()
