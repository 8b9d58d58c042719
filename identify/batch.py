"""Batch identification: one fit per session folder, as tasks on a Dask cluster.

The client sends each task a session's *path*; the worker reads the session itself, so
the scheduler carries a few hundred bytes per task and never the data.  Each session's
result is written by its worker, atomically, as ``RESULTS_DIR/<folder name>.json`` (the
RESULT.json form plus a ``batch`` block) under a key: the digest of the session's data
(manifest and the CSVs the fit reads), the model's name and version, the start
parameters and priors, the estimated set and the fit settings.  A task that finds a
converged result under its key does no fit, which makes a batch resumable after a crash
or Ctrl-C, and makes a task that Dask retries after its worker died find what the
first attempt already wrote instead of writing it twice.  The digest is stored with the
files' sizes and modification times, and trusted while they are unchanged: a rerun
reads a manifest and a result per session, not the data.

Failures stay in their task: a session that cannot be read or fitted is written and
reported as ``failed: <reason>``; it is tried again on the next run (only converged
results count as done).

A result sink (identify.sinks, e.g. the QC records database of ``--db``) gets every
converged result, this run's and those an earlier run left, on the client as it arrives;
work it asks for runs on the cluster as one more task, ahead of the remaining fits.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import json
import logging
import os
import signal
import socket
import time
import traceback
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from importlib.util import find_spec
from pathlib import Path
from typing import TYPE_CHECKING, Any

import identify
from identify.dataset import Dataset, DatasetError, read_dataset, read_manifest
from identify.differentiation import Grid
from identify.errors import IdentifyError, InputError
from identify.files import atomic_write_bytes
from identify.fit import DEFAULT_POINTS, fit_experiments
from identify.model import load_model
from identify.parameters import Parameters
from identify.preparation import model_columns, resolve_outputs
from identify.sinks import BatchState, Delivery, DeliveryState, ResultSink, SessionOutcome, Task

if TYPE_CHECKING:
    from distributed import Client

SUMMARY = "summary.csv"
CONNECT_TIMEOUT_S = 10.0


class BatchError(InputError):
    """A batch that cannot start: no sessions, an unreadable list, an unreachable scheduler."""


@dataclass(frozen=True)
class FitSettings:
    """What every session of a batch is fitted with; checked on the client before any task
    is sent, so that a bad model or parameter name stops the batch, not each session."""

    model: str  # as given on the command line: built-in name or path/file.py:ClassName
    model_name: str
    model_version: str
    start: dict[str, float]
    priors: dict[str, float | None]
    estimate: tuple[str, ...]  # stable names, in the order given
    n: int | None = None  # None: as `identify fit` chooses it, per session
    scheme: str | None = None  # None: as `identify fit` chooses it, per session
    max_iterations: int = 40
    oversample: int | None = None

    @classmethod
    def resolve(cls, model: str, params: str | None, estimate: Sequence[str], *, n: int | None = None,
                scheme: str | None = None, max_iterations: int = 40, oversample: int | None = None) -> FitSettings:
        compiled = load_model(model)  # also fills the on-disk code cache the local workers load from
        start = Parameters.from_file(compiled, params) if params else Parameters(compiled)
        if not estimate:
            raise BatchError("--estimate names no parameter")
        names = tuple(dict.fromkeys(start[k].name for k in estimate))  # aliases to names, once each
        Grid(n or DEFAULT_POINTS, scheme or "bdf2", oversample=oversample or 1)
        if max_iterations < 1:
            raise BatchError(f"--max-iterations must be at least 1, got {max_iterations}")
        return cls(model, compiled.name, compiled.version, start.as_dict(), {p.name: p.prior_std for p in start},
                   names, n, scheme, max_iterations, oversample)

    def parameters(self) -> Parameters:
        params = Parameters(load_model(self.model), self.start)
        for name, prior in self.priors.items():
            params[name].prior_std = prior
        return params

    def key(self, data_hash: str) -> str:
        """The identity of one session's result: a different digest means a different fit."""
        doc = {"data": data_hash, "model": self.model_name, "model_version": self.model_version,
               "identify": identify.__version__, "start": self.start, "priors": self.priors,
               "estimate": sorted(self.estimate), "n": self.n, "scheme": self.scheme,
               "max_iterations": self.max_iterations, "oversample": self.oversample}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


# ------------------------------------------------------------------------------------------
# The task (runs on a worker)


def _data_files(ds: Dataset) -> dict[str, Path]:
    """What a fit reads, by name in the session: the manifest and the periodic
    experiments' CSVs (a session's logs, journal or drop record change nothing)."""
    return {"dataset.json": ds.path / "dataset.json"} | {e.file: ds.path / e.file for e in ds.select(kind="periodic")}


def session_stamp(ds: Dataset) -> dict[str, list[int]]:
    """Size and modification time (ns) of each file a fit reads: while they are unchanged,
    the digest stored with a result is trusted, so that resuming a batch reads a
    manifest and a result per session instead of all its data."""
    stamp = {}
    for name, path in _data_files(ds).items():
        try:
            st = path.stat()
        except FileNotFoundError:
            raise DatasetError(f"{path}: file not found") from None
        except OSError as exc:
            raise DatasetError(f"{path}: cannot be read ({exc.strerror or exc})") from None
        stamp[name] = [st.st_size, st.st_mtime_ns]
    return stamp


def session_digest(ds: Dataset) -> str:
    """SHA-256 of the files a fit reads, names included."""
    h = hashlib.sha256()
    for name, path in _data_files(ds).items():
        h.update(name.encode() + b"\0")
        try:
            with path.open("rb") as f:
                h.update(hashlib.file_digest(f, "sha256").digest())
        except OSError as exc:
            raise DatasetError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return h.hexdigest()


def fit_session(path: str, settings: FitSettings, out_dir: str, run_id: str) -> SessionOutcome:
    """Identify one session and write its result; never raises for the session's own
    faults (they become a ``failed`` outcome), so one session cannot stop the batch."""
    t0 = time.perf_counter()
    directory = Path(path)
    target = Path(out_dir) / f"{directory.name}.json"
    serial, key, stamp, data_hash = "", None, None, None
    try:
        model = load_model(settings.model)
        if model.version != settings.model_version:
            raise BatchError(f"model {model.name!r} on this worker is version {model.version}, the client's is "
                             f"{settings.model_version}: install the same project on the client and every worker")
        manifest = read_manifest(directory)
        serial = _serial(manifest)
        stamp = session_stamp(manifest)
        previous = _read_json(target)
        stored = _batch_block(previous)
        data_hash = stored.get("data_hash") if stored.get("stamp") == stamp else None
        if not isinstance(data_hash, str):
            data_hash = session_digest(manifest)
        key = settings.key(data_hash)
        if stored.get("key") == key and _stored_state(stored) is BatchState.OK:
            # Written by an earlier attempt of this very task (its worker died before it
            # could report) or by an earlier run: either way the fit is not repeated.
            return _outcome(directory, previous, BatchState.OK if stored.get("run") == run_id else BatchState.SKIPPED)
        labels = [e.label for e in manifest.select(kind="periodic")]
        outputs = resolve_outputs(model, None)
        ds = read_dataset(directory, model_columns(model, outputs), labels)
        result = fit_experiments(model, ds.select(labels), settings.parameters(), list(settings.estimate),
                                 n=settings.n, scheme=settings.scheme, outputs=outputs,
                                 max_iterations=settings.max_iterations, oversample=settings.oversample)
        doc = result.to_document()
        state, reason = (BatchState.OK, "") if result.converged else (BatchState.FAILED,
                                                                       f"not converged ({result.message})")
    except IdentifyError as exc:
        state, reason = BatchState.FAILED, str(exc)
        doc = _failure_document(settings, str(exc))
    except Exception as exc:  # a bug met by one session's data is that session's failure, with its traceback
        state, reason = BatchState.FAILED, f"internal error: {type(exc).__name__}: {exc}"
        doc = _failure_document(settings, f"{state}: {reason}") | {"traceback": traceback.format_exc()}
    status = f"{state}: {reason}" if reason else str(state)
    doc["batch"] = {"status": status, "state": state.value, "reason": reason, "key": key, "run": run_id,
                    "session": str(directory), "serial": serial,
                    "fit_s": time.perf_counter() - t0, "model_version": settings.model_version,
                    "data_hash": data_hash, "stamp": stamp}
    atomic_write_bytes(target, (json.dumps(doc, indent=2) + "\n").encode())
    return _outcome(directory, doc, state, reason)


def _stored_state(block: dict[str, Any]) -> BatchState | None:
    """The state a stored result's batch block records: its ``state`` field, or for a
    result written before there was one, its status when that was the bare word ``ok``."""
    state = block.get("state", "ok" if block.get("status") == "ok" else None)
    return BatchState(state) if state in tuple(BatchState) else None


def _serial(ds: Dataset) -> str:
    unit = ds.manifest.get("unit")
    serial = unit.get("serial") if isinstance(unit, dict) else None
    return str(serial) if serial is not None else ""


def _read_json(path: Path) -> Any:
    """A JSON file's content; None when it is absent or not JSON (then fitted again and replaced)."""
    try:
        return json.loads(path.read_bytes())
    except (OSError, ValueError):
        return None


def _batch_block(doc: Any) -> dict[str, Any]:
    """The ``batch`` block of a result written by a batch (empty for anything else)."""
    batch = doc.get("batch") if isinstance(doc, dict) else None
    return batch if isinstance(batch, dict) else {}


def _failure_document(settings: FitSettings, message: str) -> dict[str, Any]:
    """RESULT.json form of a fit that did not happen: start values, no std."""
    return {"model": settings.model_name, "converged": False, "iterations": 0, "message": message,
            "parameters": {name: {"value": value, "std": None, "estimated": name in settings.estimate}
                           for name, value in settings.start.items()},
            "correlation": {}, "channels": {}, "experiments": {}}


def _outcome(directory: Path, doc: dict[str, Any], state: BatchState, reason: str = "") -> SessionOutcome:
    # Only a fit that got as far as a covariance has estimates to show; start values are not.
    fitted = {name: p for name, p in doc["parameters"].items() if p.get("estimated") and p.get("std") is not None}
    residual = any(p.get("std_residual") is not None for p in fitted.values())
    return SessionOutcome(directory.name, str(directory), state, doc["batch"]["serial"], bool(doc["converged"]),
                          doc["batch"]["fit_s"], {k: p["value"] for k, p in fitted.items()},
                          {k: p["std_residual"] if residual else p["std"] for k, p in fitted.items()}, residual,
                          reason=reason)


# ------------------------------------------------------------------------------------------
# The client


def read_session_list(path: str | Path) -> list[Path]:
    """Session folders named in a list file: one per line, ``#`` starts a comment, a
    relative path is relative to the list file's folder (a list kept beside the data
    stays valid wherever the batch is started)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BatchError(f"{path}: session list not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise BatchError(f"{path}: cannot read the session list ({getattr(exc, 'strerror', None) or exc})") from None
    out = []
    for line in text.splitlines():
        entry = line.split("#", 1)[0].strip()
        if entry:
            out.append(path.parent / entry)
    return out


def check_sessions(sessions: Sequence[str | Path]) -> list[Path]:
    """Absolute session paths, each once.  Two different folders of the same name are
    refused: the folder name is the result's file name.  Whether a folder holds a valid
    session is each task's business (its failure is that session's alone)."""
    # abspath, not resolve: a folder reached through a symbolic link keeps the name it was given
    unique = list(dict.fromkeys(Path(os.path.abspath(s)) for s in sessions))
    if not unique:
        raise BatchError("no sessions: name session folders or give --list FILE")
    by_name: dict[str, Path] = {}
    for p in unique:
        if p.name in by_name:
            raise BatchError(f"sessions {by_name[p.name]} and {p} share the folder name {p.name!r}; "
                             f"results are named after it: rename one or run them in separate batches")
        by_name[p.name] = p
    return unique


@contextlib.contextmanager
def connect(scheduler: str | None = None, workers: int | None = None,
            timeout_s: float = CONNECT_TIMEOUT_S) -> Iterator[Client]:
    """A client of the plant's scheduler, or of a local cluster of single-threaded worker
    processes (the fits are numpy/scipy: one thread per process avoids BLAS contention,
    and Dask's nanny already sets OMP/MKL/OPENBLAS_NUM_THREADS=1 in each worker)."""
    import dask
    from distributed import Client, LocalCluster

    if scheduler is not None:
        _check_reachable(scheduler, timeout_s)
        try:
            client = Client(scheduler, timeout=timeout_s)
        except (OSError, TimeoutError) as exc:
            raise BatchError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
        with client:
            yield client
        return
    if workers is not None and workers < 1:
        raise BatchError(f"--workers must be at least 1, got {workers}")
    # A dashboard needs bokeh; without it no port is opened (and none is announced).
    dashboard = ":0" if find_spec("bokeh") else None
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in each worker (and in this process's
    # environment, which a process started later inherits), so that freed memory goes
    # back to the OS at once.  A fit allocates and frees its arrays thousands of times:
    # with that setting each allocation faults its pages in again, and a fit took 1.7x
    # the CPU (benchmarks/bench_batch.py).  glibc's own adaptive threshold keeps them.
    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ").items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    with dask.config.set({"distributed.nanny.pre-spawn-environ": environ}), \
            LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                         dashboard_address=dashboard, silence_logs=logging.ERROR, preload=[__name__]) as cluster, \
            Client(cluster) as client:
        yield client


def dask_setup(worker: object) -> None:
    """Run in each local worker process as it starts (the cluster's preload).  Ctrl-C in
    a terminal reaches the whole process group; the client handles it and closes the
    cluster, so a worker ignores it instead of dying with a traceback mid-fit."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _check_reachable(scheduler: str, timeout_s: float) -> None:
    """Refuse a malformed or unreachable address before a Client is made: a Client that
    fails to connect complains again on stderr when it is garbage-collected."""
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(scheduler)
        host, port = parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise BatchError(f"--scheduler {scheduler!r}: not a scheduler address ({exc}); "
                         f"expected tcp://HOST:PORT") from None
    if scheme not in ("tcp", "tls"):
        raise BatchError(f"--scheduler {scheduler!r}: a plant's scheduler listens on tcp:// or tls://, "
                         f"not {scheme}://")
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as exc:
        raise BatchError(f"--scheduler {scheduler}: cannot reach the scheduler ({exc.strerror or exc})") from None


def dashboard_link(client: Client) -> str | None:
    """The dashboard's address when the scheduler runs one.  Every scheduler serves HTTP
    (health, metrics); the dashboard pages need bokeh, which a local cluster has only
    when it is installed here, and the plant's scheduler is assumed to have."""
    if client.cluster is not None and not find_spec("bokeh"):
        return None
    services = client.scheduler_info().get("services", {})
    return client.dashboard_link if "dashboard" in services else None


def run_batch(client: Client, sessions: Sequence[Path], settings: FitSettings, out: Path,
              on_outcome: Callable[[SessionOutcome], None] | None = None,
              sink: ResultSink | None = None) -> list[SessionOutcome]:
    """Fit every session on the client's cluster; write RESULTS_DIR/summary.csv and return
    its rows in the order of ``sessions`` (as given by :func:`check_sessions`).  With a
    sink, each converged result (fitted now or skipped as done) is delivered to it on
    the client as it arrives (``on_outcome`` sees the fit; the row gets the delivery)."""
    from distributed import as_completed

    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    run_id = uuid.uuid4().hex
    paths = [str(p) for p in sessions]
    futures = client.map(fit_session, paths, key=[f"identify-batch-{run_id}-{i}" for i in range(len(paths))],
                         settings=settings, out_dir=str(out), run_id=run_id, pure=False)
    by_key = {f.key: p for f, p in zip(futures, sessions, strict=True)}
    sink_tasks: dict[str, tuple[SessionOutcome, Task]] = {}
    outcomes: dict[str, SessionOutcome] = {}
    arrivals = as_completed(futures)
    for future in arrivals:
        if sink is not None and future.key in sink_tasks:  # a sink's work for a result that arrived earlier
            outcome, task = sink_tasks.pop(future.key)
            try:
                value = future.result()
            except Exception as exc:  # raised by the task, or the task lost with its workers
                value = exc
            future.release()
            outcomes[outcome.session] = replace(outcome, delivery=finish(sink, outcome, task, value))
            continue
        path = by_key[future.key]
        try:
            outcome = future.result()
        except Exception as exc:  # the task itself was lost, e.g. its worker died on every allowed attempt
            outcome = SessionOutcome(path.name, str(path), BatchState.FAILED, reason=f"{type(exc).__name__}: {exc}")
        future.release()  # nothing more is wanted from it: the scheduler may forget it
        if sink is not None and outcome.state in (BatchState.OK, BatchState.SKIPPED):
            step = deliver(sink, outcome, out)
            if isinstance(step, Task):
                # Ahead of the fits still queued (priority), so that records follow the results
                # instead of all waiting for the last fit.
                key = f"identify-sink-{run_id}-{outcome.session}"
                work = client.submit(step.function, *step.args, key=key, priority=1, pure=False)
                sink_tasks[key] = (outcome, step)
                arrivals.add(work)
            else:
                outcome = replace(outcome, delivery=step)
        outcomes[outcome.session] = outcome
        if on_outcome is not None:
            on_outcome(outcome)
    rows = [outcomes[p.name] for p in sessions]
    atomic_write_bytes(out / SUMMARY, summary_csv(rows, settings.estimate))
    return rows


def deliver(sink: ResultSink, outcome: SessionOutcome, out: Path) -> Delivery | Task:
    """One converged result to the sink, read back from RESULTS_DIR (the file is the
    result; the outcome is only its summary row).  Nothing the sink meets stops the batch."""
    path = Path(out) / f"{outcome.session}.json"
    doc = _read_json(path)
    if _stored_state(_batch_block(doc)) is not BatchState.OK:
        return Delivery(DeliveryState.FAILED, f"{path}: the result cannot be read back")
    try:
        return sink.deliver(outcome, doc)
    except Exception as exc:  # a sink's bug met by one result is that session's failure, as a fit's is
        return Delivery(DeliveryState.FAILED, f"internal error in {sink.name}: {type(exc).__name__}: {exc}")


def finish(sink: ResultSink, outcome: SessionOutcome, task: Task, value: Any) -> Delivery:
    """The sink's delivery once its task is done (``value`` may be the task's exception)."""
    try:
        return sink.finish(outcome, task, value)
    except Exception as exc:
        return Delivery(DeliveryState.FAILED, f"internal error in {sink.name}: {type(exc).__name__}: {exc}")


def summary_csv(rows: Sequence[SessionOutcome], estimate: Sequence[str]) -> bytes:
    """summary.csv: session, serial, status, converged, fit_s, then <param>, <param>_std (the
    σ to quote), and std_from: ``residuals`` where the residuals exceed the measurement
    noise and the stds are the residual-based ones, ``noise`` otherwise."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["session", "serial", "status", "converged", "fit_s",
                     *[c for p in estimate for c in (p, f"{p}_std")], "std_from"])
    for r in rows:
        writer.writerow([r.session, r.serial, r.status, r.converged, _num(r.fit_s, ".3f"),
                         *[c for p in estimate for c in (_num(r.values.get(p), ".9g"), _num(r.stds.get(p), ".3g"))],
                         ("residuals" if r.residual_std else "noise") if r.stds else ""])
    return buf.getvalue().encode()


def _num(x: float | None, fmt: str) -> str:
    return "" if x is None else format(x, fmt)
