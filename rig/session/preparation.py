"""``prepare``: a session's files, addresses, plan, limits and arguments checked; nothing
written, nothing sent (:class:`~rig.errors.BadInput` → exit 2)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from identify.model import DEFAULT_ESTIMATE
from rig.config import RigConfig, load_rig_config
from rig.drivers.daq import Calibration, check_daq_address
from rig.drivers.registers import RegisterMap, load_register_map
from rig.drivers.shaker import ShakerAddress
from rig.errors import RigFault
from rig.planning.plans import Plan, PlanError, check_plan, load_plan
from rig.session.outcome import ExitStatus, stored_exit_status
from rig.session.storage import Session, SessionError


@dataclass
class RunOptions:
    plan: str
    shaker: str | None
    daq: str | None
    out: Path
    experiments: list[str] | None = None
    periods: int | None = None
    resume: bool = False
    reset_alarm: bool = False               # clear an alarm latched before the session (read and logged first)
    identify: bool = False
    on_alarm: str = "abort"                 # or "skip"
    rig_config: str | None = None
    calibration: str | None = None
    register_map: str | None = None
    model: str = "2dof"
    params: str | None = None
    estimate: list[str] = field(default_factory=list)   # empty: the plan's purpose, else the model's default
    date: str | None = None
    unit_serial: str = "unknown"
    order: str | None = None                # thermal or fixed; None: the plan's, and a --experiments list as given


class PlanRefused(PlanError):
    """The plan breaks the rig's limits; every violation is listed."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.problems = problems
        if len(problems) == 1:   # one violation: one line
            super().__init__(f"plan refused, nothing moved (the limits in {source}): {problems[0]}")
            return
        lines = "\n".join(f"  {p}" for p in problems)
        super().__init__(f"plan refused, nothing moved ({len(problems)} violations of the limits in {source}):\n"
                         f"{lines}")


class AlarmLatched(RigFault):
    """The controller holds an alarm from before this session: nothing is moved until
    someone who knows why has cleared it."""


@dataclass
class Prepared:
    """Everything a session needs, checked; nothing has been written or sent yet."""

    options: RunOptions
    shaker_url: str
    daq_url: str
    config: RigConfig
    calibration: Calibration
    register_map: RegisterMap
    plan: Plan                              # as listed until ordered()
    stored: Session | None                  # the session to resume, as read

    def ordered(self, progress: Callable[[int, int], object] | None = None) -> Prepared:
        """With the plan in the order it runs. The lifecycle orders once the links have
        answered, so that a wrong or swapped address is named within seconds, not after
        the standard plan's seconds of ordering (told to ``progress``)."""
        return replace(self, plan=self.plan.ordered(self.config, progress=progress))


# ----- prepare: check everything, write nothing ----------------------------------------------------
def prepare(opt: RunOptions) -> Prepared:
    config = load_rig_config(opt.rig_config)
    calibration = Calibration.from_file(opt.calibration)
    register_map = load_register_map(opt.register_map)
    stored = None
    if opt.resume:
        stored = Session.load(opt.out)
        if stored_exit_status(stored.meta) is ExitStatus.COMPLETE:
            raise SessionError(f"{opt.out}: the session is complete; nothing to resume")
        meta = stored.meta
        if "identify" in meta and not opt.identify:   # asked for when the session began
            wanted = meta["identify"]
            opt = replace(opt, identify=True, model=wanted["model"], estimate=wanted["estimate"],
                          params=wanted["params"])
        plan = load_plan(meta["plan"]).select(meta["experiments"]).with_periods(meta["periods"])
        shaker_url = opt.shaker or meta.get("endpoints", {}).get("shaker")
        daq_url = opt.daq or meta.get("endpoints", {}).get("daq")
    else:
        Session.check_new(opt.out)
        plan = load_plan(opt.plan).select(opt.experiments).with_periods(opt.periods)
        shaker_url, daq_url = opt.shaker, opt.daq
    if not shaker_url or not daq_url:
        raise SessionError("--shaker and --daq are needed (a resumed session takes them from its session.json)")
    ShakerAddress.parse(shaker_url)
    check_daq_address(daq_url)
    problems = check_plan(plan, config)
    if problems:
        raise PlanRefused(config.source, problems)
    if stored is None:
        # Settling is most of a session and depends on the experiment before: on request
        # the order of least predicted rig time (a resumed session keeps the order it began
        # with; a list of experiments the operator typed runs as typed unless --order thermal).
        order = opt.order or ("fixed" if opt.experiments else plan.order)
        plan = replace(plan, order=order)
    opt = replace(opt, estimate=opt.estimate or designed_estimate(plan, opt.model))
    if opt.identify:
        _check_identification(opt)
    return Prepared(opt, shaker_url, daq_url, config, calibration, register_map, plan, stored)


def designed_estimate(plan: Plan, model: str) -> list[str]:
    """The parameters a fit of this plan's data estimates when none are named: those the
    plan was designed for (its purpose, for the same model), else the model's default."""
    if plan.purpose is not None and plan.purpose.model == model:
        return list(plan.purpose.estimate)
    return list(DEFAULT_ESTIMATE.get(model, ()))


def _check_identification(opt: RunOptions) -> None:
    """Model, start file and estimated names, before the rig spends an hour on data they would refuse."""
    from identify.model import load_model
    from identify.parameters import Parameters

    if not opt.estimate:
        raise PlanError("--estimate names no parameter")
    model = load_model(opt.model)
    params = Parameters.from_file(model, opt.params) if opt.params else Parameters(model)
    params.set_estimated(opt.estimate)
