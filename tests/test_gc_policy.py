"""app/core/gc_policy.py (issue #37): while something drives, survivors are settled out of the collector's walk; at
rest, after driving, they are given back and cyclic garbage made meanwhile is freed."""

from __future__ import annotations

import gc
import weakref

from app.core.gc_policy import HeapPolicy


class _Node:
    def __init__(self) -> None:
        self.me = self  # a cycle: only the collector frees it


def test_survivors_settled_while_driving_and_collected_at_rest() -> None:
    drives = ["the robot is ON"]
    policy = HeapPolicy(lambda: drives[0])
    try:
        node = _Node()
        gone = weakref.ref(node)
        policy.tick()  # driving: the node is settled
        assert policy.frozen and gc.get_freeze_count() > 0
        del node
        gc.collect()
        assert gone() is not None  # out of the collector's sight while the therapy runs
        drives[0] = ""
        policy.tick()  # at rest: given back, collected once
        assert not policy.frozen and gc.get_freeze_count() == 0 and policy.full_collections == 1
        assert gone() is None
        policy.tick()  # at rest again: nothing more to do
        assert policy.full_collections == 1
    finally:
        gc.unfreeze()


def test_settle_alone_is_not_given_back_at_rest() -> None:
    policy = HeapPolicy(lambda: "")
    try:
        policy.settle()  # the window just built: lives as long as the app
        policy.tick()
        assert policy.frozen and policy.full_collections == 0
    finally:
        gc.unfreeze()
