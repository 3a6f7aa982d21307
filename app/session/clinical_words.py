"""The record in a clinician's words (Qt-free, no I/O): what the devices, the supervisor and the runner write into
a session's record (exception names, enum names, identifiers, file paths, hashes, ``key=value`` details) turned
into the sentences the printed report shows; the original text goes to the report's technical appendix.

:func:`plain` is the one translator. It first replaces the phrases it knows (a LINarm error state, a lost link, an
emergency stop's source), then makes whatever engineering detail is left readable: an exception's class name is
dropped, ``ENUM_NAMES`` and ``snake_case`` become words, a path becomes its file name, a hash is dropped.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from app.core import streams

# Who or what raised an alarm or stopped something, as the record names them → as a clinician says it.
SOURCE_WORDS: dict[str, str] = {
    streams.LINARM: "robot",
    streams.PHYSIO: "physiological sensors",
    streams.FES: "stimulator",
    streams.PATIENT_MODEL: "patient model",
    streams.VR: "VR",
    "keyboard": "F12 key",
    "button": "STOP button",
    "script": "the running program",
    "script runner": "the running program",
    "fes profile": "the stimulation profile",
    "FES panel": "FES panel",
    "electrode set-up": "electrode set-up",
    "recording": "recording",
    "safety": "safety supervisor",
    "limits": "safety limits",
}
# An alarm's level (app.safety.supervisor.AlarmLevel names) → its name in the report.
LEVEL_WORDS: dict[str, str] = {"INFO": "Information", "WARNING": "Warning", "STOP": "Stop alarm",
                               "FATAL": "Fatal alarm"}
# The LINarm controller's error states (app.wire.linarm_protocol.ErrorState) in words.
ROBOT_ERROR_WORDS: dict[str, str] = {
    "NO_ERROR": "no error",
    "TRACKING_ERROR": "the robot could not follow its planned movement",
    "ENDSTROKE_HIT": "the robot reached the end of its travel",
    "OVER_FORCE": "the force on the handle went above the limit",
    "OVER_CURRENT": "a motor drew more current than allowed",
    "OVER_VELOCITY": "the handle moved faster than allowed",
    "WATCHDOG": "the robot stopped itself: it lost contact with the computer",
    "POSITION_LIMIT": "the handle went outside the allowed range",
    "HOMING_FAILED": "the robot could not find its reference position",
    "ENVELOPE_BREACH": "the handle left the range locked for the exercise (too fast or too far)",
}
# What the record calls an event (its kind) → the report's word for it.
EVENT_WORDS: dict[str, str] = {
    "emergency_stop": "Emergency stop",
    "script_stop": "Program stopped",
    "exercise_paused": "Paused",
    "exercise_resumed": "Resumed",
    "gap_start": "Data gap",
    "gap_end": "Data back",
    "command_refused": "Command refused",
}

# The robot's commands (the protocol table's names, camelCase as the script API spells them) in words; a command not
# named here is "a robot command". The table itself is the one place the names live.
ROBOT_COMMAND_WORDS: dict[str, str] = {
    "setAssistanceTargetPos": "a new target for the robot",
    "setAssistanceParameter": "a new assistance gain",
    "setAdmittanceParameter": "a new admittance gain",
    "setStiffness": "a new stiffness",
    "setCtrlState": "switching the robot on or off",
    "setCtrlMode": "a new robot mode",
    "moveCentreTo": "a robot movement",
    "moveDeltaTo": "a change of the springs' pretension",
    "goToHome": "homing the robot",
}


def _robot_command_names() -> tuple[str, ...]:
    from app.wire.linarm_protocol import HOST_COMMANDS

    # Only names that are not plain words (camelCase): "identify" or "heartbeat" in a sentence stays as it is.
    return tuple(sorted((c.name for c in HOST_COMMANDS if re.search(r"[a-z][A-Z]", c.name)), key=len, reverse=True))


_API_OBJECTS = ("linarm", "fes", "physiologicalSensors", "patientModel", "VRUnity", "linarmppManager")
_API_WORDS = {"linarm": "robot", "fes": "stimulator", "physiologicalSensors": "sensor", "patientModel": "patient model",
              "VRUnity": "VR", "linarmppManager": "manager"}

# (pattern, replacement): the phrases the devices write, said plainly. Applied in order, before the generic rules.
_PHRASES: tuple[tuple[re.Pattern[str], Any], ...] = (
    (re.compile(r"\blinarm: (?=LINarm error)"), lambda m: ""),
    (re.compile(r"LINarm error: ([A-Z_]+)(?: \([^)]*\))?"),
     lambda m: "robot error: " + ROBOT_ERROR_WORDS.get(m.group(1), m.group(1).replace("_", " ").lower())),
    (re.compile(r"\bno valid datagram from (\w+)"), lambda m: f"no data from the {_source(m.group(1))}"),
    (re.compile(r"\bno host bytes\b"), lambda m: "no message from the computer"),
    (re.compile(r"(^|: )(linarm|physio|fes|patient_model|vr): "), lambda m: f"{m.group(1)}{_source(m.group(2))}: "),
    (re.compile(r"\((keyboard|button)\)"), lambda m: f"({SOURCE_WORDS[m.group(1)]})"),
    (re.compile(r"\b(" + "|".join(_API_OBJECTS) + r")\.(\w+)\((?:[^()]|\([^()]*\))*\)"),
     lambda m: f"the {_API_WORDS[m.group(1)]} command"),
    (re.compile(r"\b(" + "|".join(_API_OBJECTS) + r")\.(\w+)\b"), lambda m: f"the {_API_WORDS[m.group(1)]} command"),
    (re.compile(r"\bthe (\w+(?: \w+)?) command was refused: (stimulation refused|command refused): "),
     lambda m: f"{m.group(2)}: "),
    (re.compile(r"^Emergency stop: emergency stop pressed"), lambda m: "Emergency stop pressed"),
    (re.compile(r"\b(" + "|".join(_robot_command_names()) + r")\b"),
     lambda m: ROBOT_COMMAND_WORDS.get(m.group(1), "a robot command")),
)
_EXCEPTION = re.compile(r"\b(?:[A-Z][a-z0-9]+){1,5}(?:Error|Refused|Exception|Stopped|Unavailable|Latched|Aborted|"
                        r"Timeout|Cancelled|Rejected)\b(?::\s*)?")
_ENUM = re.compile(r"\b[A-Z][A-Z0-9]*(?:_[A-Z0-9]+)+\b")
_PATH = re.compile(r"(?:[A-Za-z]:)?(?<![\w.])[\\/](?:[\w.\-+~]+[\\/])+([\w.\-+]+)")
_TEMP_NAME = re.compile(r"\btmp[a-z0-9_]{6,}\b")
_HEX = re.compile(r"\s*\b[0-9a-f]{12,}\b")
_KEY_VALUE = re.compile(r"\b[a-z_][a-z0-9_]*=")
_SNAKE = re.compile(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b(?!\.\w)")
_CAMEL = re.compile(r"\b[a-z]{2,}(?:[A-Z][a-z0-9]+)+\b")  # an argument's name (targetPos, maxVel): its words
_LITERALS = {"None": "—", "True": "yes", "False": "no"}
_LITERAL = re.compile(r"\b(None|True|False)\b")


def _source(name: str) -> str:
    return SOURCE_WORDS.get(name, name.replace("_", " "))


def source_words(name: Any) -> str:
    """Who raised or did something ("linarm", "keyboard", "Dr Rossi"), as the report says it."""
    text = str(name or "")
    return SOURCE_WORDS.get(text, plain(text))


def plain(text: Any) -> str:
    """``text`` in a clinician's words: the known phrases said plainly, the remaining engineering detail made
    readable or dropped (see the module's description). Idempotent; "" stays ""."""
    out = str(text or "")
    for pattern, replacement in _PHRASES:
        out = pattern.sub(replacement, out)
    out = _EXCEPTION.sub("", out)
    out = _ENUM.sub(lambda m: m.group(0).replace("_", " ").lower(), out)
    out = _PATH.sub(lambda m: m.group(1), out)
    out = _TEMP_NAME.sub("a temporary file", out)
    out = _HEX.sub("", out)
    out = _KEY_VALUE.sub("", out)
    out = _SNAKE.sub(lambda m: m.group(0).replace("_", " "), out)
    out = _CAMEL.sub(lambda m: re.sub(r"(?<=[a-z0-9])(?=[A-Z])", " ", m.group(0)).lower(), out)
    out = _LITERAL.sub(lambda m: _LITERALS[m.group(1)], out)
    out = re.sub(r"\s{2,}", " ", out).strip()
    out = re.sub(r"\s+([,;:.)])", r"\1", out)
    starts_a_sentence = str(text or "")[:1].isupper() or _CAMEL.match(str(text or "")) is not None
    return out[:1].upper() + out[1:] if out and out[0].islower() and starts_a_sentence else out


def is_technical(text: Any) -> bool:
    """Whether ``text`` holds detail :func:`plain` rewrites (the report keeps the original in its appendix)."""
    return plain(text) != re.sub(r"\s{2,}", " ", str(text or "")).strip()


def level_words(level: Any) -> str:
    return LEVEL_WORDS.get(str(level or "").upper(), "Alarm")


def event_words(kind: str, data: Mapping[str, Any]) -> str:
    """What happened, in the report's words: "Stop alarm", "Warning", "Emergency stop", "Program stopped"."""
    if kind == "alarm":
        return level_words(data.get("level"))
    return EVENT_WORDS.get(kind, kind.replace("_", " ").capitalize())
