"""Experiment plans: the standard set built in, or a TOML file; checked against the
rig's limits before anything moves (every violation listed), with an estimated
duration: the controller's moves and ramps, the acquisition's waits and blocks, and
the thermal settling predicted from the damper model (:mod:`rig.planning.settling`)."""

from __future__ import annotations

import difflib
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from identify.errors import InputError
from identify.parameters import Parameters
from identify.plans import CAPTURES, STANDARD_SET, ExperimentSpec, Purpose
from rig.config import RigConfig
from rig.drivers.shaker import check_waveform
from rig.errors import BadInput
from rig.planning.criterion import first_block_s
from rig.planning.ordering import Progress, thermal_order
from rig.planning.settling import DRIFT_DRAWS, PAUSE_S, Conditioning, Hold, predict_settling
from rig.tomlfile import read_toml

EXPERIMENT_KEYS = {"label", "group", "static_mm", "amplitude_mm", "frequency_Hz", "waveform", "periods", "capture"}
PLAN_KEYS = {"name", "periods", "order", "experiment", "capture", "purpose"}


class PlanError(BadInput):
    """A plan that cannot be run (file problems, or limit violations listed one per line)."""


ORDERS = ("thermal", "fixed")
BUILT_IN = ("standard",)    # plans known by name (load_plan); any other is a file


@dataclass(frozen=True)
class Plan:
    """``order``: ``thermal`` runs the experiments in the order of least predicted rig time
    (rig.planning.ordering), ``fixed`` as listed."""

    name: str
    experiments: tuple[ExperimentSpec, ...]
    text: str = ""
    order: str = "fixed"
    purpose: Purpose | None = None   # what a designed plan is for (its [purpose] table)

    def select(self, letters: list[str] | None) -> Plan:
        if not letters:
            return self
        by_letter = {e.letter: e for e in self.experiments}
        unknown = [x for x in letters if x not in by_letter]
        if unknown:
            raise PlanError(f"plan {self.name!r} has no experiment {', '.join(unknown)} "
                            f"(letters: {', '.join(by_letter)})")
        return replace(self, experiments=tuple(by_letter[x] for x in letters))

    def ordered(self, config: RigConfig, start_position_m: float = 0.0, progress: Progress | None = None) -> Plan:
        """The plan in the order it runs: as listed when ``order = "fixed"``, else the
        order of least predicted rig time from rest at ``start_position_m`` (seconds of CPU
        for the standard plan, told to ``progress``). The result is fixed: ordering it
        again costs nothing."""
        if self.order == "fixed" or len(self.experiments) < 2:
            return self

        def durations(sequence: Sequence[ExperimentSpec]) -> list[float]:
            # Noise-free: an order is chosen on the transients its transitions leave, and the
            # noise floor each experiment settles to is its own whatever comes before it.
            return [d.total_s for d in estimate_experiment_durations(Plan("order", tuple(sequence)), config,
                                                                     start_position_m, noise_draws=0)]
        return replace(self, experiments=thermal_order(self.experiments, durations, progress), order="fixed")

    def with_periods(self, periods: int | None) -> Plan:
        if periods is None:
            return self
        if periods < 1:
            raise PlanError(f"--periods {periods}: at least one whole period must be captured")
        return replace(self, experiments=tuple(replace(e, periods=periods) for e in self.experiments))


def comma_list(text: str | None) -> list[str] | None:
    """A comma-separated list as typed (``a, h,`` -> ['a', 'h']); None when it names nothing."""
    return [x.strip() for x in text.split(",") if x.strip()] or None if text else None


def load_plan(source: str) -> Plan:
    """``standard`` or the path of a plan TOML file.  A QC spec is a plan file with more
    tables (it checks its own keys), so a top-level key is refused only when it is a near
    miss of a plan key."""
    if source == "standard":
        # In the order of least predicted rig time: listed, its high group starts with a
        # 116 mm compression whose heat c has to lose where the gas's wall area is least.
        return Plan("standard", STANDARD_SET, "standard", "thermal")
    path = Path(source)
    if not path.exists():   # a misspelt name reads as a missing file: say what plans there are
        meant = difflib.get_close_matches(source, BUILT_IN, n=1)
        raise PlanError(f"plan {source!r}: no such plan and no such file"
                        + (f" (did you mean {meant[0]!r}?)" if meant else "")
                        + f"; the plans: {', '.join(BUILT_IN)} (built in), or the path of a plan TOML file")
    text, doc = read_toml(path, PlanError, "plan ")
    for key in sorted(set(doc) - PLAN_KEYS):
        meant = difflib.get_close_matches(key, PLAN_KEYS, n=1)
        if meant:   # a misspelt order (ordr) would silently run the plan as listed
            raise PlanError(f"plan {path}: unknown key {key!r} (did you mean {meant[0]!r}?)")
    entries = doc.get("experiment", [])
    if not entries:
        raise PlanError(f"plan {path}: no [[experiment]] tables")
    experiments, seen = [], set()
    for i, e in enumerate(entries, 1):
        where = f"plan {path}, experiment {i}"
        unknown = sorted(set(e) - EXPERIMENT_KEYS)
        if unknown:   # a misspelt optional key (period for periods) would silently take its default
            raise PlanError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                            f"(known: {', '.join(sorted(EXPERIMENT_KEYS))})")
        try:
            spec = ExperimentSpec(str(e["label"]), str(e.get("group", "")), float(e["static_mm"]),
                                  float(e["amplitude_mm"]), float(e["frequency_Hz"]), str(e.get("waveform", "sine")),
                                  int(e.get("periods", doc.get("periods", 3))),
                                  str(e.get("capture", doc.get("capture", "steady"))))
        except KeyError as exc:
            raise PlanError(f"{where}: missing key {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise PlanError(f"{where}: {exc}") from None
        if spec.capture not in CAPTURES:
            raise PlanError(f"{where}: capture {spec.capture!r} is not one of {', '.join(CAPTURES)}")
        if spec.letter in seen:
            raise PlanError(f"{where}: label {spec.letter!r} used twice")
        seen.add(spec.letter)
        experiments.append(spec)
    order = str(doc.get("order", "fixed"))
    if order not in ORDERS:
        raise PlanError(f"plan {path}: order {order!r} is not one of {', '.join(ORDERS)}")
    try:
        purpose = Purpose.from_document(doc["purpose"], f"plan {path}") if "purpose" in doc else None
    except InputError as exc:   # identify's words, the rig's refusal (exit 2 like every plan error)
        raise PlanError(str(exc)) from None
    return Plan(str(doc.get("name", path.stem)), tuple(experiments), text, order, purpose)


def check_plan(plan: Plan, config: RigConfig) -> list[str]:
    """Every violation of the rig's limits and capabilities, one line each."""
    problems = []
    for e in plan.experiments:
        for p in check_waveform(config.limits, e.static_position_mm * 1e-3, e.amplitude_mm * 1e-3,
                                e.frequency_hz, e.waveform):
            problems.append(f"experiment {e.letter}: {p}")
        if e.periods < 1:
            problems.append(f"experiment {e.letter}: periods {e.periods} < 1")
        if config.stroke_envelope_m is not None:
            # Past a stop but within the controller's trip limits (beyond them the limits' line says it).
            limits = (config.limits.stroke_low_m, config.limits.stroke_high_m)
            problems += [f"experiment {e.letter}: {p}" for p in envelope_problems(e, *config.stroke_envelope_m, limits)]
    return problems


def envelope_problems(e: ExperimentSpec, full_extension_m: float, bottom_out_m: float,
                      limits: tuple[float, float] = (-math.inf, math.inf)) -> list[str]:
    """Where experiment ``e`` commands the stroke past the damper's end stops, but not
    past ``limits`` (the controller's trip limits, whose own check says that)."""
    low, high = (e.static_position_mm - e.amplitude_mm) * 1e-3, (e.static_position_mm + e.amplitude_mm) * 1e-3
    problems = []
    # The stop engages at contact: commanding onto it is commanding into it (the
    # actuator's overshoot, micrometres, meets a stop as stiff as the stroke's steel).
    if limits[0] <= low <= full_extension_m:
        problems.append(f"commands the stroke to {low * 1e3:.1f} mm, past the damper's full extension at "
                        f"{full_extension_m * 1e3:.1f} mm")
    if bottom_out_m <= high <= limits[1]:
        problems.append(f"commands the stroke to {high * 1e3:.1f} mm, past the damper's bottom-out at "
                        f"{bottom_out_m * 1e3:.1f} mm")
    return problems


@dataclass(frozen=True)
class ExperimentDuration:
    """Rig time of one experiment of a plan, phase by phase [s]."""

    letter: str
    pause_s: float        # at rest before it: commands, handshakes, writing the previous data
    move_s: float         # to its static position (the controller's profile), by way of the hold
    lead_in_s: float      # RUN to the first comparison block (amplitude ramp + the acquisition's wait)
    settle_cycles: int    # predicted by rig.planning.settling
    settle_s: float       # the comparison blocks until the criterion passes
    capture_s: float      # the captured periods
    fade_s: float         # the waveform faded out to the static position
    hold: Hold | None = None   # the thermal conditioning hold on the way, if any
    time_constant_s: float = math.nan   # the gas's relaxation there, predicted
    links_s: float = 0.0  # the acquisition's polls and the links' commands, at their pace (rig seconds)

    @property
    def total_s(self) -> float:
        hold_s = self.hold.duration_s if self.hold else 0.0
        return (self.pause_s + self.move_s + hold_s + self.lead_in_s + self.settle_s + self.capture_s + self.fade_s
                + self.links_s)


def conditioning_for(plan: Plan, config: RigConfig, pace: float = 1.0, answer_s: float = 0.0) -> Conditioning | None:
    """Where conditioning holds may go: within the stroke the plan's experiments sweep
    anyway (and the rig's limits), so that a hold takes the damper nowhere new; and how
    short a hold may be on a link that runs ``pace`` rig seconds per second (a simulator
    at 50x): a hold ends on the measured temperature, which the acquisition sees and
    answers a few tenths of a second late, tenths of a kelvin in a short hold and
    fifty times as much, in the rig's time, at 50x.

    How far off a hold's end is answered, in the rig's seconds: the acquisition's own
    timing (``hold_timing_s``) and the commands between the hold's end and RUN
    (``answer_s``, measured by :meth:`rig.session.acquisition.Acquisition.measure_pace`), both
    in the links' seconds, times the pace (see :func:`rig.planning.settling.landing_error_k`)."""
    if config.max_hold_s <= 0 or not plan.experiments:
        return None
    low = min(e.static_position_mm - e.amplitude_mm for e in plan.experiments) * 1e-3
    high = max(e.static_position_mm + e.amplitude_mm for e in plan.experiments) * 1e-3
    return Conditioning((max(low, config.limits.stroke_low_m), min(high, config.limits.stroke_high_m)),
                        config.max_hold_s, max(config.min_hold_s, config.min_hold_s * pace),
                        (config.hold_timing_s + answer_s) * pace)


def estimate_experiment_durations(plan: Plan, config: RigConfig, start_position_m: float = 0.0,
                                  params: Parameters | None = None, *, start_temperature_k: float | None = None,
                                  pause_s: float | Sequence[float] = PAUSE_S, pace: float = 1.0,
                                  answer_s: float = 0.0, overhead_s: float = 0.0,
                                  noise_draws: int = DRIFT_DRAWS) -> list[ExperimentDuration]:
    """Per experiment, in plan order, the rig time it will take when the plan runs from
    the damper resting at ``start_position_m`` (and ``start_temperature_k``, default
    ambient).  ``params``: the damper's parameters for the settling prediction
    (default: the 2-dof model's nominal values); ``pause_s``: the rig's time at rest
    before each experiment (one for all, or one per experiment); ``pace``: the link's
    rig seconds per second and ``answer_s`` the time [s] its commands take between a
    hold's end and RUN (see :func:`conditioning_for`); ``overhead_s`` the time [s] an
    experiment's polls and commands take beyond the rig's own motion (both measured by
    :meth:`rig.session.acquisition.Acquisition.measure_pace`), rig time at the pace, and a held
    experiment's ``answer_s`` too: nothing on a rig, where they are milliseconds, a few
    seconds each on a simulator at 50x; ``noise_draws``: see
    :func:`rig.planning.settling.predict_settling`."""
    ss, rate = config.steady_state, config.daq_rate_hz
    settling = predict_settling(plan.experiments, ss, rate, params, start_position_m=start_position_m,
                                start_temperature_k=start_temperature_k, pause_s=pause_s,
                                conditioning=conditioning_for(plan, config, pace, answer_s),
                                noise_draws=noise_draws, move=config.move)
    pauses = np.broadcast_to(np.asarray(pause_s, dtype=float), len(plan.experiments))
    out, position = [], start_position_m
    for e, s, pause in zip(plan.experiments, settling, pauses, strict=True):
        static = e.static_position_mm * 1e-3
        samples_per_period = rate / e.frequency_hz
        # Blocks and the capture are whole samples, as the acquisition cuts them.
        move = config.move.duration_s
        move_s = (move(s.hold.position_m - position) + move(static - s.hold.position_m) if s.hold
                  else move(static - position))
        if e.capture == "transient":  # no hold, no settling: the capture starts at RUN, the ramp included
            out.append(ExperimentDuration(e.letter, float(pause), move(static - position), 0.0, 0, 0.0,
                                          transient_capture_s(e, ss.ramp_time_s, rate), ss.ramp_time_s, None,
                                          s.time_constant_s, pace * overhead_s))
            position = static
            continue
        out.append(ExperimentDuration(e.letter, float(pause), move_s,
                                      first_block_s(ss, rate), s.cycles, round(s.cycles * samples_per_period) / rate,
                                      math.ceil(e.periods * samples_per_period) / rate, ss.ramp_time_s, s.hold,
                                      s.time_constant_s, pace * (overhead_s + (answer_s if s.hold else 0.0))))
        position = static
    return out


def transient_capture_s(e: ExperimentSpec, ramp_time_s: float, rate_hz: float) -> float:
    """Rig seconds a transient capture records: from RUN, the amplitude ramp, then the
    plan's periods at full amplitude (whole samples, as the acquisition cuts them)."""
    return math.ceil(ramp_time_s * rate_hz + e.periods * rate_hz / e.frequency_hz) / rate_hz


def estimate_duration_s(plan: Plan, config: RigConfig, start_position_m: float = 0.0,
                        params: Parameters | None = None) -> float:
    """Rig time of the whole plan [s] (see :func:`estimate_experiment_durations`)."""
    return sum(d.total_s for d in estimate_experiment_durations(plan, config, start_position_m, params))
