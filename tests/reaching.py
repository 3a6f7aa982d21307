"""The simulated patient of the assisted-reaching tests: reaches for the target at each prompt and back to the start
after each repetition. The push's force rises over PUSH_RISE_S on the patient's own clock (``push_to(rise_s=)``):
stepped from a thread of the test (five steps 40 ms apart), a busy machine delayed the steps and the simulator took
them together — a step of force shook the handle past the speed envelope (ENVELOPE_BREACH, #38). The pushes are
handed to the simulator in the order of the records, by one thread (a thread per push could reorder them; not seen
to: the "(2, 1)" count once blamed on it was the metrics' attribution, docs/metrics.md)."""

from __future__ import annotations

import queue
import threading
from typing import Any

PUSH_RISE_S = 0.2


class ReachingPatient:
    """Listens on ``manager``'s bus until :meth:`close`."""

    def __init__(self, manager: Any, start_m: float, target_m: float, force_n: float = 15.0) -> None:
        self._patient = manager.sim_patient()
        self._force_n = force_n
        self._targets: queue.SimpleQueue[float | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._push_in_order, name="reaching patient", daemon=True)
        self._thread.start()

        def on_record(record: Any) -> None:  # on the publishing thread: only queued here
            if record.kind == "prompt":
                self._targets.put(target_m)
            elif record.kind == "repetition_end":
                self._targets.put(start_m)

        self._listener = manager.bus.listen("reaching patient", on_record)

    def _push_in_order(self) -> None:
        while (target := self._targets.get()) is not None:
            try:
                self._patient.push_to(target, self._force_n, rise_s=PUSH_RISE_S)
            except Exception:  # the run ended and its simulators with it: a last "back to the start" has no one
                return

    def close(self) -> None:
        self._listener.close()
        self._targets.put(None)
        self._thread.join(5.0)
