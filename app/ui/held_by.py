""""Robot held by: Trigger reaching": who owns a device now (one owner during a run, issue #36), where its
commands are given (the Robot, Assistance and FES tabs).
Follows the journal's lease records (the window's adapter's ``lease_changed``)."""

from __future__ import annotations

from typing import Any

from PySide6.QtWidgets import QWidget

from app.core.ownership import DEVICE_WORDS, ROBOT, STIMULATOR
from app.ui.alarms_panel import LinesLabel
from app.ui.qt_bus import shared_qt_bus

_WHAT = {ROBOT: "its target, mode and gains are the run's: the buttons here are refused until it ends",
         STIMULATOR: "its profile, start and pulse width are the run's: Stop and lowering a scale still work"}


def held_text(supervisor: Any, device: str, what: str = "") -> str:
    """The sentence for ``device`` ("" when nobody holds it); ``what``: what it means where it is shown."""
    lease = supervisor.lease(device) if hasattr(supervisor, "lease") else None
    if lease is None:
        return ""
    name = DEVICE_WORDS[device].removeprefix("the ").capitalize()
    composed = [c for c in lease.compose if c.device == device]
    extra = ""
    if composed:
        parts = []
        for c in composed:
            within = f" within {c.range_m[0]:.2f}–{c.range_m[1]:.2f} m" if c.range_m else ""
            parts.append(f"{c.source} sets the {c.sets.replace('_', ' ')}{within}")
        extra = " (" + "; ".join(parts) + ")"
    return f"{name} held by: {lease.holder}{extra} — {what or _WHAT[device]}."


class HeldByLabel(LinesLabel):
    """Two lines at most naming the device's holder (the rest in its tooltip); hidden when nobody holds it. No
    height-for-width: it sits in scrolling panels (app.ui.alarms_panel.LinesLabel)."""

    def __init__(self, supervisor: Any, device: str, parent: QWidget | None = None, what: str = "") -> None:
        super().__init__(2, parent)
        self.supervisor = supervisor
        self.device = device
        self.what = what
        self.setObjectName(f"heldBy_{device}")
        self.setStyleSheet("QLabel { background: #fff3cd; color: #5c4400; border: 1px solid #e0c060; "
                           "border-radius: 3px; padding: 1px 4px; }")
        bus = getattr(supervisor, "bus", None)
        if bus is not None:  # the holder changes as the journal says (the window's adapter)
            shared_qt_bus(bus).lease_changed.connect(self.refresh)
        self.refresh()

    def refresh(self) -> None:
        text = held_text(self.supervisor, self.device, self.what)
        self.set_full_text(text, text)
        self.setAccessibleName(text or f"{DEVICE_WORDS[self.device]} is free")
        self.setVisible(bool(text))
