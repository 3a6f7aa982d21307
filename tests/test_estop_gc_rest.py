"""The window's collector policy waits for a real rest before its full walk (issue #37): the walk is one turn of the
window's thread of 50-70 ms with every graph drawn, holding the interpreter lock, and a stop followed by a new start
within seconds is when the next e-stop press comes (the e-stop bench's presses waited behind it). On a virtual
clock: no full collection while the stops and starts follow each other; one once nothing drove for REST_S."""

from __future__ import annotations

import gc

from app.core.gc_policy import REST_S, TICK_S, HeapPolicy


def test_the_full_collection_waits_for_rest_s_without_driving() -> None:
    now = [0.0]
    drives = ["stimulation runs"]
    policy = HeapPolicy(lambda: drives[0], clock=lambda: now[0], rest_s=REST_S)
    try:
        for _ in range(10):  # e-stop, reset, start again: a moment of rest between every two drives
            policy.tick()
            now[0] += TICK_S
            drives[0] = ""
            policy.tick()
            assert policy.full_collections == 0 and policy.frozen
            now[0] += TICK_S
            drives[0] = "stimulation runs"
        policy.tick()
        drives[0] = ""
        ticks = 0
        while policy.full_collections == 0:
            now[0] += TICK_S
            ticks += 1
            policy.tick()
            assert ticks * TICK_S <= REST_S + TICK_S
        assert ticks * TICK_S >= REST_S and not policy.frozen  # given back and collected once, after the rest
        now[0] += TICK_S
        policy.tick()
        assert policy.full_collections == 1
    finally:
        gc.unfreeze()

