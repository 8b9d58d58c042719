"""A QC station's configuration: which database its records go to, with which password,
the station's name in the records, its rig's addresses, how it knows its operators and
when its queue is too long, from ``station.toml`` in the station's folder.

    station = "line2-A"                          # the station's name in every record
    db = "postgresql://qc_line2a@db.plant:5432/qc"   # without a password
    password = "…"                               # optional: then the file is the owner's alone
    shaker = "tcp://10.0.0.7:502"                # optional: qc run's --shaker, --daq, --calibration
    daq = "socket://10.0.0.8:5025"
    calibration = "/etc/rig/daq-calibration.toml"
    identify = "login"                           # or "pin": how the station identifies its operator
    queue_max_age_h = 24                         # a record queued longer than this warns on every run
    queue_max_records = 20                       # and so do more records queued than this

    [[operator]]                                 # the qualified operators (none listed: any login)
    name = "A. Jones"
    login = "ajones"
    pin = "scrypt$…"                             # python -m rig qc station pin: the PIN's hash, never the PIN

The password is never on a command line (every user reads the process list): it comes
from libpq's own places (a pgpass file, a pg_service.conf service, PGPASSWORD) or from
this file, and a file that holds one but that its group or others may read is refused,
as ssh refuses a private key that others can read.  ``--db`` on the command line
overrides ``db``; the station's name defaults to the rig's.
"""

from __future__ import annotations

import getpass
import hashlib
import hmac
import os
import secrets
import stat
import sys
from dataclasses import dataclass, field
from pathlib import Path

from rig.errors import BadInput
from rig.tomlfile import read_toml

CONFIG_FILE = "station.toml"
TEXT_KEYS = {"station", "db", "password", "shaker", "daq", "calibration", "identify"}
KEYS = TEXT_KEYS | {"queue_max_age_h", "queue_max_records", "operator"}
OPERATOR_KEYS = {"name", "login", "pin"}
IDENTIFY = ("login", "pin")
QUEUE_MAX_AGE_H = 24.0
QUEUE_MAX_RECORDS = 20
SCRYPT = {"n": 2 ** 14, "r": 8, "p": 1}     # a PIN has few digits: a slow, salted hash (RFC 7914)


class StationConfigError(BadInput):
    """A station.toml that cannot be used (names the file and what is wrong)."""


@dataclass(frozen=True)
class Operator:
    """A qualified operator of the station."""
    name: str
    login: str | None = None
    pin: str | None = None            # "scrypt$SALT$HASH" (hex): :func:`pin_hash`


@dataclass(frozen=True)
class Identified:
    """Who runs the station now, and how the station knows it."""
    operator: str
    by: str                           # login, pin, or typed (a bench folder without station.toml)


@dataclass(frozen=True)
class StationConfig:
    name: str | None = None           # the station's name in the records
    db: str | None = None             # the records database's URL, without a password
    password: str | None = None       # handed to the driver as a connection argument only
    shaker: str | None = None
    daq: str | None = None
    calibration: str | None = None
    identify: str = "login"
    queue_max_age_h: float = QUEUE_MAX_AGE_H
    queue_max_records: int = QUEUE_MAX_RECORDS
    operators: tuple[Operator, ...] = field(default=())
    path: Path | None = None          # the file read (None: the folder has none: a bench, not a station)

    def __repr__(self) -> str:        # never the password, should one print the object
        return f"StationConfig(name={self.name!r}, db={self.db!r}, password={'***' if self.password else None})"

    @property
    def is_station(self) -> bool:
        """A configured station (it has a station.toml): commissioned before production runs."""
        return self.path is not None


def load_station_config(folder: Path) -> StationConfig:
    """The station folder's ``station.toml``; an empty configuration where there is none."""
    path = Path(folder) / CONFIG_FILE
    if not path.is_file():
        return StationConfig()
    _, doc = read_toml(path, StationConfigError)
    unknown = set(doc) - KEYS
    if unknown:
        raise StationConfigError(f"{path}: unknown key {', '.join(sorted(unknown))} ({', '.join(sorted(KEYS))})")
    for key in TEXT_KEYS & set(doc):
        if not isinstance(doc[key], str) or not doc[key]:
            raise StationConfigError(f"{path}: {key} must be a non-empty string")
    if doc.get("identify", "login") not in IDENTIFY:
        raise StationConfigError(f"{path}: identify = {doc['identify']!r}: login or pin")
    age, count = doc.get("queue_max_age_h", QUEUE_MAX_AGE_H), doc.get("queue_max_records", QUEUE_MAX_RECORDS)
    if isinstance(age, bool) or not isinstance(age, (int, float)) or age <= 0:
        raise StationConfigError(f"{path}: queue_max_age_h must be a positive number of hours")
    if isinstance(count, bool) or not isinstance(count, int) or count < 0:
        raise StationConfigError(f"{path}: queue_max_records must be a whole number ≥ 0")
    operators = []
    entries = doc.get("operator", [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise StationConfigError(f"{path}: operator must be [[operator]] tables (name, login, pin)")
    for i, e in enumerate(entries, 1):
        bad = set(e) - OPERATOR_KEYS
        if bad or not isinstance(e.get("name"), str) or not e["name"]:
            raise StationConfigError(f"{path}: operator {i}: a name, and only name, login, pin"
                                     + (f" (unknown {', '.join(sorted(bad))})" if bad else ""))
        if "pin" in e and not str(e["pin"]).startswith("scrypt$"):
            raise StationConfigError(f"{path}: operator {i} ({e['name']}): pin must be the PIN's hash "
                                     "(python -m rig qc station pin), never the PIN itself")
        operators.append(Operator(e["name"], e.get("login"), e.get("pin")))
    if doc.get("identify") == "pin" and not any(o.pin for o in operators):
        raise StationConfigError(f"{path}: identify = \"pin\" but no [[operator]] has a pin")
    if "password" in doc:
        info = path.stat()
        if info.st_uid != os.geteuid():
            raise StationConfigError(f"{path}: holds a password but belongs to another user (uid {info.st_uid}): "
                                     "the station's own user must own it, with mode 600")
        if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise StationConfigError(f"{path}: holds a password but its group or others may read it "
                                     f"({stat.filemode(info.st_mode)}): chmod 600 {path}")
    return StationConfig(doc.get("station"), doc.get("db"), doc.get("password"), doc.get("shaker"), doc.get("daq"),
                         doc.get("calibration"), doc.get("identify", "login"), float(age), count, tuple(operators),
                         path)


def pin_hash(pin: str) -> str:
    salt = secrets.token_bytes(16)
    digest = hashlib.scrypt(pin.encode(), salt=salt, dklen=32, **SCRYPT)
    return f"scrypt${salt.hex()}${digest.hex()}"


def pin_matches(pin: str, stored: str) -> bool:
    try:
        _, salt, digest = stored.split("$")
        mine = hashlib.scrypt(pin.encode(), salt=bytes.fromhex(salt), dklen=32, **SCRYPT)
        return hmac.compare_digest(mine.hex(), digest)
    except ValueError:
        return False


def read_pin(prompt: str = "operator PIN: ") -> str:
    """The PIN from the terminal without echo, or a line of stdin where there is no terminal."""
    if sys.stdin.isatty():
        return getpass.getpass(prompt)
    return sys.stdin.readline().strip()


def identify_operator(config: StationConfig, typed: str | None = None, pin: str | None = None) -> Identified:
    """Who runs the station: its OS login (a qualified one, where station.toml lists
    operators) or the operator whose PIN matches; on a bench folder without station.toml,
    the name typed (``--operator``) or the login.  A station refuses a typed name."""
    if not config.is_station:
        return Identified(typed, "typed") if typed else Identified(getpass.getuser(), "login")
    if typed:
        raise StationConfigError(f"--operator {typed}: the station identifies its operator ({config.path}: "
                                 f"identify = {config.identify!r}); a name is typed on a bench folder only")
    if config.identify == "pin":
        entered = pin if pin is not None else read_pin()
        for o in config.operators:
            if o.pin and pin_matches(entered, o.pin):
                return Identified(o.name, "pin")
        raise StationConfigError(f"{config.path}: the PIN entered is no qualified operator's")
    login = getpass.getuser()
    if not config.operators:
        return Identified(login, "login")
    for o in config.operators:
        if o.login == login:
            return Identified(o.name, "login")
    raise StationConfigError(f"{config.path}: login {login!r} is not a qualified operator of this station "
                             "(its [[operator]] list)")
