"""The command line's progress bar: a stage is shown with what it counts, with or without a
known total (Lanczos does not know how many iterations it will take)."""

from __future__ import annotations

import io

from stepsafe.cli import progressbar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def drawn(monkeypatch, calls) -> str:
    """What the bar leaves on a terminal's stderr after ``calls(progress)``."""
    screen = Terminal()
    monkeypatch.setattr("sys.stderr", screen)
    monkeypatch.setattr(progressbar, "DELAY", 0.0)
    with progressbar.progress_bar("coupled analysis") as progress:
        assert progress is not None
        calls(progress)
    return screen.getvalue()


def test_a_stage_without_a_total_shows_its_label_and_its_count(monkeypatch):
    out = drawn(monkeypatch, lambda p: [p.stage("Lanczos iterations (Hessian-vector "
                                                "products)", k, None) for k in (1, 2, 37)])
    assert "Lanczos iterations (Hessian-vector products)" in out
    assert " 37 " in out and "%" not in out


def test_a_stage_with_a_total_shows_done_of_total(monkeypatch):
    out = drawn(monkeypatch, lambda p: p.stage("dense Hessian (force-difference columns)",
                                               10, 120))
    assert "dense Hessian (force-difference columns)" in out
    assert "10 of 120" in out


def test_a_fraction_shows_a_percentage(monkeypatch):
    out = drawn(monkeypatch, lambda p: p(0.5))
    assert "coupled analysis" in out and "50%" in out


def test_no_bar_off_a_terminal(monkeypatch):
    monkeypatch.setattr("sys.stderr", io.StringIO())
    with progressbar.progress_bar("coupled analysis") as progress:
        assert progress is None
