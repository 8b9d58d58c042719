"""The console's fits (no Qt here): identification after a session, a re-fit of a stored
one and the 1-dof/2-dof comparison, each in a process of its own (:class:`rig.gui.fits.FitRunner`),
their progress and results posted to the window."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from rig.events import Message
from rig.gui import fits
from rig.gui.fits import FitRunner
from rig.gui.messages import ComparisonDone, FitDone, FitProgress, Notice
from rig.session.outcome import RunResult
from rig.session.preparation import RunOptions


@dataclass(frozen=True)
class IdentifySettings:
    model: str = "2dof"
    params: str | None = None
    estimate: list[str] = field(default_factory=list)   # empty: the plan's purpose, else the model's default


class Fitting:
    def __init__(self, post: Callable[[Message], None]) -> None:
        self.post = post
        self._runner = FitRunner(lambda title, it, objective: post(FitProgress(title, it, objective)),
                                 lambda title, text: post(Notice(f"{title} failed: {text}", "error")))

    @property
    def busy(self) -> bool:
        return self._runner.busy

    def identify(self, result: RunResult, opt: RunOptions) -> None:
        """``rig run --identify``'s fit of a session just captured."""
        title = f"identification {opt.model} of {result.session.path.name}"
        folder = result.session.path
        self._runner.submit(title, fits.session_fit, (result.session, opt, result.captured),
                            lambda summary: self.post(FitDone(title, summary, folder)))

    def refit(self, folder: Path, settings: IdentifySettings) -> None:
        title = f"re-fit {settings.model} of {folder.name}"
        self._runner.submit(title, fits.refit, (folder, settings.model, settings.params, list(settings.estimate)),
                            lambda summary: self.post(FitDone(title, summary, folder)))

    def compare(self, folder: Path, settings: IdentifySettings) -> None:
        title = f"1-dof vs 2-dof on {folder.name}"
        self._runner.submit(title, fits.compare_models, (folder, list(settings.estimate), settings.params),
                            lambda results: self.post(ComparisonDone(results, folder)))

    def close(self) -> None:
        self._runner.close()
