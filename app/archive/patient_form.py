"""The Patients form's rules without the window: what the form's fields say, as the profile they make.

The Patients form (app/ui/patient_dialog.py) and ``linarmpp archive patient add`` (app/archive/cli.py) both hand
the texts their user typed to :func:`form_data` and :func:`profile_of`, so a patient made on the command line is
checked exactly as one made in the window: the profile's own schema (``app.therapy.patients.parse_profile``:
types, ranges, the id's characters, the date) and the configuration's limits (a patient may only narrow them).
The save is the form's too (``app.archive.station.save_profile`` with ``expected_version=None``).

Qt-free.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Any

import yaml

from app.therapy.patients import ClinicalChannelCap, ClinicalScores, PatientProfile, PatientRobotLimits, parse_profile

# The form's keys of each group, in its order (the window gives them labels).
SCORE_KEYS: tuple[str, ...] = tuple(f.name for f in fields(ClinicalScores) if f.name != "other")
ROBOT_KEYS: tuple[str, ...] = tuple(f.name for f in fields(PatientRobotLimits))
CAP_KEYS: tuple[str, ...] = tuple(f.name for f in fields(ClinicalChannelCap))


def field_value(text: str) -> Any:
    """A field's text as YAML reads it (so '0.5' is a number and 'abc' stays text for the validator); empty: None."""
    text = text.strip()
    if not text:
        return None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


@dataclass
class FormTexts:
    """What the form's fields hold, as typed."""

    patient_id: str = ""
    full_name: str = ""
    birth_date: str = ""
    record_number: str = ""
    affected_side: str = "unknown"
    k_r: str = ""
    k_f: str = ""
    fes_profile: str = ""
    scores: dict[str, str] = field(default_factory=dict)  # SCORE_KEYS -> text
    robot: dict[str, str] = field(default_factory=dict)  # ROBOT_KEYS -> text
    caps: dict[Any, dict[str, str]] = field(default_factory=dict)  # channel -> CAP_KEYS -> text
    notes: str = ""


def form_data(texts: FormTexts, original: PatientProfile | None = None) -> dict[str, Any]:
    """The profile's YAML data the form's texts make; ``original`` (the profile edited, None for a new patient)
    gives what the form does not edit: its creation time, its therapy plan, its electrode choices, its other
    scores."""
    def group(values: dict[str, str], keys: tuple[str, ...]) -> dict[str, Any]:
        out = {}
        for key in keys:
            value = field_value(values.get(key, ""))
            if value is not None:
                out[key] = str(value) if key == "assessed_on" else value
        return out

    caps: dict[Any, dict[str, Any]] = {}
    for ch, row in texts.caps.items():
        cells = {key: value for key in CAP_KEYS if (value := field_value(row.get(key, ""))) is not None}
        cells.update({key: field_value(text) for key, text in row.items() if key not in CAP_KEYS})  # refused below
        if cells:
            caps[ch] = cells
    original = original or PatientProfile()
    scores = group(texts.scores, SCORE_KEYS)
    scores.update({k: field_value(v) for k, v in texts.scores.items() if k not in SCORE_KEYS})  # refused below
    if original.scores.other:
        scores["other"] = dict(original.scores.other)
    robot = group(texts.robot, ROBOT_KEYS)
    robot.update({k: field_value(v) for k, v in texts.robot.items() if k not in ROBOT_KEYS})  # refused below
    data: dict[str, Any] = {
        "patient_id": texts.patient_id.strip(),
        # as typed (text, never a YAML date or number: "0123" stays "0123")
        "full_name": texts.full_name.strip(),
        "birth_date": texts.birth_date.strip(),
        "record_number": texts.record_number.strip(),
        "affected_side": texts.affected_side,
        "scores": scores,
        "assistance": {k: v for k, v in (("k_r", field_value(texts.k_r)), ("k_f", field_value(texts.k_f)))
                       if v is not None},
        "fes": {"profile": texts.fes_profile.strip(), "caps": caps},
        "robot": robot,
        "notes": texts.notes,
    }
    if original.created:
        data["created"] = original.created
    if original.therapy_plan:  # not edited in the form (the plan dialog's): kept as it is
        data["therapy_plan"] = [asdict(step) for step in original.therapy_plan]
    if original.fes.electrodes:  # chosen by the electrode set-up (issue #32), not edited in the form: kept as it is
        data["fes"]["electrodes"] = {name: asdict(choice) for name, choice in original.fes.electrodes.items()}
    return data


def profile_of(data: dict[str, Any], safety: Any = None, where: str = "patient form") -> PatientProfile:
    """:func:`form_data`'s data as a valid profile: the profile's schema, and with ``safety`` the configuration's
    limits. Raises app.therapy.patients.PatientError naming the key (:func:`error_key` for a whole-profile check)."""
    return parse_profile(yaml.safe_dump(data, sort_keys=False, allow_unicode=True), where, safety)


def error_key(key: str, problem: str, known: Any) -> str:
    """The field a PatientError is about: its key, or for a whole-profile check (no key) the problem's first word
    when that is one of ``known``'s keys ("birth_date '…' is not a date")."""
    if not key or key == "(top level)":
        first = problem.split(" ", 1)[0]
        return first if first in known else key
    return key


__all__ = ["CAP_KEYS", "ROBOT_KEYS", "SCORE_KEYS", "FormTexts", "error_key", "field_value", "form_data",
           "profile_of"]
