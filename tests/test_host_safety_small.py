"""Issue #17, point 7: the smaller host-safety points (each reproduced first)."""

from __future__ import annotations

import pytest

from app.wire.sciencemode import ChannelListConfig, ScienceModeRangeError, validate_channel_list


def test_sm2_accepts_a_third_party_default_t2_of_2_ms_with_two_channels() -> None:
    # pysciencemode's RehaStim2 default: t2 = 2 ms; SM2 (S4 §4.3) bounds t2 to 1.5..129 ms and t1 >= npg*t2,
    # with no 1.5 ms-per-channel rule (that one is ScienceMode 1's, S1 §4).
    config = ChannelListConfig((1, 2), 25.0, 2.0)
    validate_channel_list(config, "sm2")
    with pytest.raises(ScienceModeRangeError):
        validate_channel_list(config, "sm1")  # SM1 keeps its documented rule (and its 3 ms minimum)


def test_losing_alpha_returns_fes_and_robot_assistance_to_their_non_alpha_values() -> None:
    from tests.test_assistance import controller

    ctl, rec, _clock = controller()
    ctl.set_gains(1.0, 1.0)
    ctl.update_alpha(1.0)
    assert rec.fes[-1] == 300.0 and rec.robot[-1][2] == 150.0  # α drives both
    ctl.invalidate()  # the patient model is lost
    assert rec.fes[-1] is None  # the FES profile's own pulse width again
    neutral = ctl.preview(0.0)
    assert rec.robot[-1] == (neutral.k_m, neutral.k_a, neutral.k_t) and neutral.k_t == 0.0  # no assistive pull
    n = (len(rec.fes), len(rec.robot))
    ctl.invalidate()  # nothing more to undo
    assert (len(rec.fes), len(rec.robot)) == n


def test_the_estop_reset_event_names_whoever_resets() -> None:
    from app.core.config import SafetyConfig
    from app.safety.supervisor import SafetySupervisor

    events: list[tuple[str, dict]] = []
    sup = SafetySupervisor(SafetyConfig())
    sup.bus.listen("test", lambda r: events.append((r.kind, r.data)))
    sup.emergency_stop("test")
    sup.reset_emergency_stop("Dr Rossi")
    assert ("emergency_stop_reset", {"operator": "Dr Rossi"}) in events
