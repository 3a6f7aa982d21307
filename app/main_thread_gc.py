"""The collector runs on the main thread only (issue #38; the rule in app/core/gc_policy.py,
:class:`~app.core.gc_policy.MainThreadCollections`): a process that holds Qt objects — the window, the headless
runner, the suite's workers — turns the interpreter's automatic collections off and collects what is due from a
timer on its main thread, so that a Qt object caught in a reference cycle is destroyed on the thread it belongs to,
never on a driver's, a loader's or the bus's thread that happened to allocate.
"""

from __future__ import annotations

from PySide6.QtCore import QCoreApplication, QThread, QTimer

from app.core.gc_policy import COLLECT_EVERY_S, MainThreadCollections

_installed: MainThreadCollections | None = None


def collections() -> MainThreadCollections | None:
    """This process's collections on the main thread (None until ``collect_on_the_main_thread``)."""
    return _installed


def collect_on_the_main_thread(app: QCoreApplication) -> MainThreadCollections:
    """Once per process, from the main thread, after the Q(Core)Application exists: the automatic collections off,
    a timer of ``app`` collecting what is due every ``COLLECT_EVERY_S``. Returns the process's collections."""
    global _installed
    if _installed is not None:
        return _installed
    if QThread.currentThread() is not app.thread():
        raise RuntimeError("the collections must be installed from the application's main thread")
    collections = MainThreadCollections()
    timer = QTimer(app)
    timer.setObjectName("main-thread-gc")
    timer.setInterval(int(COLLECT_EVERY_S * 1000))
    timer.timeout.connect(collections.collect_due)
    timer.start()
    collections.take_over()
    app.aboutToQuit.connect(collections.collect_due)
    _installed = collections
    return collections
