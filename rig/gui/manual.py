"""Manual control (no Qt here): the console's own links to the controller and the DAQ,
held outside sessions, and the manual commands on them (hydraulics, a static position,
a sine, a fading stop, an alarm reset), each checked before anything is sent and sent
on the ``rig-command`` thread, one at a time.

Outside a session the controller's watchdog is fed by these links (if this program
dies, the controller trips and holds) and the DAQ streams for the live view.  A session
opens its links afresh, as ``rig run`` does, so :meth:`ManualControl.release` lets go of
them first (the DAQ takes one client at a time) and :meth:`ManualControl.take_back`
takes them back after the safe stop.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor

from identify.errors import IdentifyError, InputError
from rig.config import RigConfig
from rig.drivers.daq import Calibration, Daq, DaqError
from rig.drivers.estop import MotionLatch
from rig.drivers.peer_identity import Peers
from rig.drivers.peers import wrong_peer_or
from rig.drivers.registers import ControllerState, RegisterMap
from rig.drivers.shaker import Shaker, ShakerLinkError, ShakerStatus, check_waveform
from rig.errors import BadInput, RigError
from rig.events import LinkCondition, LinkNotice, Message
from rig.gui.messages import LinkState, Notice
from rig.session.links import Links, close_links

CONSOLE_RECONNECT_S = 2.0


class Heartbeat:
    """Whether the controller's watchdog is being fed, from the links' notices (the
    console's links and a session's alike)."""

    def __init__(self) -> None:
        self.ok = True

    def follow(self, state: LinkCondition) -> None:
        if state is LinkCondition.HEARTBEAT_FAILING:
            self.ok = False
        elif state is LinkCondition.HEARTBEAT_BACK:
            self.ok = True


def run_job(post: Callable[[Message], None], what: str, fn: Callable[[], None]) -> None:
    """Run one job; its failure is posted in one line (bugs with their traceback)."""
    try:
        fn()
    except (BadInput, InputError, RigError, IdentifyError) as exc:
        post(Notice(f"{what} failed: {exc}", "error"))
    except Exception as exc:  # noqa: BLE001 — a bug: shown, the console goes on
        post(Notice(f"{what}: internal error {type(exc).__name__}: {exc}\n{traceback.format_exc()}", "error"))


class ManualControl:
    def __init__(self, config: RigConfig, calibration: Calibration, register_map: RegisterMap, latch: MotionLatch,
                 post: Callable[[Message], None], heartbeat: Heartbeat, session_running: Callable[[], bool],
                 open_estop_line: Callable[[str | None], None]) -> None:
        self.config, self.calibration, self.register_map = config, calibration, register_map
        self.open_estop_line = open_estop_line
        self.latch, self.post, self.heartbeat, self.session_running = latch, post, heartbeat, session_running
        self.shaker: Shaker | None = None
        self.daq: Daq | None = None
        self.urls: tuple[str | None, str | None] = (None, None)
        self.frequency_hz: float | None = None       # the manual sine's
        self.runs = 0                                # manual sines sent: each new one is a new excitation
        self._held_before = False                    # the links were held when a session took the rig
        self._commands = ThreadPoolExecutor(1, "rig-command")

    # ----- links ----------------------------------------------------------------------------------------
    def connect(self, shaker_url: str | None, daq_url: str | None) -> Future:
        self.urls = (shaker_url, daq_url)

        def job() -> None:
            try:
                self._connect()
            except Exception as exc:
                self.post(LinkState(False, self.unconnected(str(exc))))
                raise
        return self.submit("connect", job)

    def _connect(self, taking_back: bool = False) -> None:
        if self.shaker is not None:
            return
        self._release()                 # the DAQ read alone while the controller did not answer
        if self.session_running() and not taking_back:
            raise BadInput("a session holds the rig's links: they come back to the console after its safe stop")
        shaker_url, daq_url = self.urls
        if not shaker_url or not daq_url:
            raise BadInput("give the controller's and the DAQ's addresses (--shaker, --daq) or --simulate")
        shaker = Shaker(shaker_url, self.config.limits, self.register_map, reconnect_s=CONSOLE_RECONNECT_S,
                        on_event=self._link_event, interlock=self.latch)
        daq = Daq(daq_url, self.calibration, rate_hz=self.config.daq_rate_hz, reconnect_s=CONSOLE_RECONNECT_S,
                  on_event=self._link_event)
        try:
            self.open_estop_line(shaker_url)
            shaker.connect()        # limits written, watchdog on and fed: if this program dies, the rig holds
        except ShakerLinkError as exc:
            self._close(shaker, daq)
            problem = wrong_peer_or(exc, shaker_url, daq_url, self.register_map)
            if problem is exc:   # swapped or wrong addresses: no DAQ is where the DAQ's address points
                self._daq_alone(daq_url)
            raise problem from None
        except BaseException:
            self._close(shaker, daq)
            raise
        try:
            identity = daq.open()
            peers = Peers(shaker.identify(), identity)
            daq.start()             # the live view streams whenever no session does
        except (ShakerLinkError, DaqError) as exc:
            self._close(shaker, daq)
            raise wrong_peer_or(exc, shaker_url, daq_url, self.register_map) from None
        except BaseException:
            self._close(shaker, daq)
            raise
        self.shaker, self.daq = shaker, daq
        self.post(LinkState(True, f"controller {shaker_url}, DAQ {daq_url} ({identity})", peers.simulated))

    def _close(self, shaker: Shaker, daq: Daq) -> None:
        """Links that failed to open, closed again; a step that failed is said, not swallowed."""
        for failure in close_links(Links(shaker, daq, "", None)):
            self.post(Notice(f"closing the links after the failed connect: {failure}", "error"))

    def _daq_alone(self, daq_url: str) -> None:
        """The controller did not answer: the DAQ is read all the same, for it is the one
        independent proof (stroke and force) of whether the rig moves.  No command goes
        anywhere without the controller, so nothing else is held."""
        daq = Daq(daq_url, self.calibration, rate_hz=self.config.daq_rate_hz, reconnect_s=CONSOLE_RECONNECT_S,
                  on_event=self._link_event)
        try:
            daq.open()
            daq.start()
        except Exception as exc:  # noqa: BLE001 — said beside the controller's own failure
            daq.close()
            self.post(Notice(f"DAQ at {daq_url} not read either: {exc}", "error"))
            return
        self.daq = daq

    def _release(self) -> None:
        shaker, daq = self.shaker, self.daq
        self.shaker = self.daq = None
        for link in (shaker, daq):
            if link is not None:
                try:
                    link.close()
                except Exception as exc:  # noqa: BLE001 — closing must not hide why the links went: said beside it
                    self.post(Notice(f"closing the console's {'controller' if link is shaker else 'DAQ'} link "
                                     f"failed: {exc}", "error"))

    def disconnect(self) -> Future:
        def job() -> None:
            self._release()
            self.post(LinkState(False, "disconnected"))
        return self.submit("disconnect", job)

    def release(self) -> None:
        """Let go of the links for a session (waits until they are closed)."""
        self._held_before = self.shaker is not None or self.daq is not None
        self._commands.submit(self._release).result()
        if self._held_before:
            self.post(LinkState(False, "the session holds the links: the controller and the DAQ are read on its "
                                       "own until its safe stop"))

    def take_back(self) -> None:
        """After a session: the links again, if they were held before it; if they cannot
        be opened, the link line says so (not the session's last words)."""
        if not self._held_before:
            return
        self._held_before = False

        def job() -> None:
            try:
                self._connect(taking_back=True)
            except Exception as exc:
                why = f"the links were not taken back after the session ({exc})"
                self.post(LinkState(False, self.unconnected(why)))
                raise
        self.submit("reconnect", job)

    def unconnected(self, why: str) -> str:
        """The link line when the controller is not connected: whether the DAQ is read all the same."""
        return f"not connected: {why}" + ("; the DAQ alone is read, for the live view" if self.daq is not None else "")

    def _link_event(self, notice: LinkNotice) -> None:
        self.heartbeat.follow(notice.state)
        self.post(Notice(notice.message))

    # ----- manual commands: checked here, sent on the command thread ------------------------------------
    def _refuse(self, status: ShakerStatus | None, need_hydraulics: bool, motion: bool = True) -> list[str]:
        if self.session_running():
            return ["a session is running: abort it first"]
        if motion and self.latch.latched:
            return [f"{self.latch.reason}: confirm the reset first"]
        if self.shaker is None:
            return ["not connected"]
        if status is not None and status.state is ControllerState.ALARM:
            return [f"alarm latched ({status.alarm}): reset it first"]
        if need_hydraulics and status is not None and status.state is ControllerState.OFF:
            return ["the hydraulics are off: switch them on first"]
        return []

    def _send(self, what: str, problems: list[str], action: Callable[[Shaker], None]) -> list[str]:
        """Send ``action`` unless ``problems``; the refusal is returned and posted, nothing sent."""
        if problems:
            self.post(Notice(f"{what} refused, nothing sent: {'; '.join(problems)}", "refused"))
            return problems
        shaker = self.shaker
        assert shaker is not None  # _refuse checked it

        def job() -> None:
            action(shaker)      # returns once the controller has answered the write
            self.post(Notice(f"{what}: written, the controller answered"))
        self.submit(what, job)
        return []

    def hydraulics(self, on: bool, status: ShakerStatus | None) -> list[str]:
        problems = self._refuse(status, need_hydraulics=False, motion=on)
        return self._send(f"hydraulics {'on' if on else 'off'}", problems, lambda s: s.hydraulics(on))

    def move(self, static_m: float, status: ShakerStatus | None) -> list[str]:
        lim = self.config.limits
        problems = self._refuse(status, need_hydraulics=True)
        if not lim.stroke_low_m <= static_m <= lim.stroke_high_m:
            problems.append(f"static position {static_m * 1e3:.2f} mm outside the stroke limits "
                            f"{lim.stroke_low_m * 1e3:.1f}…{lim.stroke_high_m * 1e3:.1f} mm")
        return self._send(f"move to {static_m * 1e3:.2f} mm", problems, lambda s: s.move_to(static_m))

    def sine(self, static_m: float, amplitude_m: float, frequency_hz: float, status: ShakerStatus | None) -> list[str]:
        problems = self._refuse(status, need_hydraulics=True)
        problems += check_waveform(self.config.limits, static_m, amplitude_m, frequency_hz)
        ramp = self.config.steady_state.ramp_time_s

        def run(s: Shaker) -> None:
            s.run(static_m, amplitude_m, frequency_hz, "sine", ramp)
            self.frequency_hz = frequency_hz
            self.runs += 1
        return self._send(f"sine {amplitude_m * 1e3:.2f} mm at {frequency_hz:g} Hz around {static_m * 1e3:.2f} mm",
                          problems, run)

    def fade_stop(self, status: ShakerStatus | None) -> list[str]:
        """Stop: fade a running waveform out (then hold), else hold at once."""
        problems = self._refuse(None, need_hydraulics=False, motion=False)
        # A fade is a move to the static position: after an E-STOP only STOP holds.
        running = status is not None and status.state is ControllerState.RUNNING and not self.latch.latched

        def stop(s: Shaker) -> None:
            s.fade_out() if running else s.stop()
        return self._send("fade out" if running else "stop", problems, stop)

    def reset_alarm(self) -> list[str]:
        problems = ["a session is running: abort it first"] if self.session_running() else []
        if self.shaker is None and not problems:
            problems = ["not connected"]
        return self._send("alarm reset", problems, lambda s: s.reset_alarm())

    # ----- plumbing ---------------------------------------------------------------------------------------
    def submit(self, what: str, fn: Callable[[], None]) -> Future:
        return self._commands.submit(run_job, self.post, what, fn)

    def close(self) -> None:
        """The links closed and the command thread ended."""
        self._commands.submit(self._release)
        self._commands.shutdown(wait=True)
