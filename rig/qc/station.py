"""A QC station's configuration: which database its records go to, with which password,
and the station's name in the records, from ``station.toml`` in the station's folder.

    station = "line2-A"                          # the station's name in every record
    db = "postgresql://qc@db.plant:5432/qc"      # without a password
    password = "…"                               # optional: then the file is the owner's alone

The password is never on a command line (every user reads the process list): it comes
from libpq's own places (a pgpass file, a pg_service.conf service, PGPASSWORD) or from
this file, and a file that holds one but that its group or others may read is refused,
as ssh refuses a private key that others can read.  ``--db`` on the command line
overrides ``db``; the station's name defaults to the rig's.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path

from rig.errors import BadInput
from rig.tomlfile import read_toml

CONFIG_FILE = "station.toml"
KEYS = {"station", "db", "password"}


class StationConfigError(BadInput):
    """A station.toml that cannot be used (names the file and what is wrong)."""


@dataclass(frozen=True)
class StationConfig:
    name: str | None = None           # the station's name in the records
    db: str | None = None             # the records database's URL, without a password
    password: str | None = None       # handed to the driver as a connection argument only

    def __repr__(self) -> str:        # never the password, should one print the object
        return f"StationConfig(name={self.name!r}, db={self.db!r}, password={'***' if self.password else None})"


def load_station_config(folder: Path) -> StationConfig:
    """The station folder's ``station.toml``; an empty configuration where there is none."""
    path = Path(folder) / CONFIG_FILE
    if not path.is_file():
        return StationConfig()
    _, doc = read_toml(path, StationConfigError)
    unknown = set(doc) - KEYS
    if unknown:
        raise StationConfigError(f"{path}: unknown key {', '.join(sorted(unknown))} (station, db, password)")
    for key in KEYS & set(doc):
        if not isinstance(doc[key], str) or not doc[key]:
            raise StationConfigError(f"{path}: {key} must be a non-empty string")
    if "password" in doc:
        info = path.stat()
        if info.st_uid != os.geteuid():
            raise StationConfigError(f"{path}: holds a password but belongs to another user (uid {info.st_uid}): "
                                     "the station's own user must own it, with mode 600")
        if info.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise StationConfigError(f"{path}: holds a password but its group or others may read it "
                                     f"({stat.filemode(info.st_mode)}): chmod 600 {path}")
    return StationConfig(doc.get("station"), doc.get("db"), doc.get("password"))
