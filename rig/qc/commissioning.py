"""Commissioning a QC station (``rig qc station check --out DIR``): before its first
production unit, and after any change of its database, addresses, calibration or spec.

The check connects to everything a run needs and moves nothing: the records database
(reachable, its schema version, a station's rights: INSERT and SELECT only, the tables
owned by another role), the controller (Modbus, its device identification) and the DAQ
(``*IDN?``), the DAQ calibration file and the spec.  Each item passes or fails; the list
is printed and written to ``DIR/commissioning.json`` with what was checked.  ``qc run``
on a station (a folder with a ``station.toml``) refuses to test until the last check
passed for the configuration it runs with (:func:`require_commissioned`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from identify.files import atomic_write_bytes
from rig.errors import BadInput, RigError
from rig.qc.records import (
    SCHEMA_VERSION,
    Records,
    SchemaMismatch,
    TooPrivileged,
    Unreachable,
    default_url,
    parse_url,
    safe_url,
)
from rig.qc.station import StationConfig
from rig.qc.trace import now_utc, sha256

RESULT_FILE = "commissioning.json"
SUMMARY_FILE = "commissioning.txt"


class NotCommissioned(BadInput):
    """A production run on a station whose commissioning has not passed for what it runs with."""


@dataclass(frozen=True)
class Item:
    name: str          # "database reachable", "controller" …
    passed: bool
    detail: str        # what was found, or what is wrong


@dataclass(frozen=True)
class Configuration:
    """What a commissioning is valid for: a run with anything else needs a new check."""
    station: str | None
    db: str               # the database's name, without a password
    shaker: str | None
    daq: str | None
    calibration_sha256: str | None
    spec_sha256: str | None

    def differences(self, other: Configuration) -> list[str]:
        return [k for k, v in asdict(self).items() if asdict(other)[k] != v]


@dataclass(frozen=True)
class Commissioning:
    checked: str
    configuration: Configuration
    items: tuple[Item, ...]

    @property
    def passed(self) -> bool:
        return all(i.passed for i in self.items)

    def lines(self) -> list[str]:
        return [f"{'PASS' if i.passed else 'FAIL'}  {i.name}: {i.detail}" for i in self.items] + [
            f"station {self.configuration.station or '—'}: commissioning "
            f"{'PASSED' if self.passed else 'FAILED'} ({self.checked})"]


def configuration(folder: Path, config: StationConfig, db: str | None, shaker: str | None, daq: str | None,
                  calibration: str | None, spec_sha256: str | None) -> Configuration:
    from rig.drivers.daq import DEFAULT_CALIBRATION

    url = db or config.db or default_url(folder)
    return Configuration(config.name, safe_url(parse_url(url)), shaker, daq,
                         sha256(Path(calibration) if calibration else DEFAULT_CALIBRATION), spec_sha256)


def check_station(folder: Path, config: StationConfig, db: str | None, shaker: str | None, daq: str | None,
                  calibration: str | None, spec: str) -> Commissioning:
    """Every item checked, none stopping the others."""
    items: list[Item] = []
    spec_sha = None
    try:
        from rig.qc.characteristics import check_model
        from rig.qc.spec import load_spec

        loaded = load_spec(spec)
        check_model(loaded)
        spec_sha = loaded.sha256
        items.append(Item("spec", True, f"{loaded.name} {loaded.version} (sha256 {loaded.sha256[:12]}…)"))
    except RigError as exc:
        items.append(Item("spec", False, str(exc)))
    conf = configuration(folder, config, db, shaker, daq, calibration, spec_sha)
    items += _database(folder, config, db)
    cal = None
    try:
        from rig.drivers.daq import Calibration

        cal = Calibration.from_file(calibration)
        items.append(Item("DAQ calibration", True, f"{Path(cal.source).name} (sha256 "
                                                   f"{(conf.calibration_sha256 or '')[:12]}…)"))
    except RigError as exc:
        items.append(Item("DAQ calibration", False, str(exc)))
    items += _addresses(shaker, daq, cal)
    return Commissioning(now_utc(), conf, tuple(items))


def _database(folder: Path, config: StationConfig, db: str | None) -> list[Item]:
    url = db or config.db or default_url(folder)
    try:
        records = Records.open(url, create=True, defer=True, password=config.password, writer=True)
    except Unreachable as exc:
        return [Item("database reachable", False, str(exc))]
    except TooPrivileged as exc:
        return [Item("database reachable", True, safe_url(parse_url(url))),
                Item("schema version", True, str(SCHEMA_VERSION)), Item("database rights", False, str(exc))]
    except SchemaMismatch as exc:
        return [Item("database reachable", True, safe_url(parse_url(url))), Item("schema version", False, str(exc))]
    except RigError as exc:      # a refused login, a URL that is none, a station.toml others may read …
        return [Item("database reachable", False, str(exc))]
    try:
        name = records.name
        if records.url.get_backend_name() == "sqlite":
            return [Item("database reachable", True, f"{name} (a local SQLite file of the station)"),
                    Item("schema version", True, f"{SCHEMA_VERSION}" + (" (the file is made with the first record)"
                                                                        if not Path(str(records.url.database))
                                                                        .is_file() else "")),
                    Item("database rights", True, "the station's own file (its records are hash-chained)")]
        rights = records.rights()
        return [Item("database reachable", True, name), Item("schema version", True, str(SCHEMA_VERSION)),
                Item("database rights", True, f"role {rights.role}: INSERT and SELECT, owns none of the tables")]
    finally:
        records.close()


def _addresses(shaker: str | None, daq: str | None, calibration: Any) -> list[Item]:
    from rig.config import load_rig_config
    from rig.drivers.daq import Daq
    from rig.drivers.peer_identity import Peers
    from rig.drivers.shaker import Shaker

    items = []
    controller: dict[str, str] | None = None
    if not shaker:
        items.append(Item("controller", False, "no address (station.toml's shaker or --shaker)"))
    else:
        link = None
        try:
            link = Shaker(shaker, load_rig_config(None).limits)
            link.connect(heartbeat=False)
            controller = link.identify()
            items.append(Item("controller", True, f"{shaker}: " + ", ".join(f"{k} {v}" for k, v in controller.items())))
        except (RigError, OSError) as exc:
            items.append(Item("controller", False, f"{shaker}: {exc}"))
        finally:
            if link is not None:
                link.close()
    if not daq:
        items.append(Item("DAQ", False, "no address (station.toml's daq or --daq)"))
    elif calibration is not None:
        box = Daq(daq, calibration)
        try:
            idn = box.open()
            simulated = Peers(controller or {}, idn).simulated
            items.append(Item("DAQ", True, f"{daq}: {idn}" + (" (a SIMULATOR)" if simulated else "")))
        except (RigError, OSError) as exc:
            items.append(Item("DAQ", False, f"{daq}: {exc}"))
        finally:
            box.close()
    return items


def write(folder: Path, result: Commissioning) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    doc = {"checked": result.checked, "passed": result.passed, "configuration": asdict(result.configuration),
           "items": [asdict(i) for i in result.items]}
    atomic_write_bytes(folder / SUMMARY_FILE, ("\n".join(result.lines()) + "\n").encode())
    path = folder / RESULT_FILE
    atomic_write_bytes(path, (json.dumps(doc, indent=1) + "\n").encode())
    return path


def require_commissioned(folder: Path, current: Configuration) -> None:
    """A production run's gate: the station's last check passed, for this configuration."""
    path = Path(folder) / RESULT_FILE
    hint = f"python -m rig qc station check --out {folder}"
    if not path.is_file():
        raise NotCommissioned(f"station {folder} is not commissioned: no production unit before {hint} passes")
    try:
        doc = json.loads(path.read_text())
        checked = Configuration(**doc["configuration"])
    except (ValueError, KeyError, TypeError):
        raise NotCommissioned(f"{path}: not a commissioning result; run {hint}") from None
    if not doc.get("passed"):
        failed = [i["name"] for i in doc.get("items", []) if not i.get("passed")]
        raise NotCommissioned(f"station {folder}: its commissioning of {doc.get('checked')} failed "
                              f"({', '.join(failed)}); no production unit before {hint} passes")
    changed = checked.differences(current)
    if changed:
        raise NotCommissioned(f"station {folder}: {', '.join(changed)} changed since its commissioning of "
                              f"{doc.get('checked')}; run {hint} again")
