"""The collector runs on the main thread only (issue #38; app/core/gc_policy.py, app/main_thread_gc.py): cyclic
garbage -- a Qt object caught in a cycle included -- is freed on the main thread, never on the thread that happened
to allocate (the suite crashed with a segmentation fault "Garbage-collecting" on the Patients window's loading
thread; a shown plot widget collected on another thread hung it in QWindow::close)."""

from __future__ import annotations

import gc
import re
import threading
from pathlib import Path
from typing import Any

from PySide6.QtCore import QObject, Qt

from app.core.gc_policy import MainThreadCollections
from app.main_thread_gc import collections

ROOT = Path(__file__).resolve().parent.parent


class _Cycle:
    """Cyclic garbage holding a Qt object; says on which thread the collector freed it."""

    def __init__(self, freed_on: list[str]) -> None:
        self.me = self
        self.freed_on = freed_on
        self.qt = QObject()
        self.qt.destroyed.connect(lambda: freed_on.append(f"qt:{threading.current_thread().name}"),
                                  Qt.ConnectionType.DirectConnection)

    def __del__(self) -> None:
        self.freed_on.append(threading.current_thread().name)


def _allocate_on_a_thread(kept: list[Any]) -> str:
    """Allocate like a driver's thread does (many short-lived containers), and keep more than the collector's first
    threshold alive in ``kept``: an automatic collection is then due (the count is of live objects made since the
    last collection), on this thread before the change, on the main thread's next tick after it."""
    threshold = gc.get_threshold()[0]

    def work() -> None:
        for n in range(100_000):
            item = (n, [n])
            if n % 20 == 0:
                kept.append(item)
            if len(kept) > 3 * threshold:
                break
    thread = threading.Thread(target=work, name="allocating-thread")
    thread.start()
    thread.join(30)
    assert not thread.is_alive() and len(kept) > 3 * threshold
    return thread.name


def test_cyclic_garbage_with_a_qt_object_is_freed_on_the_main_thread(qtbot: Any) -> None:
    main_thread = collections()
    assert main_thread is not None and main_thread.active and not gc.isenabled(), \
        "the suite's process collects on its main thread (tests/conftest.py), as the app's does"
    freed_on: list[str] = []
    _Cycle(freed_on)  # garbage at once: only the collector frees it
    kept: list[Any] = []
    _allocate_on_a_thread(kept)  # before: an automatic collection on that thread freed the cycle there
    qtbot.waitUntil(lambda: len(freed_on) == 2, timeout=5000)  # the application's timer collects
    kept.clear()
    assert sorted(freed_on) == ["MainThread", "qt:MainThread"], \
        f"cyclic garbage was freed on {freed_on}, not the main thread"


def test_due_follows_the_thresholds_and_a_full_walk_waits_for_its_gap_and_the_window() -> None:
    now = [100.0]
    collector = MainThreadCollections(clock=lambda: now[0], full_gap_s=60.0)
    saved = gc.get_threshold()
    was_enabled = gc.isenabled()
    try:
        gc.set_threshold(10, 1, 1)
        collector.take_over()
        assert not gc.isenabled() and collector.active
        gc.collect()
        assert collector.due() is None
        junk = [[] for _ in range(50)]  # generation 0 past its threshold
        assert collector.collect_due() == 0 and collector.collections[0] == 1
        for _ in range(8):  # generation 1 past its threshold (twice), so generation 2's count past its own
            junk.append([[] for _ in range(50)])  # kept: the count is of live objects made since
            collector.collect_due()
        assert collector.collections[1] >= 2 and collector.collections[2] == 0
        assert gc.get_count()[2] > 1
        assert collector.due() != 2, "a full walk before its gap"
        now[0] += 61.0
        collector.full_allowed = lambda: False  # the window: something drives, the heap not frozen
        assert collector.due() != 2, "a full walk the window's policy did not allow"
        collector.full_allowed = lambda: True
        assert collector.collect_due() == 2 and collector.collections[2] == 1
        assert collector.due() in (None, 0, 1)
        now[0] += 1.0
        for _ in range(4):
            junk.append([[] for _ in range(50)])
            collector.collect_due()
        assert collector.collections[2] == 1 and collector.due() != 2, "a second full walk inside the gap"
    finally:
        collector.give_back()
        gc.set_threshold(*saved)
        if not was_enabled:
            gc.disable()
        installed = collections()
        if installed is not None and installed.active:
            gc.disable()  # the suite's process keeps collecting on its main thread
    assert collector.active is False


def test_every_process_with_a_qt_application_collects_on_its_main_thread() -> None:
    """The window's and the headless runner's Q(Core)Application, each followed by the collections."""
    for path in ("app/application.py", "app/scripting/headless.py"):
        text = (ROOT / path).read_text(encoding="utf-8")
        made = [m.start() for m in re.finditer(r"Q(?:Core)?Application\((?:sys\.argv|\[)", text)]
        assert made, path
        for at in made:
            following = text[at:at + 400]
            assert "collect_on_the_main_thread(app)" in following, \
                f"{path}: a Qt application made without the collections on its main thread"


def test_a_windows_policy_is_asked_too_and_its_end_leaves_the_rule_before_it() -> None:
    """The suite's rule (a full walk only between tests) held after a window had come and gone: the window replaced
    it and left "always" behind (a 143 ms full walk landed in a later test's measured turn)."""
    from app.core.gc_policy import HeapPolicy

    collector = MainThreadCollections()
    between_tests = [False]
    collector.full_allowed = lambda: between_tests[0]
    drives = ["the robot is ON"]
    policy = HeapPolicy(lambda: drives[0])  # a window's, not frozen, something driving: no full walk
    collector.also_ask(policy)
    between_tests[0] = True
    assert collector.full_allowed() is False
    drives[0] = ""
    assert collector.full_allowed() is True  # at rest, between tests
    between_tests[0] = False
    assert collector.full_allowed() is False  # the rule before it still holds
    del policy  # the window closed
    assert collector.full_allowed() is False, "a closed window's rule allowed a full walk inside a test"
    between_tests[0] = True
    assert collector.full_allowed() is True
