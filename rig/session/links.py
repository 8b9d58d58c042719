"""``connect``: both links of a session opened and the controller's state read (a dead
link or a latched alarm ends here, nothing written: exit 3); the links' pace probed
for a prediction made before a session; the links closed again."""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from rig.config import RigConfig
from rig.drivers.daq import Calibration, Daq, DaqError
from rig.drivers.peer_identity import Peers
from rig.drivers.peers import wrong_peer_or
from rig.drivers.registers import ControllerState, RegisterMap, load_register_map
from rig.drivers.shaker import MotionInterlock, Shaker, ShakerLinkError
from rig.events import EventBus, LinkNotice
from rig.planning.prediction import LinkTiming, measured, remember
from rig.session.acquisition import Acquisition
from rig.session.preparation import AlarmLatched, Prepared

_log = logging.getLogger(__name__)


@dataclass
class Links:
    shaker: Shaker
    daq: Daq
    identity: str
    latched_alarm: str | None                # an alarm cleared by --reset-alarm, for the record
    start_position_m: float = 0.0            # where the actuator stood when the session connected
    peers: Peers | None = None               # who answered on both links (session.json, QC records)


# ----- connect: both links, and the controller's state ------------------------------------------------
def connect(prep: Prepared, on_event: Callable[[LinkNotice], object],
            interlock: MotionInterlock | None = None) -> Links:
    """Open both links for a prepared session.  The caller closes them (:func:`close_links`).
    ``interlock`` (an E-STOP's latch) vetoes every motion command from the first one on."""
    return open_links(prep.shaker_url, prep.daq_url, prep.config, prep.calibration, prep.register_map,
                      reset_alarm=prep.options.reset_alarm, on_event=on_event, interlock=interlock)


def open_links(shaker_url: str, daq_url: str, config: RigConfig, calibration: Calibration,
               register_map: RegisterMap, *, reset_alarm: bool, on_event: Callable[[LinkNotice], object],
               interlock: MotionInterlock | None = None) -> Links:
    """Open the controller and the DAQ and read the controller's state; a latched alarm
    is refused unless ``reset_alarm``.  On any failure both links are closed again."""
    shaker = Shaker(shaker_url, config.limits, register_map, reconnect_s=config.reconnect_s, on_event=on_event,
                    interlock=interlock)
    daq = Daq(daq_url, calibration, rate_hz=config.daq_rate_hz, reconnect_s=config.reconnect_s, on_event=on_event)
    links = Links(shaker, daq, "", None)
    try:
        shaker.connect()
        links.identity = daq.open()
        links.peers = Peers(shaker.identify(), links.identity)
        status = shaker.status()
        links.start_position_m = status.position_m
        if status.state is ControllerState.ALARM:
            if not reset_alarm:
                raise AlarmLatched(
                    f"the controller at {shaker_url} holds a latched alarm: {status.alarm} (stroke "
                    f"{status.position_m * 1e3:.2f} mm). Find out why, then clear it with "
                    f"'python -m rig stop --reset --shaker {shaker_url}' or run again with --reset-alarm")
            links.latched_alarm = status.alarm
            shaker.reset_alarm()
            if shaker.status().state is ControllerState.ALARM:
                raise AlarmLatched(f"the controller at {shaker_url} still holds the alarm {status.alarm} "
                                   "after a reset: the cause is still there")
    except (ShakerLinkError, DaqError) as exc:
        close_links(links)
        raise wrong_peer_or(exc, shaker_url, daq_url, register_map) from None   # the other box may have answered
    except BaseException:
        close_links(links)
        raise
    return links


def probe_timing(shaker_url: str, daq_url: str, config: RigConfig) -> LinkTiming:
    """The links' pace and latencies measured now (the session's pace probe: the DAQ
    streams, the controller's state is read; nothing moves), for a prediction made
    before a session (``rig design --shaker … --daq …``); kept as the last measured."""
    bus = EventBus()
    links = open_links(shaker_url, daq_url, config, Calibration.from_file(), load_register_map(), reset_alarm=False,
                       on_event=bus.publish_link)
    try:
        # As in a session: the DAQ's bytes journalled to disk as they come (the DAQ's stop,
        # part of every latency measured, waits for that journal's flush).
        with tempfile.TemporaryDirectory(prefix="rig-pace-probe-") as scratch:
            links.daq.attach_journal(Path(scratch) / "daq-raw.bin")
            try:
                acq = Acquisition(links.shaker, links.daq, config, bus, links.shaker.clock)
                pace = acq.measure_pace()
            finally:
                links.daq.detach_journal()
    finally:
        close_links(links, disarm=True)
        bus.close()
    timing = measured(pace, acq.answer_s, acq.overhead_s, f"{shaker_url} and {daq_url}", "a pace probe just now")
    remember(timing)
    return timing


def close_links(links: Links, *, disarm: bool = False) -> list[str]:
    """Close both links; with ``disarm``, first hand the controller back with its watchdog
    off, as the manual commands leave it: a session that ends before it ran took nothing
    over, and an armed watchdog would trip a rig left with its hydraulics on.  Each step
    is tried whatever the one before did (closing must not hide why the session ended);
    a step that failed is logged and returned, "what: why", for the caller to show."""
    steps = ([("the watchdog's disarm", links.shaker.disable_watchdog)] if disarm else []) + [
        ("the controller's link", links.shaker.close), ("the DAQ's link", links.daq.close)]
    failures = []
    for what, close in steps:
        try:
            close()
        except Exception as exc:  # noqa: BLE001 — logged and returned: the caller says it
            failures.append(f"{what}: {exc}")
            _log.warning("closing the links: %s failed: %s", what, exc)
    return failures
