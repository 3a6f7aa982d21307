"""The clinician's main window: the seed's four frames as rearrangeable docks, an always-visible
emergency stop, a status bar with each device's connection and rate, and menus.

The window is a view: its one Qt bus adapter (:class:`~app.ui.qt_bus.QtBus` on ``manager.bus``) brings the
samples and device events to its frames as Qt signals; it sends commands through the manager; it never parses
bytes or opens ports. Closing the window closes the adapter: nothing of the window stays subscribed to the bus.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6.QtCore import QEvent, QObject, QSettings, Qt, QThread, QTimer, Signal
from PySide6.QtGui import QAction, QFont, QFontMetrics, QKeySequence, QPainter, QPixmap
from PySide6.QtWidgets import (
    QApplication,
    QDockWidget,
    QHBoxLayout,
    QLabel,
    QMainWindow,
    QMessageBox,
    QPushButton,
    QSizePolicy,
    QToolBar,
    QWidget,
)

from app import __version__
from app.core.logging_setup import log_file
from app.core.paths import data_dir, sessions_dir
from app.core.resources import RESOURCES
from app.manager import LinarmppManager
from app.ui.qt_bus import QtBus, takes_qt_bus
from app.ui.recovery import Restartable
from app.ui.tasks import QtTasks

log = logging.getLogger(__name__)

ARCHIVE_PASS_MS = 30_000  # the outbox's pass: its own back-off decides whether a try is due
ESTOP_STYLE = (
    "QPushButton { background: #c62828; color: white; font-size: 20px; font-weight: bold;"
    " border: 3px solid #7f0000; border-radius: 8px; padding: 8px 28px; }"
    "QPushButton:pressed { background: #8e0000; }"
)

# (dock title, module, class) — the frames of the seed's GUI (D2.1 "LINarm++").
FRAMES: list[tuple[str, str, str, Qt.DockWidgetArea]] = [
    ("1 · Values", "app.ui.values_frame", "ValuesFrame", Qt.DockWidgetArea.LeftDockWidgetArea),
    ("2 · Graphs", "app.ui.plots_frame", "PlotsFrame", Qt.DockWidgetArea.RightDockWidgetArea),
    ("3 · Device view", "app.ui.device_view", "DeviceView", Qt.DockWidgetArea.LeftDockWidgetArea),
    ("4 · Commands", "app.ui.commands_frame", "CommandsFrame", Qt.DockWidgetArea.RightDockWidgetArea),
]


class EmergencyStopKeyFilter(QObject):
    """Application-wide key filter: the e-stop key works whatever has focus, modal dialogs included
    (a QShortcut is blocked by a modal dialog; an application event filter is not)."""

    triggered = Signal()

    def __init__(self, key: QKeySequence) -> None:
        super().__init__()
        self.key = key

    def eventFilter(self, obj: QObject, event: QEvent) -> bool:
        if event.type() in (QEvent.Type.KeyPress, QEvent.Type.ShortcutOverride):
            combo = QKeySequence(event.keyCombination())
            if combo.matches(self.key) == QKeySequence.SequenceMatch.ExactMatch:
                if event.type() == QEvent.Type.KeyPress and not event.isAutoRepeat():
                    self.triggered.emit()
                event.accept()
                return True
        return False


class EmergencyStopPressFilter(QObject):
    """Fires on the e-stop button's mouse press before the button handles it: QAbstractButton repaints
    itself synchronously before it emits ``pressed``, and that repaint flushes every pending paint of
    the window (a graphs frame: tens of ms) ahead of the stop."""

    triggered = Signal()

    def __init__(self) -> None:
        super().__init__()
        self.fired = False  # this press already stopped: ``pressed`` must not stop again

    def eventFilter(self, obj: QObject, event: QEvent) -> bool:
        if (event.type() in (QEvent.Type.MouseButtonPress, QEvent.Type.MouseButtonDblClick)
                and event.button() == Qt.MouseButton.LeftButton):  # type: ignore[attr-defined]
            self.fired = True
            self.triggered.emit()
        elif event.type() == QEvent.Type.MouseButtonRelease:
            self.fired = False  # had the button not emitted ``pressed``, the next press must still stop
        return False  # the button still shows itself pressed


class DeviceStatus(QLabel):
    def __init__(self, name: str) -> None:
        super().__init__()
        self.name = name
        self.connected = False
        self.reason = "starting"
        self.setTextFormat(Qt.TextFormat.RichText)
        # Room for the longest state and a four-digit rate, reserved: a rate gaining a digit must not
        # clip the label before the status bar lays itself out again.
        bold = QFont(self.font())
        bold.setBold(True)
        plain = QFontMetrics(self.font())
        # Fixed, not just a minimum: a label whose size can change asks the status bar, and through it the
        # whole main window, to lay itself out and repaint again on every new text.
        self.setFixedWidth(QFontMetrics(bold).horizontalAdvance(name) + 8
                           + max(plain.horizontalAdvance(f"● {t} 9999 Hz") for t in ("connected", "silent"))
                           + plain.horizontalAdvance("  "))
        self.setFixedHeight(max(QFontMetrics(bold).height(), plain.height()) + 2)
        self.shown_rate = 0.0
        self.refresh({})

    def set_connection(self, connected: bool, reason: str) -> None:
        self.connected = connected
        self.reason = reason
        self.setToolTip(reason)

    def refresh(self, rates: dict[str, float], silent: bool = False) -> None:
        if self.connected and not silent:
            colour, state = "#2e7d32", "connected"
        elif self.connected:
            colour, state = "#ef6c00", "silent"
        else:
            colour, state = "#c62828", "disconnected"
        rate = max(rates.values()) if rates else 0.0
        # The measured rate wanders by a few Hz around the nominal one: a new figure only when it moved by
        # more than 5 % (a stream that drops to half its rate still shows at once).
        if abs(rate - self.shown_rate) > 0.05 * max(self.shown_rate, 1.0):
            self.shown_rate = rate
        rate_txt = f" {self.shown_rate:.0f} Hz" if self.connected else ""
        text = f"<span style='color:{colour}'>●</span> <b>{self.name}</b> {state}{rate_txt}"
        if text != self.text():  # a rich-text label re-lays itself out on every setText
            self.setText(text)
            self.setAccessibleName(f"{self.name} {state}")


def recorder_folder(manager: LinarmppManager) -> Path | None:
    recorder = manager.recorder
    return None if recorder is None else recorder.folder


class MainWindow(QMainWindow):
    def __init__(self, manager: LinarmppManager) -> None:
        super().__init__()
        self.manager = manager
        # The window's one adapter: every frame takes its samples and device events from it.
        # The one adapter: the panels built with the manager only find it (shared_qt_bus) and take their journal
        # signals (alarms, e-stop, leases, records, progress) from it.
        self.qt_bus = QtBus(manager.bus, parent=self, alarms=manager.supervisor.alarm, share=True)
        self.setWindowTitle("LINarm++ Manager")
        self.setObjectName("MainWindow")
        self.setDockNestingEnabled(True)
        self.frames: dict[str, QWidget] = {}
        self.docks: dict[str, QDockWidget] = {}
        self._build_toolbar()
        self._build_frames()
        self._build_menus()
        self._build_status_bar()
        self._estop_filter = EmergencyStopKeyFilter(QKeySequence(manager.config.ui.emergency_stop_shortcut))
        self._estop_filter.triggered.connect(lambda: self.emergency_stop("keyboard"))
        app = QApplication.instance()
        if app is not None:
            app.installEventFilter(self._estop_filter)
        from app.ui.widgets import install_wheel_guard

        install_wheel_guard()  # the wheel over a number box scrolls the form unless the box has the focus (#36)
        self.qt_bus.estop_changed.connect(self._on_estop_changed)
        self._quit_confirmed = False  # may_quit() said yes: a second close event does not ask again
        self._install_gui_watch()
        self._offer_larger_graphs()
        self._restore_settings()

    # ------------------------------------------------------------------ the watched window (#37)
    def _install_gui_watch(self) -> None:
        """This window's thread beats for the GUI watch (app.gui_watch): a stall while the robot is ON or
        stimulation runs is an alarm, a longer one the safe state."""
        from app.ui.gui_heartbeat import install_gui_watch

        self.gui_heartbeat = install_gui_watch(self.manager, self)
        # The collector's full walks kept off the therapy (app/core/gc_policy.py): survivors settled while driving,
        # everything collected once at rest.
        from app.core.gc_policy import REST_S, TICK_S, HeapPolicy
        from app.gui_watch import what_drives

        self.heap_policy = HeapPolicy(lambda: what_drives(self.manager), rest_s=REST_S)
        self._heap_timer = QTimer(self)
        self._heap_timer.setInterval(int(TICK_S * 1000))
        self._heap_timer.timeout.connect(self.heap_policy.tick)
        self._heap_timer.start()
        from app.main_thread_gc import collections

        main_thread = collections()
        if main_thread is not None:  # full walks on the main thread only when the window's policy allows them too
            main_thread.also_ask(self.heap_policy)
        QTimer.singleShot(0, self.heap_policy.settle)  # the window and its frames live as long as the app

    def _offer_larger_graphs(self) -> None:
        """The Graphs frame's "Larger": the Commands frame steps aside so the graphs get the whole right column
        (#37: six graphs readable at 1366×768); any command tab opened brings it back."""
        plots, commands = self.frames.get("PlotsFrame"), self.docks.get("CommandsFrame")
        if plots is None or commands is None or not hasattr(plots, "enlarge_toggled"):
            return
        plots.set_enlarge_offered(True)
        plots.enlarge_toggled.connect(self.set_graphs_enlarged)
        commands.toggleViewAction().toggled.connect(lambda shown: plots.set_enlarged(not shown))

    def set_graphs_enlarged(self, enlarged: bool) -> None:
        commands = self.docks.get("CommandsFrame")
        if commands is not None:
            commands.setVisible(not enlarged)

    def stop_gui_watch(self) -> None:
        """No more judgement of this window's thread (it closes, or the application's loop has ended)."""
        heartbeat = getattr(self, "gui_heartbeat", None)
        if heartbeat is not None:
            heartbeat.close()

    # ------------------------------------------------------------------ building
    def _build_toolbar(self) -> None:
        bar = QToolBar("Safety", self)
        bar.setObjectName("SafetyToolbar")
        bar.setMovable(False)
        bar.setFloatable(False)
        bar.toggleViewAction().setEnabled(False)  # the e-stop can never be hidden
        self.addToolBar(Qt.ToolBarArea.TopToolBarArea, bar)
        holder = QWidget()
        row = QHBoxLayout(holder)
        row.setContentsMargins(4, 2, 4, 2)
        key = self.manager.config.ui.emergency_stop_shortcut
        self.estop_button = QPushButton(f"EMERGENCY STOP  ({key})")
        self.estop_button.setObjectName("EmergencyStop")
        self.estop_button.setStyleSheet(ESTOP_STYLE)
        self.estop_button.setMinimumHeight(52)
        self.estop_button.setToolTip(f"Stops stimulation and the robot at once ({key} works from every window)")
        # On press, not on release: an emergency stop acts when the hand comes down, it must not wait
        # for the button to be let go (nor be cancelled by sliding off it before release). A mouse press
        # is caught before the button repaints; ``pressed`` covers the rest (keyboard, click()).
        self._estop_press = EmergencyStopPressFilter()
        self._estop_press.triggered.connect(lambda: self.emergency_stop("button"))
        self.estop_button.installEventFilter(self._estop_press)
        self.estop_button.pressed.connect(self._estop_button_pressed)
        row.addWidget(self.estop_button)
        self.estop_reset = QPushButton("Reset e-stop…")
        self.estop_reset.setEnabled(False)
        self.estop_reset.clicked.connect(self._reset_estop)
        row.addWidget(self.estop_reset)
        # One word here; the reason is in the alarm banner beside it (and in this label's tooltip).
        self.estop_label = QLabel("")
        self.estop_label.setStyleSheet("color: #c62828; font-weight: bold; font-size: 16px;")
        row.addWidget(self.estop_label)
        from app.ui.alarms_panel import AlarmBanner
        from app.ui.widgets import ElidedLabel

        self.alarm_banner = AlarmBanner(self.manager)
        self.alarm_banner.show_alarms_requested.connect(self.show_alarms)
        self.alarm_banner.restart_provider = self._interrupted_exercise
        self.alarm_banner.script_running = lambda: bool(getattr(self._script_runner(), "running", False))
        self.alarm_banner.stop_script = self._stop_script_for_recovery
        self.alarm_banner.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        self.alarm_banner.setMinimumWidth(160)
        row.addWidget(self.alarm_banner, 3)
        # Long patient/operator names must not widen the window's minimum size (1366×768 screens):
        # elided, with the whole text (and the recording folder) in the tooltip.
        self.session_label = ElidedLabel()
        self.session_label.setObjectName("SessionLabel")
        self.session_label.setMinimumWidth(90)
        self.session_label.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        row.addWidget(self.session_label, 1)
        self.session_button = QPushButton()
        self.session_button.clicked.connect(self._session_button_clicked)
        row.addWidget(self.session_button)
        bar.addWidget(holder)
        self.manager.session_changed.connect(lambda _folder: self._show_session())
        # A session has started: its plan and exercises come next (one action fewer to the first exercise).
        self.manager.session_changed.connect(lambda folder: self.show_tab("Exercises") if folder is not None else None)
        # Heavy work (reading sessions, reports, exports) runs in a worker process (issue #37), started when first
        # needed; a session that ends gets its columnar copy there, so opening it later is fast.
        self._tasks: QtTasks | None = None
        self._tasks_closed = False
        from app.worker.jobs import import_result_types

        import_result_types()  # at start-up, not during a therapy when the first result arrives (app/worker/jobs.py)
        # The worker started when a session starts (off this thread, niced): its first start imports the
        # scientific stack, 20 s and more on a loaded PC, and the first exercise's summary should not wait for it.
        self.manager.session_changed.connect(lambda folder: self._warm_worker() if folder is not None else None)
        self._recording: Path | None = recorder_folder(self.manager)
        self.manager.session_changed.connect(self._session_folder_changed)
        self._show_session()

    def _build_frames(self) -> None:
        for title, module_name, class_name, area in FRAMES:
            widget = self._make_frame(module_name, class_name, title)
            dock = QDockWidget(title, self)
            dock.setObjectName(f"dock:{class_name}")
            dock.setWidget(widget)
            # Closable: the View menu's toggles are enabled only for docks that can be closed.
            dock.setFeatures(QDockWidget.DockWidgetFeature.DockWidgetMovable
                             | QDockWidget.DockWidgetFeature.DockWidgetFloatable
                             | QDockWidget.DockWidgetFeature.DockWidgetClosable)
            self.addDockWidget(area, dock)
            self.frames[class_name] = widget
            self.docks[class_name] = dock

    def _make_frame(self, module_name: str, class_name: str, title: str) -> QWidget:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            placeholder = QLabel(f"{title}\n(not available in this build)")
            placeholder.setAlignment(Qt.AlignmentFlag.AlignCenter)
            return placeholder
        factory: Callable[..., QWidget] = getattr(module, class_name)
        return factory(self.manager, qt_bus=self.qt_bus) if takes_qt_bus(factory) else factory(self.manager)

    def _build_menus(self) -> None:
        file_menu = self.menuBar().addMenu("&File")
        quit_action = QAction("&Quit", self)
        quit_action.setShortcut(QKeySequence.StandardKey.Quit)
        # From any window (Sessions, Replay, …): the shortcut is application-wide and Quit ends the app.
        quit_action.setShortcutContext(Qt.ShortcutContext.ApplicationShortcut)
        quit_action.triggered.connect(self.close)
        file_menu.addAction(quit_action)
        session_menu = self.menuBar().addMenu("&Session")
        start = QAction("&Start session…", self)
        start.setShortcut(QKeySequence("Ctrl+N"))
        start.triggered.connect(self.prompt_session)
        session_menu.addAction(start)
        end = QAction("&End session", self)
        end.triggered.connect(self.end_session)
        end.setEnabled(self.manager.recorder is not None)
        self.end_action = end
        session_menu.addAction(end)
        session_menu.addSeparator()
        patients = QAction("&Patients…", self)
        patients.triggered.connect(self.show_patients)
        session_menu.addAction(patients)
        browser = QAction("Sessions &browser…", self)
        browser.triggered.connect(self.show_sessions_browser)
        session_menu.addAction(browser)
        view_menu = self.menuBar().addMenu("&View")
        for dock in self.docks.values():
            view_menu.addAction(dock.toggleViewAction())
        self.dark_action = QAction("&Dark palette", self)
        self.dark_action.setCheckable(True)
        self.dark_action.setShortcut(QKeySequence("Ctrl+Shift+D"))
        self.dark_action.toggled.connect(self.set_dark_palette)
        view_menu.addAction(self.dark_action)
        reset_layout = QAction("Reset &layout", self)
        reset_layout.triggered.connect(lambda: self._reset_layout())
        view_menu.addAction(reset_layout)
        help_menu = self.menuBar().addMenu("&Help")
        about = QAction("&About", self)
        about.triggered.connect(self.show_about)
        help_menu.addAction(about)

    def _build_status_bar(self) -> None:
        self.device_status: dict[str, DeviceStatus] = {}
        for name in self.manager.devices:
            label = DeviceStatus(name)
            label.set_connection(self.qt_bus.connected(name), "starting")
            self.statusBar().addPermanentWidget(label)
            self.device_status[name] = label
        self.qt_bus.connection_changed.connect(self._on_device_connection)
        self._status_timer = QTimer(self)
        # Rates and silence once a second; a connection or loss shows at once (_on_device_connection).
        self._status_timer.setInterval(1000)
        self._status_timer.timeout.connect(self._refresh_status)
        self._status_timer.start()
        self._refresh_status()
        # The station's outbox (#39): "2 sessions waiting for the archive", nothing when all are archived.
        # Put in the status bar only once it has something to say: even hidden there, it made the bar 13 px
        # taller and pushed the sixth graph out of view at 1366×768 (tests/test_graphs_1366.py).
        self.archive_status = QLabel("")
        self.archive_status.setObjectName("archiveStatus")
        self.archive_status.setVisible(False)
        self._archive_task: Any = None
        self._archive_again = False
        self._archive_timer = QTimer(self)
        self._archive_timer.setInterval(ARCHIVE_PASS_MS)
        self._archive_timer.timeout.connect(self.archive_pass)
        from app.archive import station

        if station.in_use():  # the application's archive (opened before the window); none: nothing to pass
            self._archive_timer.start()
            QTimer.singleShot(0, self, lambda: self.archive_pass(force=True))  # the sessions left over

    # ------------------------------------------------------------------ behaviour
    def emergency_stop(self, source: str) -> None:
        self.manager.supervisor.emergency_stop(source)  # the stop itself: a direct call, the devices first
        self.qt_bus.tick()  # then the screen, now rather than at the adapter's next tick

    def _estop_button_pressed(self) -> None:
        if self._estop_press.fired:  # the mouse press already stopped
            self._estop_press.fired = False
            return
        self.emergency_stop("button")

    # ------------------------------------------------------------------ sessions
    def _show_session(self) -> None:
        recorder = self.manager.recorder
        if recorder is None:
            self.session_label.set_full_text("No session: not recording", "Data is not being recorded")
            self.session_label.setStyleSheet("color: #ef6c00; font-weight: bold;")
            self.session_button.setText("Start session…")
        else:
            folder = recorder.folder
            self.session_label.set_full_text(f"● {folder.parent.name} · {self.manager.operator}",
                                             f"Session of {folder.parent.name}, operator {self.manager.operator},"
                                             f" recording to {folder}")
            self.session_label.setStyleSheet("")
            self.session_button.setText("End session")
        end = getattr(self, "end_action", None)
        if end is not None:
            end.setEnabled(recorder is not None)

    def _session_button_clicked(self) -> None:
        if self.manager.recorder is None:
            self.prompt_session()
        else:
            self.end_session()

    def prompt_session(self) -> None:
        from app.ui.patient_dialog import StartSessionDialog

        if self.manager.recorder is not None:
            QMessageBox.information(self, "Session", "A session is already running. End it first.")
            return
        dialog = StartSessionDialog(self.manager.config.safety, parent=self)
        self._session_dialog = dialog

        def accepted() -> None:
            patient_id, operator, note = dialog.values()
            try:
                self.manager.start_session(patient_id, operator, note)
            except (ValueError, RuntimeError, OSError) as exc:
                text = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
                QMessageBox.warning(self, "Session not started", text)

        dialog.accepted.connect(accepted)
        dialog.open()

    def _stop_question(self, question: str) -> str:
        """The words of End session's question, also Quit's: what stops, and the alarms left unacknowledged."""
        open_ = [a for a in self.manager.supervisor.alarms() if not a.acknowledged]
        warning = (f"<br><br><b>{len(open_)} alarm(s) are not acknowledged</b> — they stay unacknowledged in "
                   "the session record. Acknowledge them first from the Alarms list if you want them signed."
                   if open_ else "")
        return f"{question} Stimulation stops and the robot goes idle.{warning}"

    def end_session(self) -> None:
        if self.manager.recorder is None:
            return
        answer = QMessageBox.question(self, "End session", self._stop_question("End the session?"))
        if answer == QMessageBox.StandardButton.Yes:
            self.manager.end_session()

    def show_patients(self) -> None:
        from app.ui.patients_window import PatientsDialog

        self._patients_window = PatientsDialog(self.manager.config.safety, parent=self)
        self._patients_window.show()

    def _warm_worker(self) -> None:
        if not self._tasks_closed:
            self.tasks().warm()

    def tasks(self) -> QtTasks:
        """The window's worker process (app/ui/tasks.py), made when first needed."""
        if self._tasks is None:
            self._tasks = QtTasks(parent=self)
            if self._tasks_closed:
                self._tasks.close()
        return self._tasks

    def _session_folder_changed(self, folder: Path | None) -> None:
        from app.session.recording import index_worthwhile

        ended, self._recording = self._recording, folder
        if ended is not None and folder != ended and not self._tasks_closed and index_worthwhile(ended):
            self.tasks().run("index_session", str(ended), title=f"Indexing session {ended.name}")
        if ended is not None and folder != ended:
            self.archive_pass(force=True)

    def archive_pass(self, force: bool = False) -> None:
        """The station's outbox uploads the finished sessions (at a session's end, at start-up, every 30 s), in
        the worker process (an upload computes the session's metrics: never in this process, #37); the status
        bar says what waits. Nothing without an archive (a library use, most tests)."""
        from app.archive import station

        if self._tasks_closed or not station.in_use():
            return
        if self._archive_task is not None:  # one pass at a time; a forced one follows the running one
            self._archive_again = self._archive_again or force
            return
        from app.archive.outbox import archive_settings
        from app.session.recording import sessions_root

        active = recorder_folder(self.manager)
        self._archive_task = self.tasks().run(
            "app.archive.outbox:station_pass", str(sessions_root(self.manager.config)),
            *archive_settings(self.manager.config), [str(active)] if active is not None else [], force,
            title="Archiving the sessions", on_done=self._archive_done)

    def _archive_done(self, task: Any) -> None:
        self._archive_task = None
        if task.ok:
            status = task.result
            text = status.text()
            if status.uploaded:
                self.statusBar().showMessage(f"{status.uploaded} session{'s' if status.uploaded > 1 else ''} "
                                             "archived", 5000)
        else:
            text = f"Sessions not archived: {task.error}"
        self.archive_status.setText(text)
        self.archive_status.setToolTip(text)
        if text and self.archive_status.parent() is None:
            self.statusBar().addPermanentWidget(self.archive_status)
        self.archive_status.setVisible(bool(text))
        if self._archive_again:
            self._archive_again = False
            self.archive_pass(force=True)

    def show_sessions_browser(self) -> None:
        from app.session.recording import sessions_root
        from app.ui.sessions_browser import SessionsBrowser

        self._browser = SessionsBrowser(sessions_root(self.manager.config), self.manager.config.ui.history_s,
                                        active=lambda: recorder_folder(self.manager), tasks=self.tasks())
        # a replay or summary window just built lives on while it is open: out of the collector's walk at once
        self._browser.opened.connect(lambda _widget: QTimer.singleShot(0, self.heap_policy.settle))
        self._browser.show()

    def show_alarms(self) -> None:
        self.show_tab("Alarms")

    def show_tab(self, title: str) -> None:
        """Bring the Commands frame's tab ``title`` to the front (the frame shown if it was closed)."""
        commands = self.frames.get("CommandsFrame")
        tabs = getattr(commands, "tabs", None)
        if tabs is None or "CommandsFrame" not in self.docks:
            return
        self.docks["CommandsFrame"].show()
        for i in range(tabs.count()):
            if tabs.tabText(i) == title:
                tabs.setCurrentIndex(i)

    def _script_console(self) -> QWidget | None:
        return getattr(self.frames.get("CommandsFrame"), "panels", {}).get("ScriptConsole")

    def _script_runner(self) -> object | None:
        return getattr(self._script_console(), "runner", None)

    def _interrupted_exercise(self) -> Restartable | None:
        """The run a STOP interrupted, for the banner's Recover (app.ui.recovery.interrupted_run)."""
        from app.ui.recovery import interrupted_run

        return interrupted_run(self.manager, getattr(self.frames.get("CommandsFrame"), "panels", {}))

    def _stop_script_for_recovery(self) -> bool:
        """Recover never resets the e-stop under a running script: stop it first (True if it ran)."""
        runner = self._script_runner()
        if runner is None or not runner.running:
            return False
        # the STOP is why it ends (#36: recorded as "stopped by the operator" before)
        cause = "emergency_stop" if self.manager.supervisor.estop_latched else "safety_stop"
        runner.stop("stopped by Recover after an emergency stop", wait_s=2.0, cause=cause)
        return True

    def _on_estop_changed(self, latched: bool, reason: str) -> None:
        self.estop_reset.setEnabled(latched)
        self.estop_label.setText("STOPPED" if latched else "")
        self.estop_label.setToolTip(reason if latched else "")

    def _reset_estop(self) -> None:
        answer = QMessageBox.question(
            self, "Reset emergency stop",
            "Reset the emergency stop? Devices stay idle until you start them again.",
        )
        if answer == QMessageBox.StandardButton.Yes:
            # The session's operator (the record must say who), "operator" only when no session runs.
            self.manager.supervisor.reset_emergency_stop(self.manager.operator or "operator")
            self.qt_bus.tick()  # the screen follows at once

    def _on_device_connection(self, name: str, connected: bool, reason: str) -> None:
        label = self.device_status.get(name)
        if label is not None:
            label.set_connection(connected, reason)
            label.refresh(self.manager.devices[name].driver.rates())
        self.statusBar().showMessage(f"{name}: {reason}", 5000)

    def _refresh_status(self) -> None:
        for name, label in self.device_status.items():
            label.connected = self.qt_bus.connected(name)
            label.refresh(self.manager.devices[name].driver.rates(), self.qt_bus.silent(name))

    def show_about(self) -> None:
        QMessageBox.about(
            self, "About LINarm++ Manager",
            f"<b>LINarm++ Manager</b> {__version__}"
            "<br>Upper-limb rehabilitation with LINarm2, physiological sensors and FES."
            f"<br><br>Configuration: {self.manager.config.source}"
            f"<br>Log file: {log_file() or '(console only)'}"
            f"<br>Sessions: {sessions_dir()}<br>Data folder: {data_dir()}<br>Resources: {RESOURCES}",
        )

    def set_dark_palette(self, dark: bool) -> None:
        from app.ui.theme import apply_palette

        app = QApplication.instance()
        if app is not None:
            apply_palette(app, "dark" if dark else "light")
        QSettings().setValue("ui/palette", "dark" if dark else "light")

    # ------------------------------------------------------------------ persistence
    def _restore_settings(self) -> None:
        settings = QSettings()
        palette = settings.value("ui/palette", self.manager.config.ui.palette)
        self.dark_action.setChecked(palette == "dark")
        if not self._restore_geometry(settings):
            self._first_run_layout()
        self._default_state = None

    def _first_run_layout(self, short: bool | None = None) -> None:
        """1366×768 first (issue #19): on a short screen the device view shares a tabbed dock with the
        values, so every clinically used value is on screen; the Commands frame gets the larger share
        of the right column. Taller screens keep the four frames side by side."""
        if short is None:
            screen = self.screen().availableGeometry() if self.screen() is not None else None
            short = screen is None or screen.height() < 900
        if short:
            self.tabifyDockWidget(self.docks["ValuesFrame"], self.docks["DeviceView"])
            self.docks["ValuesFrame"].raise_()
        else:
            self.resizeDocks([self.docks["ValuesFrame"], self.docks["DeviceView"]], [65, 35],
                             Qt.Orientation.Vertical)
        self.resizeDocks([self.docks["PlotsFrame"], self.docks["CommandsFrame"]], [45, 55],
                         Qt.Orientation.Vertical)

    def _reset_layout(self, short: bool | None = None) -> None:
        """The first-run layout again (``short``: for a screen under 900 px high; None: this screen)."""
        for title, _m, class_name, area in FRAMES:
            dock = self.docks[class_name]
            dock.setFloating(False)
            self.addDockWidget(area, dock)
            dock.show()
            del title
        self._first_run_layout(short)

    def grab(self, *args: Any) -> QPixmap:
        """The window as a pixmap, with the content of native child windows (the 3D view renders in one
        of its own, which QWidget.grab cannot see) painted in where they are shown."""
        pixmap = super().grab(*args)
        if args:  # a sub-rectangle: as Qt grabs it
            return pixmap
        painter = QPainter(pixmap)
        try:
            for frame in self.frames.values():
                paint = getattr(frame, "paint_native_views", None)
                if callable(paint):
                    paint(painter, self)
        finally:
            painter.end()
        return pixmap

    # ------------------------------------------------------------------ quitting (issue #36)
    def _activity(self) -> str:
        """What quitting would interrupt, in words ("" when nothing runs): a run (an exercise, a script, console
        code). Stimulation alone (the FES panel) stops with the devices' safe state and is not asked about."""
        runs = getattr(self.manager, "runs", None)
        run = runs.current() if runs is not None else None
        if run is not None:
            return f"“{run.title}” is running."
        if getattr(self._script_runner(), "running", False):
            return "A script is running."
        return ""

    def may_quit(self) -> bool:
        """Asked before the window closes (Ctrl+Q, File → Quit, the window's own close button): unsaved edits in
        the Script tab's editor first (Save / Discard / Cancel: never lost without a word), then an exercise or a
        script in progress (End session's question and words). False: the window stays open."""
        console = self._script_console()
        unsaved = getattr(console, "has_unsaved_changes", None)
        if callable(unsaved) and unsaved():
            path = getattr(console, "path", None)
            name = path.name if path is not None else "The script in the Script tab"
            answer = QMessageBox.question(
                self, "Unsaved script", f"{name} has changes that are not saved. Save them before quitting?",
                QMessageBox.StandardButton.Save | QMessageBox.StandardButton.Discard
                | QMessageBox.StandardButton.Cancel, QMessageBox.StandardButton.Save)
            if answer == QMessageBox.StandardButton.Cancel:
                return False
            if answer == QMessageBox.StandardButton.Save and not console.save_file(path):  # type: ignore[union-attr]
                return False  # the save dialog was cancelled, or the file could not be written: stay
        activity = self._activity()
        if activity:
            question = self._stop_question(f"{activity} Stop it{', end the session' if self.manager.recorder else ''}"
                                           " and quit?")
            answer = QMessageBox.question(self, "Quit", question, QMessageBox.StandardButton.Yes
                                          | QMessageBox.StandardButton.No, QMessageBox.StandardButton.No)
            if answer != QMessageBox.StandardButton.Yes:
                return False
        return True

    # ------------------------------------------------------------------ geometry (issue #36)
    def _screen_area(self) -> Any:
        """The available area of the screen the window opens on (QRect), None without a screen."""
        screen = self.screen()
        return screen.availableGeometry() if screen is not None else None

    @staticmethod
    def _screen_key(area: Any) -> str:
        return f"{area.width()}x{area.height()}" if area is not None else "unknown"

    def _restore_geometry(self, settings: QSettings) -> bool:
        """The geometry and layout saved on a screen of this size, when they fit it; else this screen's default
        (the whole screen, maximised). A geometry made on another screen (1272×720 from a 1366×768 laptop on a
        1920×1080 desk, 1011×718 with clipped labels the other way) is never applied here: each screen size
        keeps its own. Returns whether the saved layout (dock state) was restored."""
        area = self._screen_area()
        key = self._screen_key(area)
        geometry = settings.value(f"main/geometry/{key}")
        restored = False
        if geometry is not None and self.restoreGeometry(geometry):
            normal = self.normalGeometry() if self.isMaximized() else self.geometry()
            fits = area is None or (normal.width() <= area.width() and normal.height() <= area.height())
            restored = fits
        if not restored:
            self._default_geometry(area)
            return False
        state = settings.value(f"main/state/{key}")
        return state is not None and self.restoreState(state)

    def _default_geometry(self, area: Any) -> None:
        """First run on this screen: the whole screen (1366×768 laptops and 1920×1080 desks alike), maximised.
        The screen's size as well as "maximised": a window manager maximises (checked under openbox: 1920×1061
        below its title bar); without one (a kiosk X session) nothing would, and the window stayed 1366×768 in a
        corner of a 1920×1080 screen (issue #30)."""
        self.setWindowState(self.windowState() & ~Qt.WindowState.WindowMaximized)
        if area is not None and area.width() >= 1366 and area.height() >= 768:
            self.setGeometry(area)
        else:
            self.resize(1366, 768)
        self.setWindowState(self.windowState() | Qt.WindowState.WindowMaximized)

    def _save_geometry(self, settings: QSettings) -> None:
        """The geometry (with the maximised state) and the layout, under this screen's size."""
        key = self._screen_key(self._screen_area())
        settings.setValue(f"main/geometry/{key}", self.saveGeometry())
        settings.setValue(f"main/state/{key}", self.saveState())

    def closeEvent(self, event: QEvent) -> None:
        if not self._quit_confirmed:
            if not self.may_quit():
                event.ignore()
                return
            self._quit_confirmed = True
        settings = QSettings()
        self._save_geometry(settings)
        for frame in self.frames.values():
            save = getattr(frame, "save_settings", None)
            if callable(save):
                save(settings)
        super().closeEvent(event)
        self.stop_gui_watch()
        self.qt_bus.close()  # the frames' data stops here; the bus forgets the window
        self._tasks_closed = True
        if self._tasks is not None:
            self._tasks.close()  # the worker process ends with the window
        # The main window holds the e-stop: when it closes, the whole application ends (devices safe in
        # run_gui's shutdown). No other window may keep the app — and the devices — running without it.
        self.manager.supervisor.bring_to_safe_state("main window closed")
        app = QApplication.instance()
        if app is not None:
            for widget in app.topLevelWidgets():
                if widget is not self and widget.isVisible():
                    widget.close()
            app.removeEventFilter(self._estop_filter)
            if QThread.currentThread().loopLevel() > 0:  # the app's loop runs (not a test driving the window)
                app.quit()
