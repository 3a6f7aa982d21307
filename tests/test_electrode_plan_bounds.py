"""Bounded inputs for the electrode set-up and plain data back to scripts (issue #37): a step of 1e-12 mA looped
without end on the app's call thread, a pulse width of 1e6 µs ended as "no combination gave a response", and the
set-up's combinations reached a script as strings."""

from __future__ import annotations

import itertools
import json
import math
import time
from types import SimpleNamespace
from typing import Any

import pytest

from app.therapy import electrodes
from app.therapy.electrodes import (
    MAX_BURSTS,
    BurstResult,
    Combination,
    CombinationResult,
    District,
    SetupPlan,
    SetupResult,
)
from app.wire.sciencemode import MAX_CURRENT_MA, MAX_PULSE_WIDTH_US


@pytest.mark.parametrize(("changes", "words"), [
    ({"step_ma": 1e-12}, "the stimulator takes whole mA, so the step must be at least 1 mA"),
    ({"step_ma": 0.5}, "the step must be at least 1 mA"),
    ({"pulse_width_us": 1e6}, f"outside the stimulator's range (at most {MAX_PULSE_WIDTH_US} µs)"),
    ({"ceiling_ma": 1e6}, f"above the stimulator's range (at most {MAX_CURRENT_MA} mA)"),
    ({"ceiling_ma": 120.0, "step_ma": 1.0}, f"more than the {MAX_BURSTS} allowed: raise the step or lower the ceiling"),
    ({"ceiling_ma": 10.0, "start_ma": 12.0}, "no test burst would be given"),
])
def test_a_plan_out_of_bounds_is_refused_with_a_sentence_at_once(changes: dict[str, float], words: str) -> None:
    t0 = time.monotonic()
    with pytest.raises(ValueError) as refused:
        SetupPlan(**{"ceiling_ma": 20.0, **changes})
    assert words in str(refused.value)
    assert time.monotonic() - t0 < 0.1  # refused before anything starts, not after a long loop


def test_the_bounds_come_from_the_stimulators_tables() -> None:
    assert MAX_BURSTS == math.ceil(MAX_CURRENT_MA / SetupPlan(ceiling_ma=20).step_ma)
    widest = SetupPlan(ceiling_ma=float(MAX_CURRENT_MA), start_ma=1.0, pulse_width_us=float(MAX_PULSE_WIDTH_US))
    ladder = widest.ladder(MAX_CURRENT_MA)
    assert len(ladder) <= MAX_BURSTS and ladder[-1] <= MAX_CURRENT_MA
    assert SetupPlan(ceiling_ma=40.0).ladder(40) == list(range(6, 41, 2))  # the default plan: 18 bursts


def _summary() -> dict[str, Any]:
    district = District("anterior deltoid", (Combination(1, "1-2"), Combination(3, "1-3")), "positive")
    plan = SetupPlan(ceiling_ma=12.0)
    combos = [CombinationResult(c, 12, "the therapist's ceiling") for c in district.combinations]
    combos[0].bursts.append(BurstResult("anterior deltoid", 1, "1-2", 10, 250, 0.1, 1.2, 2.0, 30))
    result = SetupResult(district, plan, combos)
    return electrodes.result_summary(result)


def test_the_setup_result_reaches_a_script_as_plain_data() -> None:
    from app.scripting.bridge import ApiBridge

    sent: list[dict[str, Any]] = []
    bridge = SimpleNamespace(_profiles={}, _profile_ids=itertools.count(1), kernel=SimpleNamespace(send=sent.append))
    bridge._result = lambda v: ApiBridge._result(bridge, v)  # type: ignore[arg-type]
    value = bridge._result(_summary())
    ApiBridge.reply(bridge, 7, value)  # type: ignore[arg-type]
    back = json.loads(json.dumps(sent[0]))["value"]  # what the kernel reads
    combos = back["combinations"]
    assert isinstance(combos, list) and all(isinstance(c, dict) for c in combos)
    assert combos[0]["channel"] == 1 and combos[0]["electrodes"] == "1-2"
    assert combos[0]["bursts"] == [[10, 1.2]] and isinstance(combos[0]["responsePerMa"], float)
    assert back["district"] == "anterior deltoid" and back["proposedChannel"] == 1
