"""The controller's stream frames (linarmState, motorState, vsaState) encoded by their precompiled encoder are the
table's frames byte for byte (``encode_message`` with the same values), and a value the table refuses is refused
with the same error (#38: the simulated LINarm encodes ~600 of them a second; the generic way cost 37-45 µs each).
"""

from __future__ import annotations

import math
import struct
from enum import IntEnum
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from app.wire import linarm_protocol as proto
from app.wire.cmdmessenger import CmdMessengerDecoder
from app.wire.linarm_protocol import (
    ControlMode,
    ControlState,
    ErrorState,
    HomeState,
    LinarmState,
    MotorState,
    TrajectoryType,
    TriggerMode,
    VsaState,
)


def table_way(name: str, state: Any) -> bytes:
    """What every stream frame was before the precompiled encoder: the table's own encoding of its values."""
    _, names = proto._STATE_FIELDS[name]
    values = [getattr(state, n) for n in names]
    return proto.encode_message(name, *[int(v) if isinstance(v, IntEnum) else v for v in values])


ENCODERS = {"linarmState": proto.encode_linarm_state, "motorState": proto.encode_motor_state,
            "vsaState": proto.encode_vsa_state}

# every float32 the wire carries, the values that need escaping (bytes , ; / NUL) and a few refused ones
floats = st.one_of(st.floats(width=32, allow_nan=False, allow_infinity=False),
                   st.sampled_from([0.0, -0.0, 1.0, struct.unpack("<f", b",;/\x00")[0], proto.FLOAT32_MAX,
                                    -proto.FLOAT32_MAX]))
t_us = st.one_of(st.integers(0, 0xFFFFFFFF), st.sampled_from([0, 0x2C2F3B00, 0xFFFFFFFF, 0x2F2F2F2F]))


@settings(max_examples=300, deadline=None)
@given(t=t_us, index=st.integers(0, 1), values=st.lists(floats, min_size=6, max_size=6))
def test_motor_and_vsa_frames_are_the_tables(t: int, index: int, values: list[float]) -> None:
    motor = MotorState(t, index, *values[:4])
    vsa = VsaState(t, *values)
    assert proto.encode_motor_state(motor) == table_way("motorState", motor)
    assert proto.encode_vsa_state(vsa) == table_way("vsaState", vsa)
    # and what the host decodes from it is what was sent (float32 as the wire carries it)
    (frame,) = CmdMessengerDecoder().feed(proto.encode_vsa_state(vsa))
    decoded = proto.decode_controller_frame(frame)
    assert decoded.t_us == t and decoded.force == struct.unpack("<f", struct.pack("<f", values[5]))[0]


@settings(max_examples=200, deadline=None)
@given(t=t_us, control=st.sampled_from(list(ControlState)), mode=st.sampled_from(list(ControlMode)),
       home=st.sampled_from(list(HomeState)), error=st.sampled_from(list(ErrorState)),
       trigger=st.sampled_from(list(TriggerMode)), trajectory=st.sampled_from(list(TrajectoryType)),
       flags=st.lists(st.booleans(), min_size=4, max_size=4))
def test_linarm_state_frames_are_the_tables(t: int, control: ControlState, mode: ControlMode, home: HomeState,
                                            error: ErrorState, trigger: TriggerMode, trajectory: TrajectoryType,
                                            flags: list[bool]) -> None:
    state = LinarmState(t, control, mode, home, error, trigger, flags[0], trajectory, flags[1], flags[2], flags[3])
    assert proto.encode_linarm_state(state) == table_way("linarmState", state)
    plain = LinarmState(t, int(control), int(mode), int(home), int(error), int(trigger), int(flags[0]),  # type: ignore[arg-type]
                        int(trajectory), int(flags[1]), int(flags[2]), int(flags[3]))  # type: ignore[arg-type]
    assert proto.encode_linarm_state(plain) == table_way("linarmState", plain)  # ints and 0/1 for the flags


REFUSED: list[tuple[str, Any]] = [
    ("vsaState", VsaState(1, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0)),
    ("vsaState", VsaState(1, 0.0, math.inf, 0.0, 0.0, 0.0, 0.0)),
    ("vsaState", VsaState(1, 0.0, 0.0, 1e39, 0.0, 0.0, 0.0)),
    ("vsaState", VsaState(1, 0.0, 0.0, 0.0, "0.1", 0.0, 0.0)),  # type: ignore[arg-type]
    ("vsaState", VsaState(1, 0.0, 0.0, 0.0, 0.0, True, 0.0)),  # type: ignore[arg-type]
    ("vsaState", VsaState(-1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
    ("vsaState", VsaState(2 ** 32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
    ("motorState", MotorState(1.5, 0, 0.0, 0.0, 0.0, 0.0)),  # type: ignore[arg-type]
    ("motorState", MotorState(1, 0, 0.0, 0.0, -math.inf, 0.0)),
    ("linarmState", LinarmState(1, 7, 0, 0, 0, 0, True, 0, False, False, False)),  # type: ignore[arg-type]
    ("linarmState", LinarmState(1, 0, 0, 0, 0, 0, 2, 0, False, False, False)),  # type: ignore[arg-type]
    ("linarmState", LinarmState(1, 0, 0, 0, 0, 0, True, 0, None, False, False)),  # type: ignore[arg-type]
    ("linarmState", LinarmState(1, True, 0, 0, 0, 0, True, 0, False, False, False)),  # type: ignore[arg-type]
]


@pytest.mark.parametrize(("name", "state"), REFUSED)
def test_a_value_the_table_refuses_is_refused_the_same_way(name: str, state: Any) -> None:
    with pytest.raises((TypeError, ValueError)) as table:
        table_way(name, state)
    with pytest.raises(type(table.value)) as fast:
        ENCODERS[name](state)
    assert str(fast.value) == str(table.value)


def test_whole_numbers_in_float_fields_are_sent_as_before() -> None:
    """An int where a float goes (a caller's 0): the table converts it; so does the encoder."""
    vsa = VsaState(5, 0, 1, 2, 3, 4, 5)  # type: ignore[arg-type]
    assert proto.encode_vsa_state(vsa) == table_way("vsaState", vsa)
