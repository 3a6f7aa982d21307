"""Issue #17, point 7: the smaller host-safety points (each reproduced first)."""

from __future__ import annotations

import pytest

from app.devices.sciencemode import ChannelListConfig, ScienceModeRangeError, validate_channel_list


def test_sm2_accepts_a_third_party_default_t2_of_2_ms_with_two_channels() -> None:
    # pysciencemode's RehaStim2 default: t2 = 2 ms; SM2 (S4 §4.3) bounds t2 to 1.5..129 ms and t1 >= npg*t2,
    # with no 1.5 ms-per-channel rule (that one is ScienceMode 1's, S1 §4).
    config = ChannelListConfig((1, 2), 25.0, 2.0)
    validate_channel_list(config, "sm2")
    with pytest.raises(ScienceModeRangeError):
        validate_channel_list(config, "sm1")  # SM1 keeps its documented rule (and its 3 ms minimum)
