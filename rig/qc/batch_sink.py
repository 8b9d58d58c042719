"""``identify batch --db URL``: a batch's results as QC re-judgements.

The result sink (identify.sinks) that pyproject.toml installs under the entry point
``identify.result_sinks: db``.  For each session the batch identified, whose measured
data already has a QC record (found by the records' ``data_sha256``), it judges the data
again as ``qc judge`` does, but with the batch's parameters and covariance instead of a
fit of its own, and adds a record that refers to the first record of the data.  The
look-ups and the write happen in the batch's client; the judgement itself (the
characteristics: the drop test's integrations take about as long as a fit) is a task on
the cluster, :func:`judge_result`.

- The spec is the one of the data's latest record, found by its sha256: the file the
  session was run with (its ``session.json`` names it) or the spec of that name shipped
  in rig/qc/specs.  It applies when its model (name and version) and its estimated set
  are the batch's; otherwise nothing is written and the summary says why.
- A re-judgement is keyed by the batch result's key and the spec's sha256: its uid is
  derived from both, so a rerun (or a second client on the same results) finds it and
  adds none, and the database's unique uid refuses a duplicate even from a race.
- Only an existing records database is opened, before any fit runs; nothing is written
  into the session folders (the batch only reads them, and they may be read-only).
"""

from __future__ import annotations

import hashlib
import json
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from identify.batch import SessionOutcome
from identify.errors import IdentifyError
from identify.fit_warnings import FitWarning, WarningCode
from identify.model import CompiledModel
from identify.parameters import Parameters
from identify.sinks import Delivery, DeliveryState, SinkError, Task
from rig.errors import RigError
from rig.qc.characteristics import Identified, check_model
from rig.qc.evaluate import evaluate_identified, verdict_note
from rig.qc.records import QcRecord, Records, RecordsError
from rig.qc.run import judged_record, rejudge_remedy
from rig.qc.spec import SPECS_DIR, Spec, load_spec
from rig.qc.trace import SessionTrace, trace_session

# uuid5 namespace of batch re-judgements: uid = uuid5(NAMESPACE, "<result key> <spec sha256>")
NAMESPACE = uuid.UUID("3f0c7a52-5c1e-4d43-9a57-6c0de2b1a7e4")
NO_RECORD = "no QC record of this data"
SHOWN = 3  # sessions named per reason in the summary


def open_sink(url: str) -> Rejudgements:
    """The entry point's factory: the records database at ``url``, which must exist."""
    try:
        return Rejudgements(Records.open(url, create=False))
    except RecordsError as exc:
        raise SinkError(str(exc) if str(exc).startswith("--db") else f"--db: {exc}") from None


class NotApplicable(RigError):
    """No spec applies to this result (the reason is the message): nothing to write."""


class Rejudgements:
    """The result sink: one re-judgement record per converged result where a spec applies."""

    def __init__(self, records: Records) -> None:
        self.records = records
        self.name = records.name
        self._specs: dict[tuple[Path, str], Spec] = {}  # (file, sha256) → the spec, each loaded once
        self._by_state: dict[DeliveryState, list[tuple[str, str]]] = {}  # state → (session, text), in arrival order

    def deliver(self, outcome: SessionOutcome, result: dict[str, Any]) -> Delivery | Task:
        try:
            return self._deliver(outcome, result)
        except NotApplicable as exc:
            return self._count(outcome, Delivery(DeliveryState.PASSED, str(exc)))
        except (RigError, IdentifyError, OSError, ValueError) as exc:  # the records' and the data's own faults
            return self._count(outcome, Delivery(DeliveryState.FAILED, str(exc)))

    def _deliver(self, outcome: SessionOutcome, result: dict[str, Any]) -> Delivery | Task:
        session = Path(outcome.path)
        trace = trace_session(session)
        history = self.records.for_data(trace.data_sha256)
        if not history:
            raise NotApplicable(NO_RECORD)
        first, latest = history[0], history[-1]
        spec = self._spec(latest, session)
        _check_applies(spec, check_model(spec), result)
        uid = str(uuid.uuid5(NAMESPACE, f"{result['batch']['key']} {spec.sha256}"))
        earlier = next((r for r in history if r.uid == uid), None)
        if earlier is not None:
            return self._count(outcome, Delivery(DeliveryState.PRESENT, _verdict(earlier)))
        identity = {"serial": first.serial, "operator": first.operator, "rig": first.rig,
                    "station": first.station, "simulated": first.simulated}
        return Task(judge_result, (spec, trace, result, first.uid, uid, identity))

    def finish(self, outcome: SessionOutcome, task: Task, value: Any) -> Delivery:
        if isinstance(value, (RigError, IdentifyError, OSError, ValueError)):
            return self._count(outcome, Delivery(DeliveryState.FAILED, str(value)))
        if isinstance(value, BaseException):
            return self._count(outcome, Delivery(DeliveryState.FAILED,
                                                 f"internal error: {type(value).__name__}: {value}"))
        record: QcRecord = value
        try:
            self.records.add(record)
        except RecordsError as exc:
            if any(r.uid == record.uid for r in self.records.for_data(record.data_sha256)):
                # another client wrote it first
                return self._count(outcome, Delivery(DeliveryState.PRESENT, _verdict(record)))
            return self._count(outcome, Delivery(DeliveryState.FAILED, str(exc)))
        return self._count(outcome, Delivery(DeliveryState.WRITTEN, _verdict(record)))

    def _count(self, outcome: SessionOutcome, delivery: Delivery) -> Delivery:
        self._by_state.setdefault(delivery.state, []).append((outcome.session, delivery.text))
        return delivery

    def _spec(self, latest: QcRecord, session: Path) -> Spec:
        """The spec of the latest record: the file the session ran with, else the shipped
        one of its name, whichever has the recorded sha256."""
        candidates = [SPECS_DIR / f"{latest.spec_name}.toml"]
        meta = _read_json(session / "session.json")
        if isinstance(meta, dict) and isinstance(meta.get("plan"), str) and meta["plan"].endswith(".toml"):
            candidates.insert(0, Path(meta["plan"]))
        for path in candidates:
            try:
                digest = hashlib.sha256(path.read_bytes()).hexdigest()
            except OSError:
                continue
            if digest == latest.spec_sha256:  # only then parsed: another file is no business of this record
                if (path, digest) not in self._specs:
                    self._specs[path, digest] = load_spec(str(path))
                return self._specs[path, digest]
        raise NotApplicable(f"spec {latest.spec_name} {latest.spec_version} of the latest record "
                            f"(sha256 {latest.spec_sha256[:12]}…) is not at hand: neither the session's plan "
                            f"file nor {SPECS_DIR} has it")

    def summary(self) -> list[str]:
        written, present = self._by_state.get(DeliveryState.WRITTEN, []), self._by_state.get(DeliveryState.PRESENT, [])
        passed, failed = self._by_state.get(DeliveryState.PASSED, []), self._by_state.get(DeliveryState.FAILED, [])
        lines = [f"QC records in {self.name}: {len(written)} sessions re-judged{_verdicts(written)}, "
                 f"{len(present)} re-judged before{_verdicts(present)}, "
                 f"{sum(1 for _, why in passed if why == NO_RECORD)} without a QC record, "
                 f"{sum(1 for _, why in passed if why != NO_RECORD)} not re-judged, {len(failed)} failed"]
        reasons = Counter(why for _, why in passed if why != NO_RECORD)
        for why, n in reasons.most_common():
            names = [s for s, w in passed if w == why]
            shown = ", ".join(names[:SHOWN]) + (f" and {len(names) - SHOWN} more" if len(names) > SHOWN else "")
            lines.append(f"  {n} not re-judged ({shown}): {why}")
        return lines

    def close(self) -> None:
        self.records.close()


def judge_result(spec: Spec, trace: SessionTrace, result: dict[str, Any], rejudges: str, uid: str,
                 identity: dict[str, Any]) -> QcRecord:
    """The re-judgement record of one session's batch result under ``spec`` (a Dask task:
    reads the session's data for the measured characteristics, writes nothing)."""
    model = check_model(spec)
    key = result["batch"]["key"]
    notes = [f"identified by identify batch: result key {key}, model {model.name} {model.version}, "
             f"scheme {result.get('scheme')}, n {result.get('n')} (the spec's own fit: n {spec.grid_points})"]
    findings = result.get("findings")
    if isinstance(findings, list):   # worded for the verdict as a fit of qc judge's own is
        residual = isinstance(result.get("covariance"), dict) and result["covariance"].get("residual") is not None
        notes += [verdict_note(FitWarning.from_json(f), residual) for f in findings]
    else:                            # a result written before the codes: its sentences as they are
        notes += result.get("warnings", [])
    evaluation = evaluate_identified(spec, Path(trace.path), identified_from_result(model, result), notes)
    return judged_record(spec, trace, evaluation, rejudge_remedy(spec), rejudges=rejudges, uid=uid,
                         started=trace.started, finished=trace.finished, **identity)


def _check_applies(spec: Spec, model: CompiledModel, result: dict[str, Any]) -> None:
    """The spec judges with the model and estimated set the batch fitted, or not at all."""
    version = result["batch"].get("model_version")
    if (result.get("model"), version) != (model.name, model.version):
        raise NotApplicable(f"spec {spec.name} {spec.version} judges with model {model.name} {model.version}, "
                            f"the batch fitted {result.get('model')} {version}")
    wanted = {model.parameter_names[model.parameter_index(k)] for k in spec.estimate}
    fitted = {name for name, p in result["parameters"].items() if p.get("estimated")}
    if wanted != fitted:
        raise NotApplicable(f"spec {spec.name} {spec.version} estimates {', '.join(sorted(wanted))}; "
                            f"the batch {', '.join(sorted(fitted))}")


def identified_from_result(model: CompiledModel, result: dict[str, Any]) -> Identified:
    """Parameters and the covariance to propagate from a RESULT.json document: the
    residual-based one where the fit found model error, as for a fit made by qc judge,
    and the σ basis from the result's warning codes (``findings``) as that fit's."""
    cov = result.get("covariance")
    if not isinstance(cov, dict):
        raise IdentifyError("the batch result holds no covariance matrix (written by an identify before "
                            "they were stored): delete it from RESULTS_DIR and run the batch again")
    params = Parameters.from_document(model, result, source="batch result")
    matrix = cov["residual"] if cov.get("residual") is not None else cov["noise"]
    covariance = np.array([[np.nan if x is None else x for x in row] for row in matrix], dtype=float)
    estimated = tuple(cov["estimated"])
    if covariance.shape != (len(estimated), len(estimated)):
        raise IdentifyError(f"batch result: covariance of shape {covariance.shape} for {len(estimated)} parameters")
    misfit = any(isinstance(f, dict) and f.get("code") == WarningCode.MODEL_ERROR for f in result.get("findings", []))
    return Identified(params.vector(), estimated, covariance,
                      "residual" if cov.get("residual") is not None else "noise-misfit" if misfit else "noise")


def _verdict(record: QcRecord) -> str:
    return record.verdict or record.status


def _verdicts(rows: list[tuple[str, str]]) -> str:
    counts = Counter(text for _, text in rows)
    return f" ({', '.join(f'{n} {v}' for v, n in sorted(counts.items()))})" if counts else ""


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None
