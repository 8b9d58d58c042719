"""The rig side of the operator's console (no Qt here): its pieces, each with one job and
a thread of its own, wired together.  Whatever happens is *posted* as a small typed
record (:mod:`rig.gui.messages`) into a queue that the window drains on its own timer,
so that the GUI thread never talks to the rig, and the rig never waits on the GUI.

=====================  ==================================================  ================
piece                  its job                                             thread
=====================  ==================================================  ================
``manual``             the console's own links and the manual commands     ``rig-command``
                       (:class:`~rig.gui.manual.ManualControl`)
``sessions``           a plan or a unit's QC test through the one          ``rig-session``
                       lifecycle (:class:`~rig.gui.session_worker.SessionWorker`)
``poller``             the controller's status and the DAQ's counters,     ``rig-status``
                       4 times a second, from whichever links hold the rig
                       (:class:`~rig.gui.status_poller.StatusPoller`)
``emergency``          the E-STOP and its latch                            ``e-stop``
                       (:class:`~rig.gui.emergency.EmergencyStop`)
``fits``               identification, re-fits, the comparison, each in    ``fit``
                       a process of its own (:class:`~rig.gui.fitting.Fitting`)
=====================  ==================================================  ================
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path

from rig.config import RigConfig, load_rig_config
from rig.drivers.daq import Calibration, Daq
from rig.drivers.registers import RegisterMap, load_register_map
from rig.drivers.shaker import Shaker
from rig.events import Message
from rig.gui.emergency import EmergencyStop
from rig.gui.fitting import Fitting, IdentifySettings
from rig.gui.manual import Heartbeat, ManualControl
from rig.gui.session_worker import SessionWorker
from rig.gui.status_poller import StatusPoller
from rig.session.preparation import RunOptions


class Station:
    def __init__(self, shaker_url: str | None, daq_url: str | None, post: Callable[[Message], None], *,
                 rig_config: str | None = None, calibration: str | None = None, register_map: str | None = None
                 ) -> None:
        self.post = post
        self.config_files = {"rig_config": rig_config, "calibration": calibration, "register_map": register_map}
        self.config: RigConfig = load_rig_config(rig_config)
        cal = Calibration.from_file(calibration)
        registers: RegisterMap = load_register_map(register_map)
        self.heartbeat = Heartbeat()
        self.fits = Fitting(post)
        self.emergency = EmergencyStop(self.config, registers, self.active_shaker,
                                       lambda reason: self.sessions.request_stop(reason), post)
        self.manual = ManualControl(self.config, cal, registers, self.emergency.latch, post, self.heartbeat,
                                    lambda: self.sessions.running, self.emergency.open_line)
        self.manual.urls = (shaker_url, daq_url)
        self.sessions = SessionWorker(post, self.manual, self.emergency, self.heartbeat, self.config_files,
                                      self.fits.identify)
        self.poller = StatusPoller(self.links, post, lambda: self.heartbeat.ok)

    def links(self) -> tuple[Shaker | None, Daq | None, bool]:
        """The links that hold the rig now: a session's while one runs, else the console's."""
        shaker, daq = self.sessions.links()
        if shaker is not None:
            return shaker, daq, True
        return self.manual.shaker, self.manual.daq, False

    def active_shaker(self) -> Shaker | None:
        return self.links()[0]

    def live_daq(self) -> Daq | None:
        return self.links()[1]

    @property
    def urls(self) -> tuple[str | None, str | None]:
        return self.manual.urls

    def connect(self, shaker_url: str | None = None, daq_url: str | None = None) -> Future:
        old_shaker, old_daq = self.manual.urls
        return self.manual.connect(shaker_url or old_shaker, daq_url or old_daq)

    def abort(self, why: str = "Abort pressed by the operator") -> None:
        """The safe stop of a running session: fade out, STOP, hydraulics off."""
        self.sessions.request_stop(why)

    def close(self, timeout_s: float = 60.0) -> None:
        """Safe stop of a running session, then every link closed and every thread ended."""
        self.sessions.closing = True
        if self.sessions.running:
            self.abort("the console is closing")
        self.sessions.wait(timeout_s)
        self.poller.close()
        self.emergency.close()
        self.manual.close()
        self.fits.close()


def session_options(plan: str, shaker: str | None, daq: str | None, out: Path, experiments: list[str] | None,
                    station: Station, identify: IdentifySettings | None, resume: bool = False) -> RunOptions:
    """The options ``rig run`` would be given for the same session."""
    files = station.config_files
    opt = RunOptions(plan=plan, shaker=shaker, daq=daq, out=out, experiments=experiments, resume=resume,
                     identify=identify is not None, rig_config=files["rig_config"],
                     calibration=files["calibration"], register_map=files["register_map"])
    if identify is not None:
        opt.model, opt.params, opt.estimate = identify.model, identify.params, list(identify.estimate)
    return opt
