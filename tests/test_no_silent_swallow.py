"""Issue 42: a failure outside the session's lifecycle is logged, never swallowed."""

from __future__ import annotations

import logging

from rig.planning import prediction


def test_a_link_timing_that_cannot_be_kept_or_read_is_said(tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the state folder would go")
    monkeypatch.setenv("XDG_STATE_HOME", str(blocker))
    timing = prediction.LinkTiming(2.0, 0.01, 0.02, "measured", "2026-11-28T07:00:00+00:00", "tcp://x, socket://y")
    assert timing.is_measured
    with caplog.at_level(logging.WARNING, logger="rig.planning.prediction"):
        prediction.remember(timing)
    assert "is not kept in" in caplog.text and str(blocker) in caplog.text
    caplog.clear()
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path))
    prediction.timing_file().parent.mkdir(parents=True)
    prediction.timing_file().write_text("{not json")
    with caplog.at_level(logging.WARNING, logger="rig.planning.prediction"):
        assert prediction.last_measured() is prediction.NOT_MEASURED
    assert "cannot be used" in caplog.text
    caplog.clear()
    prediction.timing_file().unlink()     # nothing measured yet: nothing to say
    with caplog.at_level(logging.WARNING, logger="rig.planning.prediction"):
        assert prediction.last_measured() is prediction.NOT_MEASURED
    assert caplog.text == ""
