"""Result sinks: where a batch's results go beyond RESULTS_DIR, as they arrive.

``identify batch --db URL`` hands each converged result to a sink that some other
package provides: the QC records database belongs to ``rig``, which ``identify`` does not
import (dependencies point one way).  A package offers a sink through the entry point
group ``identify.result_sinks``; the entry point's name is the option's (``db`` for
``--db``) and its object a factory ``(url) -> ResultSink``.  The factory checks its
destination at once (the batch opens it before any task runs, so a wrong URL costs no
fit) and raises :class:`SinkError` when it cannot be used.

A sink runs in the batch's client process, one result at a time in the order they
arrive, and only there does it write: it needs no locking of its own, and a worker that
dies cannot leave half a delivery.  Work too long for the client (QC's characteristics
integrate the drop test: seconds per session, as long as a fit) a sink hands back as a
:class:`Task`, which the batch runs on the cluster ahead of the remaining fits and whose
value it gives to :meth:`ResultSink.finish`, on the client again.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from importlib.metadata import entry_points
from typing import Any, Protocol

from identify.errors import InputError

GROUP = "identify.result_sinks"


class SinkError(InputError):
    """A sink that cannot be loaded or opened (exit 2, before any task runs)."""


class DeliveryState(StrEnum):
    """What a sink did with one session's result (see :class:`Delivery`)."""

    WRITTEN = "written"
    PRESENT = "present"
    PASSED = "passed"
    FAILED = "failed"


@dataclass(frozen=True)
class Delivery:
    """What a sink did with one session's result.

    ``written``  the result went in (``text``: what it became, e.g. a verdict);
    ``present``  an earlier run already put this very result in (nothing written);
    ``passed``   the result does not belong there (``text`` says why: no record of the
                 data, another model...): nothing written, nothing wrong;
    ``failed``   it belonged there and could not be written (``text``: the reason);
                 the batch exits 1, and the next run tries again.
    """

    state: DeliveryState  # the state's word ("written", ...) is taken too, for sinks written before the enum
    text: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "state", DeliveryState(self.state))


class BatchState(StrEnum):
    """What became of one session in a batch run."""

    OK = "ok"            # fitted now and converged
    FAILED = "failed"    # not converged, or could not be fitted (``SessionOutcome.reason`` says why)
    SKIPPED = "skipped"  # converged in an earlier run, with the same data and settings


@dataclass(frozen=True)
class SessionOutcome:
    """One row of the summary: what became of one session in this run."""

    session: str  # the folder name, which is also the result's file name
    path: str
    state: BatchState  # the state's word ("ok", ...) is taken too
    serial: str = ""
    converged: bool = False
    fit_s: float | None = None
    values: dict[str, float] = field(default_factory=dict)
    stds: dict[str, float | None] = field(default_factory=dict)  # the σ to quote (see residual_std)
    # The stds are the residual-based ones: the residuals exceed the measurement noise
    # (model error), and the noise's σ would understate the uncertainty.
    residual_std: bool = False
    delivery: Delivery | None = None  # what the result sink did with it (with a sink, for a converged result)
    reason: str = ""  # why it failed (empty otherwise)

    def __post_init__(self) -> None:
        object.__setattr__(self, "state", BatchState(self.state))

    @property
    def failed(self) -> bool:
        return self.state is BatchState.FAILED

    @property
    def status(self) -> str:
        """``ok``, ``failed: <reason>`` or ``skipped``: the sentence, rendered from the state."""
        return f"{self.state}: {self.reason}" if self.reason else str(self.state)


@dataclass(frozen=True)
class Task:
    """Work a sink wants done on the cluster before it writes: ``function(*args)`` as a
    Dask task.  The function must be importable on the workers (a module-level function
    of a package installed there, as the batch's own is) and its arguments and value
    picklable; an exception it raises reaches :meth:`ResultSink.finish` as the value."""

    function: Callable[..., Any]
    args: tuple[Any, ...]


class ResultSink(Protocol):
    """A destination for a batch's converged results."""

    name: str  # where the results go, as it may be shown (no credentials)

    def deliver(self, outcome: SessionOutcome, result: dict[str, Any]) -> Delivery | Task:
        """Take one session's converged result (its RESULT.json document, ``batch``
        block included): deliver it, or ask for a :class:`Task` first.  The session's
        own faults are a ``failed`` delivery, never an exception: one session cannot
        stop the others."""
        ...

    def finish(self, outcome: SessionOutcome, task: Task, value: Any) -> Delivery:
        """Deliver ``outcome``'s result with the value of the task that :meth:`deliver`
        asked for (an exception if the task raised one or was lost)."""
        ...

    def summary(self) -> list[str]:
        """Lines for the terminal once the batch is over: what was delivered, with counts."""
        ...

    def close(self) -> None: ...


SinkFactory = Callable[[str], ResultSink]


def open_sink(option: str, url: str) -> ResultSink:
    """The sink installed under ``option``'s name, opened on ``url``.  The URL is not
    repeated in the messages raised here: it may carry a password, and only the sink
    knows how to show it without."""
    found = {ep.value: ep for ep in entry_points(group=GROUP, name=option)}  # one per target, however installed
    if not found:
        raise SinkError(f"--{option}: no result sink {option!r} is installed (entry point group {GROUP}); "
                        f"it comes with the damper-rig project's rig package: install the project, not identify alone")
    if len(found) > 1:
        raise SinkError(f"--{option}: several result sinks {option!r} are installed ({', '.join(sorted(found))}); "
                        f"uninstall all but one")
    (ep,) = found.values()
    try:
        factory = ep.load()
    except (ImportError, AttributeError) as exc:
        raise SinkError(f"--{option}: the result sink {ep.value} cannot be loaded ({exc})") from None
    sink: ResultSink = factory(url)
    return sink
