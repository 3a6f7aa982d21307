"""Starting and stopping the application: Qt + qasync event loop, the manager, the window, and the
safety nets (FES stop on crash, signals and exit)."""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

from PySide6.QtCore import QCoreApplication, QObject, QSettings, QTimer, Signal
from PySide6.QtWidgets import QApplication

from app.core.config import AppConfig
from app.core.paths import data_dir
from app.core.priority import no_thread_below_this_one
from app.manager import LinarmppManager

log = logging.getLogger(__name__)


def prepare_qt() -> None:
    """Before the QApplication exists, the process-wide settings the window depends on:

    * Every GL widget shares one context group. pyqtgraph caches compiled shader programs globally; without
      sharing, a second 3D view (a new window, a test) gets 'invalid value' from glUseProgram and draws nothing.
    * The window's thread paints by itself (``QT_NO_GUI_THREADPOOL``). Qt's raster engine otherwise hands each
      large fill or image scale to a pool of helper threads and waits for them on a latch; those helpers are not
      the window's thread, so on a busy 2-core machine the window waited for threads that had no CPU: a graph's
      repaint held the window 0.4-0.9 s, and the GUI watch stopped the robot (seen in CI on a clean clone, with
      the firmware building beside the clinician's day; py-spy showed the window's thread in QLatch::wait under
      QRasterPaintEngine::drawImage / drawPolygon). Painting on one thread costs a few ms more per frame at most.
    * No Mesa shader cache on disk (its threads run at nice 19; see below).
    """
    from PySide6.QtCore import Qt

    # Read once, by the first paint that would use the pool: must be set before anything paints.
    os.environ.setdefault("QT_NO_GUI_THREADPOOL", "1")
    # No shader cache on disk (Mesa): its writer threads run at the lowest priority (nice 19, SCHED_BATCH), and the
    # process's last thread to end unmaps all its memory at that thread's priority: beside two busy programs the
    # window's process then ended 1.5-3 s after os._exit, past the 2 s a signal allows (issue #25). Compiling the
    # views' few shaders at each start costs milliseconds.
    os.environ.setdefault("MESA_SHADER_CACHE_DISABLE", "true")
    if QCoreApplication.instance() is None:
        QCoreApplication.setAttribute(Qt.ApplicationAttribute.AA_ShareOpenGLContexts)


def configure_qt_identity() -> None:
    """QSettings in the app's data folder (LINARMPP_HOME moves it for tests)."""
    QCoreApplication.setOrganizationName("LINarmPP")
    QCoreApplication.setApplicationName("LINarm++ Manager")
    QSettings.setDefaultFormat(QSettings.Format.IniFormat)
    QSettings.setPath(QSettings.Format.IniFormat, QSettings.Scope.UserScope, str(data_dir() / "settings"))


def apply_desktop_identity(app: QApplication) -> None:
    """The window icon (resources/linarmpp.svg) and the desktop entry's name, so that a Linux desktop
    (the Wayland app id) matches the window to linarmpp.desktop and its icon."""
    from PySide6.QtGui import QGuiApplication, QIcon

    from app.core.resources import ICON_FILE

    app.setWindowIcon(QIcon(str(ICON_FILE)))
    QGuiApplication.setDesktopFileName("linarmpp")


def install_safety_nets(manager: LinarmppManager, on_signal: Callable[[int], None] | None = None
                        ) -> Callable[[], None]:
    """An uncaught exception anywhere brings devices to a safe state first; SIGTERM, SIGINT and SIGHUP are
    events (app.core.signal_events): the first one brings the devices to a safe state once, on a thread of its
    own, then ``on_signal(signum)`` (run_gui: ends the event loop). Returns a function that removes the nets."""
    from app.core.signal_events import SignalEvents, signal_name

    previous_hook = sys.excepthook
    previous_thread_hook = threading.excepthook

    def hook(exc_type: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
        log.critical("uncaught exception: stopping stimulation and robot", exc_info=(exc_type, exc, tb))
        try:
            manager.supervisor.bring_to_safe_state(f"uncaught {exc_type.__name__}")
        finally:
            previous_hook(exc_type, exc, tb)

    def thread_hook(args: threading.ExceptHookArgs) -> None:
        hook(args.exc_type, args.exc_value or Exception(), args.exc_traceback)

    def safe_state(signum: int) -> None:
        manager.supervisor.bring_to_safe_state(f"{signal_name(signum)} received")

    def closing(signum: int) -> None:
        safe_state(signum)
        if on_signal is not None:
            on_signal(signum)

    sys.excepthook = hook
    threading.excepthook = thread_hook
    signals = SignalEvents(closing, last_resort=safe_state).install()

    def remove() -> None:
        sys.excepthook = previous_hook
        threading.excepthook = previous_thread_hook
        signals.remove()

    return remove


class ArchiveOpening:
    """The station's archive opened on a thread of its own (app.archive.station.open_station: a clinic's server
    may take seconds to answer), the Qt events processed meanwhile; waited for before the devices start."""

    def __init__(self, config: AppConfig) -> None:
        from app.archive import station

        self._result: station.Opened | None = None
        self._error: BaseException | None = None
        self._done = threading.Event()

        def run() -> None:
            try:
                self._result = station.open_station(config)
            except BaseException as exc:  # handed to the GUI thread: a refusal is said there
                self._error = exc
            finally:
                self._done.set()

        self._thread = threading.Thread(target=run, name="archive-open", daemon=True)
        self._thread.start()

    def result(self, app: QCoreApplication | None = None) -> Any:
        """The Opened result once ready (the Qt events processed meanwhile); raises the archive's refusal
        (ArchiveTooNew, NeedsUpgrade, ConfigProblem) as a sentence."""
        while not self._done.wait(0.02):
            if app is not None:
                app.processEvents()
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._result


def archive_refusal(exc: BaseException) -> str:
    """The one sentence for an archive the application refuses to start with ('' when ``exc`` is not one)."""
    from app.archive.api import ArchiveTooNew, ConfigProblem, NeedsUpgrade

    if isinstance(exc, ArchiveTooNew | NeedsUpgrade | ConfigProblem):
        return f"LINarm++ Manager cannot use the patients' archive, nothing was started: {exc}"
    return ""


class _LoopExit(QObject):
    """Ends the Qt event loop from the signal thread: a Qt signal emitted there is delivered in the main
    thread (queued). ``exit`` rather than ``quit``: a window may refuse a quit (a dialog), never an exit."""

    requested = Signal(int)

    def __init__(self, app: QCoreApplication) -> None:
        super().__init__()
        self.code: int | None = None
        self.requested_at = 0.0  # time.monotonic() of the request (the devices already safe)
        self.requested.connect(self._exit)
        self._app = app

    def request(self, code: int) -> None:
        """From any thread."""
        self.requested_at = time.monotonic()
        self.requested.emit(code)

    def _exit(self, code: int) -> None:
        self.code = code
        self._app.exit(code)


def run_gui(config: AppConfig, screenshot: str | None = None, quit_after_s: float | None = None) -> int:
    import qasync

    from app.ui.main_window import MainWindow

    prepare_qt()
    app = QApplication.instance() or QApplication(sys.argv)
    from app.main_thread_gc import collect_on_the_main_thread

    collect_on_the_main_thread(app)  # before any other thread exists: Qt objects destroyed on their own thread
    configure_qt_identity()
    apply_desktop_identity(app)
    from app.ui.theme import apply_palette

    apply_palette(app, config.ui.palette)
    from app.archive import station

    # The archive is opened before the devices start, not beside them: opening it (the database code's first
    # import, the schema check, a new archive's tables) holds the interpreter ~1-2 s, and beside a starting LINarm
    # it starved the driver's heartbeat until the controller's watchdog tripped during homing (seen in the suite:
    # the window's first start in a new data folder never reached stimulation). Nothing is driven yet here.
    opening = ArchiveOpening(config)
    manager = LinarmppManager(config)
    from app.core.signal_events import exit_code_for

    loop_exit = _LoopExit(app)
    remove_nets = install_safety_nets(manager, lambda signum: loop_exit.request(exit_code_for(signum)))
    try:
        opened = opening.result(app)
    except Exception as exc:
        refusal = archive_refusal(exc)
        if not refusal:
            raise
        from PySide6.QtWidgets import QMessageBox

        print(refusal, file=sys.stderr)
        log.error("%s", refusal)
        manager.shutdown()
        remove_nets()
        QMessageBox.critical(None, "LINarm++ Manager", refusal)
        return 2
    station.install(opened.archive, opened.problem)
    manager.start()
    window = MainWindow(manager)
    window.show()
    archive_note = None
    if opened.message():  # the station runs: said once, the window not held (no nested event loop)
        from PySide6.QtWidgets import QMessageBox

        log.warning("%s", opened.message())
        archive_note = QMessageBox(QMessageBox.Icon.Warning, "Patients' archive", opened.message(),
                                   QMessageBox.StandardButton.Ok, window)
        archive_note.open()
    if screenshot:
        def shoot() -> None:
            if manager.all_connected():
                window.grab().save(screenshot)
                log.info("screenshot saved to %s", screenshot)
                app.quit()
            else:
                QTimer.singleShot(200, shoot)
        QTimer.singleShot(1500, shoot)
    if not screenshot and config.ui.ask_session_on_start:
        QTimer.singleShot(0, window.prompt_session)
    if quit_after_s is not None:
        QTimer.singleShot(int(quit_after_s * 1000), app.quit)
    loop = qasync.QEventLoop(app)
    asyncio.set_event_loop(loop)
    try:
        with loop:
            loop.run_forever()
    finally:
        window.stop_gui_watch()  # the loop has ended: no beat follows, and shutting down is no stall
        manager.shutdown()
        remove_nets()
        archive = station.uninstall()
        if archive is not None:
            archive.close()
        del archive_note
    if loop_exit.code is not None:
        # Ended by a signal, with the devices safe and the session closed: end now. Qt's teardown of the window
        # (the GL views) took 0.4-2 s on a loaded machine, and a process told to end must end (issue #25).
        log.info("closed %.3f s after the devices' safe state (exit code %d)",
                 time.monotonic() - loop_exit.requested_at, loop_exit.code)
        no_thread_below_this_one()
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(loop_exit.code)
    return 0
