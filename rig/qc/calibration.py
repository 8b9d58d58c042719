"""Calibration certificates as station data, and the type-B calibration uncertainty of a
characteristic derived from them (GUM, JCGM 100:2008, 5.1.3: sensitivity coefficients).

A station's certificate file is a TOML file with one ``[[transducer]]`` table per DAQ
channel, in the DAQ's channel order::

    [daq]
    serial = "SIM0001"                 # the DAQ the chain was calibrated with (its *IDN? serial)

    [[transducer]]
    channel = "force_N"
    unit = "N"
    serial = "LC-SIM-0001"
    certificate = "CAL-2026-0417"
    calibrated = 2026-04-17
    due = 2027-04-17
    gain = 1.0                         # engineering = offset + gain · counts
    offset = 0.0
    k = 2
    U = [[0.0, 1.0], [20000.0, 10.0]]  # expanded uncertainty over the range (reading, U), or one number

``rig.drivers.daq.Calibration`` reads its coefficients (the DAQ's calibration comes from
it); the old ``[[channel]]`` files keep working there and carry no certificate.

The DAQ reports its own serial only (``*IDN?``: ``DAQ4,<serial>,<firmware>``,
docs/rig-interfaces.md §2), not its transducers': a chain is calibrated through the DAQ,
so the coefficients hold for the DAQ named in ``[daq]``, and a DAQ that answers with
another serial is refused.

The uncertainty model of a certificate: the error of a reading x is e₀ + e₁·x, e₀ and e₁
independent, u(e₀) the certificate's U/k at the point of its range nearest zero and
u(e₁) the least that makes √(u(e₀)² + (u(e₁)·x)²) cover U(x)/k at every other point.
A characteristic's u_cal is then √Σ (cᵢ·u(eᵢ))² over the channels' e₀, e₁, with cᵢ
the change of the characteristic per unit eᵢ, by central differences of a function that
computes the characteristic again from the channels so perturbed (:func:`uncertainty_budget`).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from identify.files import atomic_write_bytes
from rig.config import CHANNELS
from rig.drivers.daq import Calibration
from rig.errors import BadInput
from rig.tomlfile import read_toml

TRANSDUCER_KEYS = ("channel", "unit", "description", "serial", "certificate", "calibrated", "due", "gain", "offset",
                   "k", "U")


class CertificateError(BadInput):
    """A certificate file that cannot be used, or a certificate that forbids the test."""


@dataclass(frozen=True)
class Certificate:
    """One transducer's calibration certificate, as the station holds it."""

    channel: str
    unit: str
    serial: str
    certificate: str
    calibrated: _dt.date
    due: _dt.date
    gain: float
    offset: float
    k: float
    U: tuple[tuple[float, float], ...]     # (reading, expanded uncertainty) in the channel's unit
    description: str = ""

    @property
    def u_offset(self) -> float:
        """u(e₀): the standard uncertainty at the point of the range nearest zero."""
        return min(self.U, key=lambda p: abs(p[0]))[1] / self.k

    @property
    def u_gain(self) -> float:
        """u(e₁), relative: what the offset's part leaves of U(x)/k, per unit reading."""
        u0 = self.u_offset
        return max((math.sqrt(max((U / self.k) ** 2 - u0 ** 2, 0.0)) / abs(x) for x, U in self.U if x != 0),
                   default=0.0)

    def expired(self, today: _dt.date) -> bool:
        return today > self.due

    def equipment(self) -> dict[str, str]:
        """What a record and a report name of it."""
        return {"channel": self.channel, "serial": self.serial, "certificate": self.certificate,
                "calibrated": self.calibrated.isoformat(), "due": self.due.isoformat()}


@dataclass(frozen=True)
class StationCalibration:
    source: str
    daq_serial: str
    certificates: tuple[Certificate, ...]
    calibration: Calibration                # the DAQ's coefficients, read from the same file

    def certificate(self, channel: str) -> Certificate:
        return next(c for c in self.certificates if c.channel == channel)

    def refusal(self, today: _dt.date, daq_identity: str | None) -> str | None:
        """Why a test may not run on these certificates (one line), or None."""
        expired = [c for c in self.certificates if c.expired(today)]
        if expired:
            c = expired[0]
            more = f" (and {len(expired) - 1} more)" if len(expired) > 1 else ""
            return (f"calibration certificate {c.certificate} of the {c.channel} transducer {c.serial} expired on "
                    f"{c.due.isoformat()}{more} ({self.source}): recalibrate before testing")
        if daq_identity is not None:
            fields = daq_identity.split(",")
            reported = fields[1].strip() if len(fields) > 1 else ""
            if reported != self.daq_serial:
                return (f"the DAQ answers as serial {reported or '?'!r} but the certificates of {self.source} are "
                        f"for the chain through DAQ {self.daq_serial!r}: use that DAQ or this one's certificates")
        return None

    def equipment(self) -> list[dict[str, str]]:
        """The certificates used, for a record's and a report's equipment list."""
        return [c.equipment() for c in self.certificates]


def is_certificate_file(path: str | Path) -> bool:
    _, doc = read_toml(Path(path), CertificateError, "calibration ")
    return "transducer" in doc


def load_certificates(path: str | Path) -> StationCalibration:
    path = Path(path)
    _, doc = read_toml(path, CertificateError, "calibration ")
    where = f"calibration {path}"
    daq = doc.get("daq")
    if not isinstance(daq, dict) or not isinstance(daq.get("serial"), str) or not daq["serial"]:
        raise CertificateError(f"{where}: no [daq] serial (the DAQ the transducers were calibrated through)")
    tables = doc.get("transducer")
    if not isinstance(tables, list) or len(tables) != len(CHANNELS):
        raise CertificateError(f"{where}: needs {len(CHANNELS)} [[transducer]] tables ({', '.join(CHANNELS)})")
    certificates = tuple(_certificate(t, i, where) for i, t in enumerate(tables))
    return StationCalibration(str(path), daq["serial"], certificates, Calibration.from_file(path))


def _certificate(t: Any, i: int, where: str) -> Certificate:
    at = f"{where}, [[transducer]] {i + 1}"
    if not isinstance(t, dict):
        raise CertificateError(f"{at}: expected a table")
    unknown = [k for k in t if k not in TRANSDUCER_KEYS]
    if unknown:
        raise CertificateError(f"{at}: unknown key {unknown[0]!r} (known: {', '.join(TRANSDUCER_KEYS)})")
    for key in ("channel", "serial", "certificate", "calibrated", "due", "gain", "offset", "k", "U"):
        if key not in t:
            raise CertificateError(f"{at}: missing {key!r}")
    for key in ("calibrated", "due"):
        if not isinstance(t[key], _dt.date) or isinstance(t[key], _dt.datetime):
            raise CertificateError(f"{at}: {key!r} must be a TOML date (2026-04-17), not {t[key]!r}")
    if not t["due"] > t["calibrated"]:
        raise CertificateError(f"{at}: due {t['due']} is not after calibrated {t['calibrated']}")
    U = t["U"]
    points: tuple[tuple[float, float], ...]
    if isinstance(U, (int, float)) and not isinstance(U, bool):
        points = ((0.0, float(U)),)
    elif isinstance(U, list) and U and all(isinstance(p, list) and len(p) == 2 for p in U):
        points = tuple((float(x), float(u)) for x, u in U)
    else:
        raise CertificateError(f"{at}: 'U' must be a number or a table [[reading, U], …]")
    if any(not u >= 0 or not math.isfinite(u) for _, u in points):
        raise CertificateError(f"{at}: an expanded uncertainty U must be finite and not negative")
    k = float(t["k"])
    if not k > 0:
        raise CertificateError(f"{at}: k must be positive")
    return Certificate(str(t["channel"]), str(t.get("unit", "")), str(t["serial"]), str(t["certificate"]),
                       t["calibrated"], t["due"], float(t["gain"]), float(t["offset"]), k, points,
                       str(t.get("description", "")))


def equipment(calibration: str | Path | None) -> list[dict[str, str]]:
    """The certificates' data (channel, serial, certificate, calibrated, due) of the
    calibration file used, for a record's and a report's equipment list; empty for a
    file without certificates (the datasheet's)."""
    if calibration is None or not is_certificate_file(calibration):
        return []
    return load_certificates(calibration).equipment()


# ----- the type-B uncertainty from the certificates -------------------------------------------------
Perturb = Callable[[str, np.ndarray], np.ndarray]     # (channel, its values) → the values perturbed
Recompute = Callable[[Perturb | None], Mapping[str, float]]   # the characteristics (None: unperturbed)


@dataclass(frozen=True)
class Contribution:
    channel: str
    component: str           # "offset" (e₀, in the channel's unit) or "gain" (e₁, relative)
    u: float                 # u(eᵢ)
    sensitivity: float       # cᵢ: the characteristic's change per unit eᵢ

    @property
    def u_characteristic(self) -> float:
        return abs(self.sensitivity) * self.u


@dataclass(frozen=True)
class Budget:
    name: str
    value: float
    contributions: tuple[Contribution, ...]

    @property
    def u_cal(self) -> float:
        return math.sqrt(sum(c.u_characteristic ** 2 for c in self.contributions))


def perturbation(channel: str, component: str, h: float) -> Perturb:
    """x → x + h (offset) or x·(1 + h) (gain) on ``channel``, the others untouched."""
    def apply(name: str, x: np.ndarray) -> np.ndarray:
        if name != channel:
            return x
        return x + h if component == "offset" else x * (1.0 + h)
    return apply


def uncertainty_budget(recompute: Recompute, certificates: StationCalibration,
                       channels: tuple[str, ...] = CHANNELS) -> dict[str, Budget]:
    """Each characteristic's calibration uncertainty budget: per channel and component the
    sensitivity coefficient by a central difference of ``recompute`` over ±u(eᵢ) (a step
    of the size of the uncertainty itself stays in the linear range the GUM's first-order
    propagation assumes), times u(eᵢ).  ``recompute`` may be any definition of the
    characteristics from the channels: the QC's identification, a measurand's formula."""
    base = dict(recompute(None))
    rows: dict[str, list[Contribution]] = {name: [] for name in base}
    for channel in channels:
        cert = certificates.certificate(channel)
        for component, u in (("offset", cert.u_offset), ("gain", cert.u_gain)):
            if u == 0:
                continue
            up, down = recompute(perturbation(channel, component, u)), recompute(perturbation(channel, component, -u))
            for name in base:
                rows[name].append(Contribution(channel, component, u, (up[name] - down[name]) / (2 * u)))
    return {name: Budget(name, value, tuple(rows[name])) for name, value in base.items()}


# ----- today's characteristics: the identification done again on the perturbed channels -----------
def identification_recompute(spec: Any, session: Path) -> Recompute:
    """The spec's characteristics of the unit measured in ``session`` computed again, the
    identification included, from its channels perturbed (what a calibration error of
    a channel does to them).  Each call is one fit (about a second and a half)."""
    from dataclasses import replace

    from identify.fit import fit_experiments
    from identify.parameters import Parameters
    from rig.qc.characteristics import Identified, check_model, measure
    from rig.qc.evaluate import periodic_experiments

    model = check_model(spec)
    experiments = periodic_experiments(model, session)
    start = Parameters.from_file(model, spec.start) if spec.start else Parameters(model)

    def recompute(perturb: Perturb | None) -> dict[str, float]:
        runs = experiments
        if perturb is not None:
            runs = []
            for e in experiments:
                assert e.data is not None
                data = e.data.copy()
                for name in CHANNELS:
                    if name in data:
                        data[name] = perturb(name, data[name].to_numpy())
                runs.append(replace(e, data=data))
        fit = fit_experiments(model, runs, start.copy(), list(spec.estimate), n=spec.grid_points)
        measured = measure(spec, model, Identified.from_fit(fit), runs)
        missing = [m.name for m in measured if m.value is None]
        if missing:
            raise CertificateError(f"{session}: {', '.join(missing)} not computed from the perturbed channels "
                                   "(the identification did not converge)")
        return {m.name: float(m.value) for m in measured if m.value is not None}

    return recompute


# ----- derived once per certificate set, used by every run ------------------------------------------
UNCERTAINTY_DIR = "qc-uncertainty"


def _budget_file(folder: Path, spec_sha256: str, calibration: str | Path) -> Path:
    digest = hashlib.sha256(Path(calibration).read_bytes()).hexdigest()
    return Path(folder) / UNCERTAINTY_DIR / f"{spec_sha256[:12]}-{digest[:12]}.json"


def store_budget(folder: Path, spec: Any, calibration: str | Path, session: Path,
                 budget: dict[str, Budget]) -> Path:
    """The derived u_cal of each characteristic for this spec and this certificate file
    (a new certificate file, a new spec: derived again), the station's to use."""
    path = _budget_file(folder, spec.sha256, calibration)
    doc = {"spec": spec.name, "spec_sha256": spec.sha256, "calibration": str(calibration), "session": str(session),
           "u_cal": {name: b.u_cal for name, b in budget.items()},
           "contributions": {name: [asdict(c) for c in b.contributions] for name, b in budget.items()}}
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, (json.dumps(doc, indent=2) + "\n").encode())
    return path


def derived_u_cal(folder: Path, spec: Any, calibration: str | Path | None) -> tuple[dict[str, float], str] | None:
    """The u_cal derived from these certificates for this spec, and the session it was
    derived on; None where it has not been (``qc uncertainty``)."""
    if calibration is None or not is_certificate_file(calibration):
        return None
    path = _budget_file(folder, spec.sha256, calibration)
    if not path.is_file():
        return None
    doc = json.loads(path.read_text())
    return {k: float(v) for k, v in doc["u_cal"].items()}, str(doc["session"])
