"""The electrode set-up dialog (issue #32): for one muscular district, test each candidate electrode
combination with ramped bursts while the robot holds the arm, plot the response against the current, propose
the combination with the largest response per mA, and save the therapist's choice in the patient's profile.

The procedure itself is app.therapy.electrodes.ElectrodeSetup (Qt-free); it runs on a worker thread and reports here
through a queued signal. Stop (and the emergency stop, which the procedure watches) end it at once.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import pyqtgraph as pg
from PySide6.QtCore import QObject, Qt, Signal
from PySide6.QtWidgets import (
    QAbstractItemView,
    QComboBox,
    QDialog,
    QDoubleSpinBox,
    QFormLayout,
    QGroupBox,
    QHBoxLayout,
    QHeaderView,
    QLabel,
    QProgressBar,
    QPushButton,
    QSpinBox,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from app.archive.station import save_choice_record
from app.core import streams
from app.core.ownership import ROBOT, SETUP_SOURCES, STIMULATOR, Lease
from app.manager import LinarmppManager
from app.safety.supervisor import SafetyError
from app.therapy.electrodes import (
    DISCOMFORT_MAX,
    BurstResult,
    ElectrodeSetup,
    SetupPlan,
    SetupResult,
    app_ports,
    choice_event,
    choice_for,
    districts_from_config,
)
from app.wire.sciencemode import MAX_CURRENT_MA, MAX_PULSE_WIDTH_US

log = logging.getLogger(__name__)

SETUP_SOURCE = SETUP_SOURCES[0]
SETUP_LEASE_KEY = "electrode-setup"


def setup_lease() -> Lease:
    """What the set-up holds while it runs: the robot (it holds the arm) and the stimulator (its bursts)."""
    return Lease(key=SETUP_LEASE_KEY, holder="Electrode set-up", devices=frozenset({ROBOT, STIMULATOR}),
                 sources=SETUP_SOURCES)

COLUMNS = ("Ch", "Electrodes", "Up to mA", "Threshold mA", "Response N/mA", "Best N", "Discomfort 0–10")
# One colour per combination, distinguishable in print and for the common colour deficiencies (Okabe–Ito).
CURVE_COLOURS = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#56B4E9", "#D55E00", "#F0E442", "#000000")
NOT_RATED = -1  # the discomfort spin box's special value


class _Relay(QObject):
    """Carries the worker's progress to the GUI thread (a queued connection)."""

    progress = Signal(str, object)


class ElectrodeSetupDialog(QDialog):
    def __init__(self, manager: LinarmppManager, parent: QWidget | None = None, district: str | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Electrode set-up")
        self.manager = manager
        self.districts = districts_from_config(manager.config.devices.fes.electrodes)
        self.setup: ElectrodeSetup | None = None
        self.result: SetupResult | None = None
        self._thread: threading.Thread | None = None
        self._previous_profile: Any = None
        self._relay = _Relay(self)
        self._relay.progress.connect(self._on_progress, Qt.ConnectionType.QueuedConnection)
        self._curves: dict[int, Any] = {}
        self._total = 0

        self.district_box = QComboBox()
        self.district_box.addItems(list(self.districts))
        if district in self.districts:
            self.district_box.setCurrentText(district)
        self.ceiling = QDoubleSpinBox()
        self.ceiling.setRange(1.0, float(MAX_CURRENT_MA))
        self.ceiling.setDecimals(0)
        self.ceiling.setSuffix(" mA")
        self.ceiling.setValue(min(30.0, manager.config.safety.fes.max_current_ma))
        self.ceiling.setToolTip("The highest test current; the patient's caps lower it per channel")
        self.start_ma = QDoubleSpinBox()
        self.start_ma.setRange(1.0, 60.0)
        self.start_ma.setDecimals(0)
        self.start_ma.setSuffix(" mA")
        self.start_ma.setValue(6.0)
        self.step_ma = QDoubleSpinBox()
        self.step_ma.setRange(1.0, 10.0)
        self.step_ma.setDecimals(0)
        self.step_ma.setSuffix(" mA")
        self.step_ma.setValue(2.0)
        self.pulse_width = QSpinBox()
        self.pulse_width.setRange(50, MAX_PULSE_WIDTH_US)
        self.pulse_width.setSingleStep(10)
        self.pulse_width.setSuffix(" µs")
        self.pulse_width.setValue(250)
        form = QFormLayout()
        form.addRow("District", self.district_box)
        form.addRow("Ceiling", self.ceiling)
        form.addRow("From", self.start_ma)
        form.addRow("Step", self.step_ma)
        form.addRow("Pulse width", self.pulse_width)
        settings = QGroupBox("Test bursts")
        settings.setLayout(form)

        self.start_button = QPushButton("&Start set-up")
        self.stop_button = QPushButton("S&top")
        self.stop_button.setStyleSheet("QPushButton { font-weight: bold; }")
        self.stop_button.setEnabled(False)
        self.progress = QProgressBar()
        self.progress.setFormat("%v of %m bursts")
        self.status = QLabel("The robot holds the arm still during the set-up (LINarm ON, position hold).")
        self.status.setWordWrap(True)
        left = QVBoxLayout()
        left.addWidget(settings)
        row = QHBoxLayout()
        row.addWidget(self.start_button)
        row.addWidget(self.stop_button)
        left.addLayout(row)
        left.addWidget(self.progress)
        left.addWidget(self.status)
        left.addStretch(1)

        self.plot = pg.PlotWidget()
        self.plot.setBackground("w")
        self.plot.showGrid(x=True, y=True, alpha=0.3)
        for side in ("bottom", "left"):  # dark axes and text on the white plot: readable when printed too
            axis = self.plot.getAxis(side)
            axis.setPen(pg.mkPen("#444444"))
            axis.setTextPen(pg.mkPen("#222222"))
        self.plot.setLabel("bottom", "Test current", units="mA")
        self.plot.setLabel("left", "Response: interaction force", units="N")
        self.plot.addLegend(offset=(10, 10), labelTextColor="#222222", brush=pg.mkBrush(255, 255, 255, 220))
        self.plot.setMinimumSize(420, 260)

        self.table = QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(list(COLUMNS))
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        header = self.table.horizontalHeader()
        header.setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(1, QHeaderView.ResizeMode.Stretch)
        self.table.verticalHeader().setDefaultSectionSize(self.table.fontMetrics().lineSpacing() + 10)
        # Every combination of a district in view at once (four, the configured arrays): the plot gives way first.
        rows = max((len(d.combinations) for d in self.districts.values()), default=4)
        self.table.setMinimumHeight(self.table.horizontalHeader().sizeHint().height()
                                    + rows * self.table.verticalHeader().defaultSectionSize()
                                    + 2 * self.table.frameWidth() + 4)

        self.proposal_label = QLabel("")
        self.proposal_label.setWordWrap(True)
        self.accept_button = QPushButton("&Accept proposal")
        self.pick_button = QPushButton("Use &selected instead")
        self.close_button = QPushButton("Close")
        for b in (self.accept_button, self.pick_button):
            b.setEnabled(False)
        choose = QHBoxLayout()
        choose.addWidget(self.proposal_label, 1)
        choose.addWidget(self.accept_button)
        choose.addWidget(self.pick_button)
        choose.addWidget(self.close_button)

        top = QHBoxLayout()
        top.addLayout(left)
        top.addWidget(self.plot, 1)
        lay = QVBoxLayout(self)
        lay.addLayout(top, 5)
        lay.addWidget(self.table, 0)
        lay.addLayout(choose)
        screen = self.screen().availableGeometry() if self.screen() is not None else None
        if screen is not None:  # as tall as the screen allows (at 1366×768 the table showed 2 of 4 rows)
            self.resize(min(1100, screen.width() - 40), min(760, screen.height() - 60))

        self.start_button.clicked.connect(self.start)
        self.stop_button.clicked.connect(lambda: self.stop("Stop pressed in the electrode set-up"))
        self.accept_button.clicked.connect(self.accept_proposal)
        self.pick_button.clicked.connect(self.use_selected)
        self.close_button.clicked.connect(self.close)
        self.district_box.currentTextChanged.connect(lambda _t: self._fill_table())
        self._fill_table()

    # ------------------------------------------------------------------ the procedure
    def plan(self) -> SetupPlan:
        fes = self.manager.config.safety.fes
        return SetupPlan(ceiling_ma=self.ceiling.value(), start_ma=self.start_ma.value(), step_ma=self.step_ma.value(),
                         pulse_width_us=float(self.pulse_width.value()), frequency_hz=fes.frequency_hz)

    def start(self, plan: SetupPlan | None = None) -> bool:
        """Start the set-up of the chosen district (on a worker thread); False with the reason shown when it
        cannot start."""
        if self.running:
            return False
        fes, robot = self.manager.driver(streams.FES), self.manager.driver(streams.LINARM)
        district = self.districts.get(self.district_box.currentText())
        limiter = getattr(self.manager.supervisor, "fes_limiter", None)
        if fes is None or robot is None or limiter is None or district is None:
            self._say("The set-up needs the stimulator, the LINarm and a district in the configuration.", "bad")
            return False
        if getattr(fes, "stimulating", False):
            self._say("Stop the running stimulation first.", "bad")
            return False
        try:
            plan = plan or self.plan()
        except ValueError as exc:
            self._say(str(exc), "bad")
            return False
        supervisor = self.manager.supervisor
        # One owner (#36): the set-up holds the robot and the stimulator while it runs; the assistance's pulse
        # width is taken off, so the bursts go out at the pulse width this dialog shows.
        take = getattr(self.manager, "take_lease", None)
        if callable(take):
            try:
                take(setup_lease())
            except SafetyError as exc:
                self._say(f"{exc.reason[:1].upper()}{exc.reason[1:]}.", "bad")
                return False
        bus = getattr(self.manager, "bus", None)  # the data backbone (#29) when merged; the driver's latest before
        latest = bus.latest if bus is not None else robot.latest
        ports = app_ports(fes, robot.command, latest, supervisor.robot_hold_reason, self._record, district.name,
                          SETUP_SOURCE, bus=bus)
        self._previous_profile = getattr(fes, "profile", None)
        self.setup = ElectrodeSetup(district, plan, limiter.limits, ports,
                                    lambda kind, payload: self._relay.progress.emit(kind, payload))
        self.result = self.setup.result
        self._reset_plot()
        self._fill_table()
        self._total = sum(len(plan.ladder(r.ceiling_ma)) for r in self.result.combinations)
        self.progress.setRange(0, max(1, self._total))
        self.progress.setValue(0)
        self._set_running(True)
        self._say(f"Testing {district.name}: {len(district.combinations)} combinations, {self._total} bursts.", "")
        self._thread = threading.Thread(target=self._run, name="electrode-setup", daemon=True)
        self._thread.start()
        return True

    def _run(self) -> None:
        setup = self.setup
        assert setup is not None
        try:
            setup.run()
        except Exception as exc:  # a bug must not leave the arm held silently
            log.exception("electrode set-up failed")
            setup.result.aborted = f"the set-up failed: {exc}"
            self._relay.progress.emit("aborted", setup.result)
        finally:
            setup.ports.close()  # the run closes it; a run that failed before its own end may not have
            self._restore_profile()
            release = getattr(self.manager, "release_lease", None)
            if callable(release):
                release(SETUP_LEASE_KEY, setup.result.aborted or "finished")
            self._relay.progress.emit("ended", None)

    def show_result(self, result: SetupResult) -> None:
        """Show a finished set-up (its curves, table and proposal) without running one."""
        if self.running:
            return
        self.result = result
        self.district_box.setCurrentText(result.district.name)
        self._reset_plot()
        for r in result.combinations:
            for burst in r.bursts:
                self._add_point(burst)
        total = sum(len(r.bursts) for r in result.combinations)
        self.progress.setRange(0, max(1, total))
        self.progress.setValue(total)
        self._fill_table()
        self._show_proposal()
        self._say(f"{result.district.name}: {total} test bursts" + (f", ended early: {result.aborted}"
                                                                      if result.aborted else ", complete."), "")

    def _restore_profile(self) -> None:
        fes, previous = self.manager.driver(streams.FES), self._previous_profile
        if fes is None or previous is None or getattr(fes, "stimulating", False):
            return
        try:
            fes.load_profile(previous, SETUP_SOURCE)
        except Exception as exc:
            log.warning("electrode set-up: the previous profile could not be loaded again: %s", exc)

    def stop(self, reason: str = "Stop pressed in the electrode set-up") -> None:
        if self.setup is not None:
            self.setup.stop(reason)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def wait(self, timeout_s: float) -> bool:
        if self._thread is not None:
            self._thread.join(timeout_s)
        return not self.running

    def _record(self, kind: str, data: dict[str, Any]) -> None:
        self.manager.record_event(kind, **data)  # the journal: the session's recorder, headless or not, writes it

    # ------------------------------------------------------------------ progress (GUI thread)
    def _on_progress(self, kind: str, payload: Any) -> None:
        if kind == "burst":
            self._add_point(payload)
            self.progress.setValue(self.progress.value() + 1)
            self._fill_table()
        elif kind == "combination":
            self._say(f"Channel {payload.combination.channel} done: ask the patient for a discomfort rating "
                      "(0–10) and enter it in the table.", "")
        elif kind == "finished":
            self._show_proposal()
            self._say("Set-up complete.", "ok")
        elif kind == "aborted":
            self._show_proposal()
            self._say(f"Set-up ended early: {payload.aborted}", "bad")
        elif kind == "ended":
            if self._thread is not None:
                self._thread.join(1.0)
            self._set_running(False)
            self._fill_table()

    def _reset_plot(self) -> None:
        self.plot.clear()
        self._curves.clear()
        if self.result is None:
            return
        for i, r in enumerate(self.result.combinations):
            colour = CURVE_COLOURS[i % len(CURVE_COLOURS)]
            self._curves[r.combination.channel] = self.plot.plot(
                [], [], pen=pg.mkPen(colour, width=2), symbol="o", symbolSize=7, symbolBrush=colour,
                name=f"ch {r.combination.channel} ({r.combination.electrodes})" if r.combination.electrodes
                else f"ch {r.combination.channel}")

    def _add_point(self, burst: BurstResult) -> None:
        if self.result is None:
            return
        combo = self.result.combination(burst.channel)
        curve = self._curves.get(burst.channel)
        if combo is not None and curve is not None:
            curve.setData([b.current_ma for b in combo.bursts], [b.response_n for b in combo.bursts])

    def _fill_table(self) -> None:
        district = self.districts.get(self.district_box.currentText())
        result = self.result if self.result is not None and district is not None \
            and self.result.district.name == district.name else None
        combos = result.combinations if result is not None else []
        rows = len(combos) if result is not None else len(district.combinations) if district else 0
        self.table.setRowCount(rows)
        plan = result.plan if result is not None else None
        proposed = result.proposal.channel if result is not None and result.proposal is not None else None
        for row in range(rows):
            if result is not None and plan is not None:
                r = combos[row]
                combo = r.combination
                threshold = r.motor_threshold_ma(plan.detect_n)
                eff = r.response_per_ma(plan.detect_n)
                best = max((b.response_n for b in r.bursts), default=None)
                cells = [str(combo.channel), combo.electrodes + ("  ← proposed" if combo.channel == proposed else ""),
                         f"{r.ceiling_ma}" + ("" if r.ceiling_reason == "the therapist's ceiling" else " (cap)"),
                         "—" if threshold is None else f"{threshold}", f"{eff:.3f}" if eff > 0 else "—",
                         "—" if best is None else f"{best:.1f}"]
            else:
                combo = district.combinations[row]  # type: ignore[union-attr]
                cells = [str(combo.channel), combo.electrodes, "", "", "", ""]
            for col, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setTextAlignment(Qt.AlignmentFlag.AlignCenter if col != 1 else
                                      Qt.AlignmentFlag.AlignLeft | Qt.AlignmentFlag.AlignVCenter)
                self.table.setItem(row, col, item)
            spin = self.table.cellWidget(row, len(COLUMNS) - 1)
            if not isinstance(spin, QSpinBox) or spin.property("channel") != combo.channel:
                spin = QSpinBox()
                spin.setRange(NOT_RATED, DISCOMFORT_MAX)
                spin.setSpecialValueText("not rated")
                spin.setValue(NOT_RATED)
                spin.setProperty("channel", combo.channel)
                spin.setAccessibleName(f"Discomfort for channel {combo.channel}")
                spin.valueChanged.connect(lambda v, ch=combo.channel: self._rated(ch, v))
                self.table.setCellWidget(row, len(COLUMNS) - 1, spin)

    def _rated(self, channel: int, value: int) -> None:
        if self.result is None:
            return
        combo = self.result.combination(channel)
        if combo is None:
            return
        combo.discomfort = None if value == NOT_RATED else int(value)
        self._record("electrode_discomfort", {"district": self.result.district.name, "channel": channel,
                                              "discomfort": combo.discomfort})
        if not self.running and self.result.proposal is not None:
            self.result.repropose()
            self._show_proposal()
            self._fill_table()

    def _show_proposal(self) -> None:
        result = self.result
        if result is None:
            return
        proposal = result.proposal or result.repropose()
        has = proposal.channel is not None
        self.proposal_label.setText(("Proposed: " if has else "No proposal: ") + proposal.reason)
        self.accept_button.setEnabled(has and not self.running)
        self.pick_button.setEnabled(any(r.bursts for r in result.combinations) and not self.running)

    # ------------------------------------------------------------------ the choice
    def accept_proposal(self) -> bool:
        if self.result is None or self.result.proposal is None or self.result.proposal.channel is None:
            return False
        return self.choose(self.result.proposal.channel)

    def use_selected(self) -> bool:
        rows = self.table.selectionModel().selectedRows()
        if self.result is None or not rows:
            self._say("Select a combination in the table first.", "bad")
            return False
        return self.choose(self.result.combinations[rows[0].row()].combination.channel)

    def choose(self, channel: int) -> bool:
        """Make ``channel`` the district's combination: in the patient's profile (saved), for the stimulator's
        district profiles from now on, and in the session record."""
        result, manager = self.result, self.manager
        if result is None or self.running:
            return False
        operator = manager.operator or "unknown operator"
        recorder = manager.recorder
        session = recorder.folder.name if recorder is not None and getattr(recorder, "folder", None) else ""
        profile = manager.patient_profile
        saved = ""
        try:
            if profile is not None:
                # this district's choice only, onto the archive's record as it is now (#39); what changed since
                # the session started (a lowered cap) applies too (#36)
                record = save_choice_record(result, channel, profile, operator, session, manager.config.safety,
                                            expected_version=getattr(manager, "patient_version", 0))
                profile = record.profile
                update = getattr(manager, "update_session_profile", None)
                if not (callable(update) and update(profile, record.version)):
                    manager.patient_profile = profile
                    manager.patient_version = record.version
                channels = profile.fes.district_channels()
                saved = f"saved in {profile.patient_id}'s profile"
            else:
                channels = {result.district.name: channel}
                saved = "not saved: this patient has no profile file (Patients menu); it applies until the app closes"
            choice = choice_for(result, channel, operator, session)
        except Exception as exc:
            self._say(f"The choice could not be saved: {exc}", "bad")
            return False
        fes = manager.driver(streams.FES)
        set_channels = getattr(fes, "set_district_channels", None)
        if callable(set_channels):
            current = dict(getattr(fes, "district_channels", {}) or {})
            set_channels({**current, **channels})
        self._record("electrode_choice", {**choice_event(result, choice), "saved": profile is not None})
        self._say(f"{result.district.name}: channel {channel} chosen, {saved}.", "ok")
        return True

    # ------------------------------------------------------------------ misc
    def _set_running(self, running: bool) -> None:
        self.start_button.setEnabled(not running)
        self.stop_button.setEnabled(running)
        for w in (self.district_box, self.ceiling, self.start_ma, self.step_ma, self.pulse_width):
            w.setEnabled(not running)
        if running:
            self.accept_button.setEnabled(False)
            self.pick_button.setEnabled(False)
        else:
            self._show_proposal()

    def _say(self, text: str, tone: str) -> None:
        colour = {"bad": "#b00020", "ok": "#1b5e20"}.get(tone, "")
        self.status.setStyleSheet(f"color: {colour};" if colour else "")
        self.status.setText(text)

    def closeEvent(self, event: Any) -> None:
        if self.running:
            self.stop("the electrode set-up was closed")
            self.wait(5.0)
        super().closeEvent(event)
