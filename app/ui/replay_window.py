"""A recorded session in the live graphs, with a time slider, play/pause, speed and the event list.

The window owns a private :class:`~app.ui.signal_store.SignalStore` and a
:class:`~app.ui.plots_frame.PlotsFrame` on it, and feeds the store from a
:class:`~app.session.replay.ReplaySource` exactly as drivers feed the live store, so the graphs behave as
if live. Seeking refills the store with the history before the new position.

The sessions browser reads the session in the worker process (issue #37) and hands the window a
:class:`~app.worker.session_data.SessionData`, whose samples are mapped, not copied: opening a 30-minute session
costs the GUI thread milliseconds. The window it opens is *staged*: built a piece per turn of the event loop (the
graphs' frame, then each pane, then their layout, the first screen, the event list a block at a time), each piece
well under the 50 ms the issue allows a turn, so that a therapy running meanwhile keeps its GUI thread.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

from PySide6.QtCore import Qt, QTimer, Signal
from PySide6.QtGui import QCloseEvent, QKeySequence, QPaintEvent, QShortcut
from PySide6.QtWidgets import (
    QComboBox,
    QHBoxLayout,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QPushButton,
    QSlider,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from app.core.bus import SampleBatch
from app.session.recording import RecordedSession
from app.session.replay import ReplaySource
from app.ui.plots_frame import DEFAULT_SIGNALS, PlotsFrame
from app.ui.signal_store import SignalStore, signal_key
from app.ui.staged import Steps
from app.ui.widgets import ClickToPositionStyle
from app.worker.session_data import SessionData

SPEEDS = (0.25, 0.5, 1.0, 2.0, 5.0, 10.0)
_TICK_MS = 33
_SLIDER_STEPS_PER_S = 100  # the slider moves in 10 ms steps
_DEFAULT_PLOTTED = 6  # signals ticked when the window opens
_EVENTS_PER_TURN = 150  # event-list rows added per turn of the event loop (a block and its layout: ~5 ms; 300 took 12)
_SLIDER_MAX = 2**31 - 1  # QSlider's range is a C int
_FIRST_STEP_LATEST_MS = 200  # a staged window's build begins when it is first drawn, or after this at the latest


def _fmt(seconds: float) -> str:
    m, s = divmod(max(0.0, seconds), 60.0)
    return f"{int(m):02d}:{s:06.3f}"


def default_replay_signals(rec: RecordedSession) -> list[str]:
    """What the Replay window opens on: the live graphs' default signals that the session recorded, then other
    measured channels -- never the robot's state codes first (issue #30: it opened on six flat zeros)."""
    recorded = [signal_key(s.name, c.name) for s in rec.streams.values() for c in s.channels]
    chosen = [k for k in DEFAULT_SIGNALS if k in recorded]
    for key in recorded:
        if len(chosen) >= _DEFAULT_PLOTTED:
            break
        if key not in chosen and not key.startswith("linarm.state."):
            chosen.append(key)
    return chosen[:_DEFAULT_PLOTTED]


class ReplayPlots(PlotsFrame):
    """The graphs of a replay: they open on the replay's own signals (``opening``, set just before one is made),
    not on the live graphs' saved choice -- which would build every plot twice, once for each choice. With
    ``tree_later`` (set likewise: a staged window) the signal list is filled by ``fill_tree``, a device per piece."""

    opening: list[str] = []
    tree_later = False

    def _restore_settings(self) -> None:
        super()._restore_settings()
        self._wanted = list(type(self).opening)
        self._tree_later = type(self).tree_later

    def _rebuild_tree(self) -> None:
        if not getattr(self, "_tree_later", False):
            super()._rebuild_tree()

    def fill_tree(self) -> Iterator[None]:
        """The signal list, a device per step."""
        self._tree_later = False
        yield from self.tree_steps()


class ReplayWindow(QWidget):
    """``staged``: the window is built a piece per turn of the event loop, from its first paint on (the graphs'
    frame; each pane, see PlotsFrame.selection_steps; the first screen; the event list), so that opening it never
    holds the GUI thread for more than one piece; its controls work and ``ready`` is emitted once the first screen is
    drawn. Unstaged (the default), it is complete when constructed."""

    ready = Signal()
    plots: ReplayPlots  # staged: made by the first step

    def __init__(self, session: RecordedSession | SessionData | str | Path, history_s: float = 30.0,
                 parent: QWidget | None = None, *, staged: bool = False) -> None:
        super().__init__(parent)
        self.is_ready = False
        self.source = ReplaySource(session.open() if isinstance(session, SessionData) else session)
        rec = self.source.session
        m = rec.manifest
        self.setWindowTitle(f"Replay — {m.get('patient_id', '?')} — {(m.get('start') or {}).get('t_wall', '')[:19]}")
        self.store = SignalStore(history_s=max(history_s, 1.0))
        for spec, device in self.source.specs().values():
            self.store.add_stream(spec, device or None)
        self._initial_signals = default_replay_signals(rec)
        if not staged:
            self._make_plots(staged=False)
        self.speed = 1.0
        self._last_tick = 0.0

        self.play_button = QPushButton("&Play")
        self.play_button.setCheckable(True)
        self.play_button.toggled.connect(self.set_playing)
        self.slider = QSlider(Qt.Orientation.Horizontal)
        self.slider.setAccessibleName("Replay position")
        self._slider_style = ClickToPositionStyle()  # a click seeks there (no page jump); kept alive here
        self.slider.setStyle(self._slider_style)
        self.slider.setRange(0, max(1, min(_SLIDER_MAX, round(self.source.duration * _SLIDER_STEPS_PER_S))))
        self.slider.valueChanged.connect(self._on_slider)
        self.time_label = QLabel()
        self.speed_box = QComboBox()
        self.speed_box.setAccessibleName("Replay speed")
        for s in SPEEDS:
            self.speed_box.addItem(f"{s:g}×", s)
        self.speed_box.setCurrentIndex(SPEEDS.index(1.0))
        self.speed_box.currentIndexChanged.connect(lambda _i: self._set_speed(float(self.speed_box.currentData())))

        self.events = QListWidget()
        self.events.setAccessibleName("Session events")
        # Laid out a batch of rows per turn of the event loop: laid out all at once (Qt's default), every block of
        # rows added re-laid out the whole list, 10-14 ms a turn once it held a thousand events (#37).
        self.events.setLayoutMode(QListWidget.LayoutMode.Batched)
        self.events.setBatchSize(_EVENTS_PER_TURN)
        self._events_left = [e for e in rec.events if isinstance(e.get("t_mono"), int | float)]
        if not staged:
            self._add_events()
        self.events.itemActivated.connect(lambda it: self.seek(float(it.data(Qt.ItemDataRole.UserRole))))

        bar = QHBoxLayout()
        bar.addWidget(self.play_button)
        bar.addWidget(self.slider, 1)
        bar.addWidget(self.time_label)
        bar.addWidget(self.speed_box)
        self.close_button = QPushButton("&Close")
        self.close_button.setToolTip("Close the replay (Esc)")
        self.close_button.clicked.connect(self.close)
        bar.addWidget(self.close_button)
        QShortcut(QKeySequence(Qt.Key.Key_Escape), self, activated=self.close)
        self._split = split = QSplitter(Qt.Orientation.Horizontal)
        # Staged, the graphs' frame is made by the first step: this holds its place in the window drawn first.
        self._plots_spot: QWidget | None = QWidget() if staged else None
        split.addWidget(self.plots if self._plots_spot is None else self._plots_spot)
        split.addWidget(self.events)
        split.setStretchFactor(0, 1)
        split.setSizes([800, 220])
        layout = QVBoxLayout(self)
        layout.addWidget(split, 1)
        layout.addLayout(bar)
        if rec.problems:
            note = QLabel("⚠ " + "; ".join(rec.problems))
            note.setWordWrap(True)
            layout.addWidget(note)

        self.timer = QTimer(self)
        self.timer.setInterval(_TICK_MS)
        self.timer.timeout.connect(self._tick)
        self.resize(1100, 650)
        self._steps: Steps | None = None
        if staged:
            for control in (self.play_button, self.slider, self.speed_box):
                control.setEnabled(False)  # until the first screen is drawn
            self._steps = Steps(self._stage(), self)
            # The first piece once the window has been drawn (paintEvent), so that the window's first paint and the
            # first pane are not one turn; by the timer alone if it is not drawn (hidden, minimised).
            self._steps.start(_FIRST_STEP_LATEST_MS)
        else:
            self._first_screen()

    def _make_plots(self, staged: bool) -> None:
        """The graphs' frame; staged, without panes (selection_steps builds them) and not drawn until they are."""
        ReplayPlots.opening = [] if staged else self._initial_signals
        ReplayPlots.tree_later = staged
        try:
            self.plots = ReplayPlots(None, self.store)
        finally:
            ReplayPlots.tree_later = False
        self.plots.timer.stop()  # redrawn when the replay moves, not on a free-running timer
        if staged:
            self.plots.graphics.setUpdatesEnabled(False)
        self.plots.x_origin = self.source.start  # the x-axis in session time, as the slider and events

    def _stage(self) -> Iterator[None]:
        """The staged build, a piece per step: the graphs' frame, its signal list, the first screen's data, the panes
        one by one, their layout, the first screen drawn; the event list after it, a block per step."""
        self._make_plots(staged=True)
        if self._plots_spot is not None:
            self._split.replaceWidget(0, self.plots)
            self._plots_spot.deleteLater()
            self._plots_spot = None
        yield
        yield from self.plots.fill_tree()  # the signal list
        yield
        # The first screen's data, a piece before the graphs that show them: its samples, then in the store.
        first_screen = self._history_at(self._first_position())
        yield
        self._fill_store(first_screen)
        yield
        yield from self.plots.selection_steps(self._initial_signals)
        self._first_screen(fed=True)  # in the step that lets the graphs be drawn: their first paint shows the data
        while self._events_left:
            yield
            self._add_events(then_next=False)

    def paintEvent(self, event: QPaintEvent) -> None:
        super().paintEvent(event)
        if self._steps is not None and not self._steps.started:
            self._steps.start(0)  # drawn: the build begins at the next turn

    def _first_position(self) -> float:
        return min(self.source.duration, self.plots.history_s)  # open on a full first screen

    def _first_screen(self, fed: bool = False) -> None:
        """The first screen drawn (``fed``: its data are in the store already), the controls on, ``ready``."""
        if fed:
            self._sync_slider()
            self._redraw()
        else:
            self.seek(self._first_position())
        for control in (self.play_button, self.slider, self.speed_box):
            control.setEnabled(True)
        self.is_ready = True
        self.ready.emit()

    def _add_events(self, then_next: bool = True) -> None:
        """The next block of the event list; the rest on the next turn of the event loop (``then_next``)."""
        block, self._events_left = self._events_left[:_EVENTS_PER_TURN], self._events_left[_EVENTS_PER_TURN:]
        for e in block:
            text = f"{_fmt(e['t_mono'] - self.source.start)}  {e.get('kind', '')}  {e.get('who', '')}"
            item = QListWidgetItem(text)
            item.setData(Qt.ItemDataRole.UserRole, float(e["t_mono"]) - self.source.start)
            item.setToolTip(f"{text}\n{e.get('data', '')}")  # the whole line, even when the list is narrow
            self.events.addItem(item)
        if self._events_left and then_next:
            QTimer.singleShot(0, self, self._add_events)

    # ------------------------------------------------------------------ control
    def seek(self, elapsed_s: float) -> None:
        """Show the session as it looked live at ``elapsed_s`` after its start."""
        self._feed(elapsed_s)
        self._sync_slider()
        self._redraw()

    def _feed(self, elapsed_s: float) -> None:
        """The store as it was live at ``elapsed_s``: the history before it."""
        self._fill_store(self._history_at(elapsed_s))

    def _history_at(self, elapsed_s: float) -> dict[str, SampleBatch]:
        """The replay moved to ``elapsed_s``; the samples a live view would hold there."""
        self.source.seek(elapsed_s)
        return self.source.history(self.store.history_s)

    def _fill_store(self, batches: dict[str, SampleBatch]) -> None:
        self.store.clear()
        self.store.feed(batches)

    def set_playing(self, playing: bool) -> None:
        if playing and self.source.at_end:
            self.seek(0.0)
        self.play_button.blockSignals(True)
        self.play_button.setChecked(playing)
        self.play_button.blockSignals(False)
        self.play_button.setText("&Pause" if playing else "&Play")
        if playing:
            self._last_tick = time.monotonic()
            self.timer.start()
        else:
            self.timer.stop()

    @property
    def playing(self) -> bool:
        return self.timer.isActive()

    def step(self, dt_s: float) -> None:
        """Play forward by ``dt_s`` of session time."""
        batches = self.source.advance(dt_s)
        if batches:
            self.store.feed(batches)
        self._sync_slider()
        self._redraw()
        if self.source.at_end:
            self.set_playing(False)

    def _tick(self) -> None:
        now = time.monotonic()
        dt, self._last_tick = (now - self._last_tick) * self.speed, now
        self.step(dt)

    def _set_speed(self, speed: float) -> None:
        self.speed = speed

    def _on_slider(self, value: int) -> None:
        target = value / _SLIDER_STEPS_PER_S
        if abs(target - self.source.elapsed) >= 1.0 / _SLIDER_STEPS_PER_S:
            self.seek(target)

    def _sync_slider(self) -> None:
        self.slider.blockSignals(True)
        self.slider.setValue(round(self.source.elapsed * _SLIDER_STEPS_PER_S))
        self.slider.blockSignals(False)
        self.time_label.setText(f"{_fmt(self.source.elapsed)} / {_fmt(self.source.duration)}")

    def _redraw(self) -> None:
        self.plots._dirty = True
        self.plots.redraw()

    def closeEvent(self, event: QCloseEvent) -> None:
        self.timer.stop()
        if self._steps is not None:
            self._steps.stop()  # the rest of the build is for nobody
        super().closeEvent(event)
