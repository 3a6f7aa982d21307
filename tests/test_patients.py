"""Patient profiles: validated YAML, one file per patient, limits that may only narrow the config."""

from __future__ import annotations

from dataclasses import replace

import pytest

from app.core.config import AppConfig, FesChannelCaps, FesSafety, SafetyConfig
from app.therapy.patients import (
    ClinicalChannelCap,
    ClinicalScores,
    PatientAssistance,
    PatientError,
    PatientFes,
    PatientProfile,
    PatientRobotLimits,
    clinical_caps,
    effective_robot_limits,
    list_patients,
    load_patient,
    parse_profile,
    patient_file,
    save_patient,
)

SAFETY = AppConfig().safety


def full_profile() -> PatientProfile:
    return PatientProfile(
        patient_id="PZ-017", affected_side="left",
        scores=ClinicalScores(fugl_meyer_ue=31, modified_ashworth=1.5, other={"NIHSS": 4.0}),
        assistance=PatientAssistance(k_r=0.7, k_f=0.3),
        fes=PatientFes(profile="reach_biceps_triceps.yaml",
                       caps={1: ClinicalChannelCap(25.0, 250.0, 6.0), 3: ClinicalChannelCap(20.0, 200.0)}),
        robot=PatientRobotLimits(position_min_m=0.05, position_max_m=0.40, max_velocity_m_s=0.2),
        notes="Shoulder pain above 0.4 m.\nPrefers mornings.")


def test_save_and_load_round_trip(tmp_path) -> None:
    profile = full_profile()
    path = save_patient(profile, tmp_path, SAFETY)
    assert path == tmp_path / "PZ-017.yaml"
    loaded = load_patient("PZ-017", SAFETY, tmp_path)
    assert loaded.created and loaded.updated
    assert replace(loaded, created="", updated="") == profile
    assert [e.patient_id for e in list_patients(tmp_path)] == ["PZ-017"]


def test_unknown_key_names_file_line_and_key(tmp_path) -> None:
    text = "patient_id: P1\nassistance:\n  k_r: 0.5\n  kr: 0.2\n"
    with pytest.raises(PatientError) as err:
        parse_profile(text, "P1.yaml")
    assert (err.value.line, err.value.key) == (4, "assistance.kr")
    assert "P1.yaml:4" in str(err.value)


def test_out_of_range_gain_is_refused() -> None:
    with pytest.raises(PatientError, match=r"assistance\.k_f.*outside the allowed range"):
        parse_profile("patient_id: P1\nassistance: {k_f: 1.5}\n", "P1.yaml")


@pytest.mark.parametrize(("yaml_text", "key", "line"), [
    ("patient_id: P1\nrobot:\n  max_velocity_m_s: 0.5\n", "robot.max_velocity_m_s", 3),
    ("patient_id: P1\nrobot:\n  position_max_m: 0.49\n", "robot.position_max_m", 3),
    ("patient_id: P1\nrobot:\n  position_min_m: 0.01\n", "robot.position_min_m", 3),
    ("patient_id: P1\nfes:\n  caps:\n    2:\n      max_current_ma: 45\n", "fes.caps.2.max_current_ma", 5),
])
def test_limits_may_only_narrow_the_config(yaml_text: str, key: str, line: int) -> None:
    parse_profile(yaml_text, "P1.yaml")  # fine on its own
    with pytest.raises(PatientError) as err:
        parse_profile(yaml_text, "P1.yaml", SAFETY)
    assert err.value.key == key and err.value.line == line


def test_site_channel_cap_is_respected() -> None:
    safety = SafetyConfig(fes=FesSafety(channels={2: FesChannelCaps(max_current_ma=20.0)}))
    with pytest.raises(PatientError, match=r"configured cap 20\.0 mA"):
        parse_profile("patient_id: P1\nfes: {caps: {2: {max_current_ma: 25}}}\n", "P1.yaml", safety)


@pytest.mark.parametrize("bad", ["", "../etc", "a b", "x/y", "-lead"])
def test_identifier_must_be_a_safe_pseudonym(bad: str) -> None:
    with pytest.raises(PatientError, match="patient_id"):
        parse_profile(f"patient_id: '{bad}'\n", "x.yaml")


def test_file_name_must_match_identifier(tmp_path) -> None:
    (tmp_path / "P2.yaml").write_text("patient_id: P3\n", encoding="utf-8")
    with pytest.raises(PatientError, match="does not match the file name"):
        load_patient("P2", folder=tmp_path)


def test_broken_files_are_listed_with_their_error(tmp_path) -> None:
    save_patient(PatientProfile(patient_id="good"), tmp_path)
    (tmp_path / "bad.yaml").write_text("patient_id: bad\nscores: {fugl_meyer_ue: 80}\n", encoding="utf-8")
    entries = {e.patient_id: e for e in list_patients(tmp_path)}
    assert entries["good"].profile is not None and entries["good"].error == ""
    assert entries["bad"].profile is None and "scores.fugl_meyer_ue" in entries["bad"].error


def test_effective_limits_and_caps() -> None:
    profile = full_profile()
    robot = effective_robot_limits(profile, SAFETY.robot)
    assert (robot.position_min_m, robot.position_max_m, robot.max_velocity_m_s) == (0.05, 0.40, 0.2)
    assert robot.max_interaction_force_n == SAFETY.robot.max_interaction_force_n
    caps = clinical_caps(profile)
    assert caps[1].max_current_ma == 25.0 and caps[1].max_rms_current_ma == 6.0 and caps[3].max_rms_current_ma is None


def test_patient_file_refuses_paths() -> None:
    with pytest.raises(ValueError):
        patient_file("../outside")
