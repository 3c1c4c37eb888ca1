"""Figures drawn in a second process while the run writes its files
(:mod:`jaxfalsify.outputs.figure_process`): the same bytes as drawn in one process (the
oracle: ``jaxfalsify figures``, which draws every figure itself), and a process that fails
costs nothing but its time."""

import subprocess
import sys

import pytest

from jaxfalsify.jobs import runs
from jaxfalsify.outputs import figure_process, figures

CONFIG = runs.RunConfig(strategy="random", evaluations=400, batch=100, seed=2)


def figure_bytes(out):
    return {p.name: p.read_bytes() for p in sorted((out / "figures").glob("*.png"))}


def redrawn_bytes(out):
    """The run's figures drawn again, all of them in this process."""
    runs.redraw(out)
    return figure_bytes(out)


def test_the_second_process_draws_the_same_figures(tmp_path, monkeypatch):
    monkeypatch.setattr(figure_process, "wanted", lambda: True)
    local = []
    real = figures.sweep_figures

    def counted(*args, **kwargs):
        local.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(figures, "sweep_figures", counted)
    runs.execute(CONFIG, tmp_path / "run")
    assert local == []  # none of them drawn by the run's own process
    drawn = figure_bytes(tmp_path / "run")
    assert set(figures.SWEEP_FIGURES) <= set(drawn) and len(drawn) == 7
    monkeypatch.undo()
    assert redrawn_bytes(tmp_path / "run") == drawn


@pytest.mark.parametrize("command", [
    [sys.executable, "-c", "pass"],  # exits at once, answers nothing
    [sys.executable, "-c", "import sys, pickle; sys.stdin.buffer.read(); "
                           "sys.stdout.buffer.write(pickle.dumps(('error', 'no')))"],
    [sys.executable, "-c", "import sys; sys.stdin.buffer.read(); "
                           "sys.stdout.buffer.write(b'not a pickle')"],
], ids=["died", "error", "garbled"])
def test_a_failing_process_leaves_the_figures_to_the_run(tmp_path, monkeypatch, command):
    real = subprocess.Popen
    started = []

    def popen(args, **kwargs):
        started.append(args)
        return real(command, **kwargs)

    monkeypatch.setattr(figure_process, "wanted", lambda: True)
    monkeypatch.setattr(figure_process.subprocess, "Popen", popen)
    runs.execute(CONFIG, tmp_path / "run")
    assert started == [figure_process.command()]
    drawn = figure_bytes(tmp_path / "run")
    monkeypatch.undo()
    assert len(drawn) == 7 and redrawn_bytes(tmp_path / "run") == drawn


def test_a_process_that_cannot_start(tmp_path, monkeypatch):
    def popen(args, **kwargs):
        raise OSError("no such program")

    monkeypatch.setattr(figure_process, "wanted", lambda: True)
    monkeypatch.setattr(figure_process.subprocess, "Popen", popen)
    runs.execute(CONFIG, tmp_path / "run")
    assert len(figure_bytes(tmp_path / "run")) == 7


def test_the_process_imports_this_copy_of_the_package(tmp_path):
    """Started from a folder holding another ``jaxfalsify``, the process still imports the
    package the run imported (the oracle: the module file each reports)."""
    import jaxfalsify

    fake = tmp_path / "jaxfalsify"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise ImportError('the wrong copy')\n")
    code = figure_process.command()
    code[-1] = code[-1].replace("from jaxfalsify.outputs.figure_process import main; "
                                "sys.exit(main())", "import jaxfalsify; print(jaxfalsify.__file__)")
    out = subprocess.run(code, cwd=tmp_path, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == jaxfalsify.__file__


def test_switched_off_by_the_environment(monkeypatch):
    monkeypatch.setenv(figure_process.ENV, "0")
    assert not figure_process.wanted()
