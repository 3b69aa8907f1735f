"""session.toml: the rig configuration a session was recorded with, who and what, and its takes.

    [session]                 subject, operator, object, paint, created (UTC, ISO 8601), rig
    [[takes]]                 name, kind, status, reason, started, duration_s, frames, lost_cameras
    [rig] [[cameras]] ...     the rig.toml tables as recorded (load_rig reads the file as it is)

A session is one rig configuration: every take of it shares the calibration and the clocks, so a
take recorded with a different configuration goes into a new session (SessionError says which
key differs). The file is rewritten atomically after every change.
"""

from __future__ import annotations

import datetime
import getpass
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from manus_core.errors import ConfigError, SessionError
from manus_core.fileio import write_atomic
from manus_core.rig_config import RigConfig, rig_from_dict, rig_to_dict

SESSION_FILE = "session.toml"
TAKE_KINDS = ("calibration", "hand", "object", "grasp", "canonical")
RIG_TABLES = ("rig", "cameras", "leds", "storage", "sim")
TAKE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


def utc_now() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def check_take_name(name: str) -> str:
    if not TAKE_NAME.fullmatch(name):
        raise SessionError(f"take name {name!r}: use letters, digits, '.', '_' and '-' (no '/')")
    return name


def check_kind(kind: str) -> str:
    if kind not in TAKE_KINDS:
        raise SessionError(f"take kind {kind!r} is not one of {', '.join(TAKE_KINDS)}")
    return kind


@dataclass
class Session:
    """A session folder and its session.toml."""

    path: Path
    rig: RigConfig
    subject: str = ""
    operator: str = ""
    object: str = ""
    paint: bool = False
    created: str = field(default_factory=utc_now)
    takes: list[dict[str, Any]] = field(default_factory=list)

    @property
    def file(self) -> Path:
        return self.path / SESSION_FILE

    def take(self, name: str) -> dict[str, Any] | None:
        return next((t for t in self.takes if t.get("name") == name), None)

    def update_take(self, name: str, **fields: Any) -> dict[str, Any]:
        """Add or update the [[takes]] entry of `name` and save the file."""
        entry = self.take(name)
        if entry is None:
            entry = {"name": name}
            self.takes.append(entry)
        entry.update({k: v for k, v in fields.items() if v is not None})
        self.save()
        return entry

    def to_toml(self) -> str:
        head = {"subject": self.subject, "operator": self.operator, "object": self.object,
                "paint": self.paint, "created": self.created, "rig": self.rig.name}
        takes = [{k: v for k, v in take.items() if v is not None} for take in self.takes]
        doc = {"session": head, **({"takes": takes} if takes else {}), **rig_to_dict(self.rig)}
        return "# manus-capture session (docs/recording.md)\n" + tomli_w.dumps(doc)

    def save(self) -> None:
        write_atomic(self.file, self.to_toml().encode())


def load_session(path: str | Path) -> Session | None:
    """The session in folder `path`, or None when it has no session.toml yet."""
    folder = Path(path)
    file = folder / SESSION_FILE
    if not file.is_file():
        return None
    try:
        doc = tomllib.loads(file.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SessionError(f"{file}: not valid TOML ({exc})") from None
    head = doc.get("session")
    if not isinstance(head, dict):
        raise SessionError(f"{file}: session: missing (not a session.toml)")
    try:
        rig = rig_from_dict({k: doc[k] for k in RIG_TABLES if k in doc}, str(file))
    except ConfigError as exc:
        raise SessionError(str(exc)) from None
    takes = doc.get("takes", [])
    if not isinstance(takes, list) or not all(isinstance(t, dict) and "name" in t for t in takes):
        raise SessionError(f"{file}: takes: expected [[takes]] tables with a name")
    return Session(folder, rig, subject=str(head.get("subject", "")), operator=str(head.get("operator", "")),
                   object=str(head.get("object", "")), paint=bool(head.get("paint", False)),
                   created=str(head.get("created", "")), takes=[dict(t) for t in takes])


def _first_difference(mine: Any, theirs: Any, key: str = "") -> str | None:
    """The first key where two rig_to_dict trees differ, as 'KEY = VALUE (session) vs KEY = VALUE'."""
    if isinstance(mine, dict) and isinstance(theirs, dict):
        names = list(mine) + [k for k in theirs if k not in mine]
        found = (_first_difference(mine.get(k), theirs.get(k), f"{key}.{k}".lstrip(".")) for k in names)
        return next((d for d in found if d), None)
    if isinstance(mine, list) and isinstance(theirs, list):
        if len(mine) != len(theirs):
            return f"{len(mine)} {key} (session) vs {len(theirs)}"
        found = (_first_difference(a, b, f"{key}[{i}]") for i, (a, b) in enumerate(zip(mine, theirs)))
        return next((d for d in found if d), None)
    return None if mine == theirs else f"{key} = {mine!r} (session) vs {key} = {theirs!r}"


def open_session(path: str | Path, rig: RigConfig, *, subject: str | None = None,
                 operator: str | None = None, obj: str | None = None, paint: bool | None = None) -> Session:
    """The session in `path`, created with `rig` if new; its rig, subject and object must match."""
    folder = Path(path)
    session = load_session(folder)
    if session is None:
        default_subject = rig.sim.subject if rig.sim is not None else ""
        try:
            default_operator = getpass.getuser()
        except (KeyError, OSError):
            default_operator = ""
        session = Session(folder, rig, subject=subject or default_subject, operator=operator or default_operator,
                          object=obj or "", paint=bool(paint))
        folder.mkdir(parents=True, exist_ok=True)
        session.save()
        return session
    difference = _first_difference(rig_to_dict(session.rig), rig_to_dict(rig))
    if difference:
        raise SessionError(f"{session.file}: recorded with another rig configuration "
                           f"({difference}); record into a new session")
    for what, given, stored in (("subject", subject, session.subject), ("operator", operator, session.operator),
                                ("object", obj, session.object)):
        if given and stored and given != stored:
            raise SessionError(f"{session.file}: session.{what} is {stored!r}, not {given!r}; "
                               "record into a new session")
    changed = False
    if obj and not session.object:
        session.object, changed = obj, True
    if paint and not session.paint:
        session.paint, changed = True, True
    if operator and not session.operator:
        session.operator, changed = operator, True
    if changed:
        session.save()
    return session
