"""The simulated patient of the assisted-reaching tests: reaches for the target at each prompt and back to the start
after each repetition. The push's force rises over PUSH_RISE_S on the patient's own clock (``push_to(rise_s=)``):
stepped from a thread of the test (five steps 40 ms apart), a busy machine delayed the steps and the simulator took
them together — a step of force shook the handle past the speed envelope (ENVELOPE_BREACH, #38)."""

from __future__ import annotations

import threading
from typing import Any

PUSH_RISE_S = 0.2


def reach_at_each_prompt(manager: Any, start_m: float, target_m: float, force_n: float = 15.0) -> Any:
    """Listen on ``manager``'s bus; returns the listener (``close()`` ends it)."""
    patient = manager.sim_patient()

    def push(target: float) -> None:  # not on the publishing thread: the simulator's answer takes a turn
        threading.Thread(target=patient.push_to, args=(target, force_n), kwargs={"rise_s": PUSH_RISE_S},
                         name="reaching patient", daemon=True).start()

    def on_record(record: Any) -> None:
        if record.kind == "prompt":
            push(target_m)
        elif record.kind == "repetition_end":
            push(start_m)

    return manager.bus.listen("reaching patient", on_record)
