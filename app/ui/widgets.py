"""Small pieces the viewers share."""

from __future__ import annotations

from typing import Any

from PySide6.QtCore import QEvent, QObject, QSize, Qt
from PySide6.QtWidgets import (
    QAbstractSpinBox,
    QApplication,
    QComboBox,
    QLabel,
    QProxyStyle,
    QSizePolicy,
    QSlider,
    QStyle,
    QStyleOptionSlider,
    QWidget,
)


def on_screen(widget: QWidget) -> bool:
    """True when some of ``widget`` can be seen: shown (not on a hidden tab, in a closed dock or a
    closed window), its window not minimised, and not clipped away entirely (scrolled out, squeezed
    to nothing). The live views' timers skip their drawing otherwise: the GUI thread must keep idle
    time for the emergency stop, and a view nobody sees is not worth a paint. They catch up when shown."""
    if not widget.isVisible() or widget.window().isMinimized():
        return False
    return not widget.visibleRegion().isEmpty()


class RefreshWhenVisible:
    """Mixin for a live view with a ``refresh()`` driven by a timer connected to ``_tick``: no work
    while nobody can see it, and it catches up at once when shown again. While hidden (another tab,
    a closed dock, a minimised window) its timer (the attribute named by ``refresh_timer_attr``) is
    stopped: a dozen hidden views ticking 10-30 times a second each woke the GUI thread for nothing."""

    refresh_timer_attr = "timer"

    def _tick(self) -> None:
        if on_screen(self):  # type: ignore[arg-type]
            self.refresh()  # type: ignore[attr-defined]

    def hideEvent(self, event: Any) -> None:
        super().hideEvent(event)  # type: ignore[misc]
        timer = getattr(self, self.refresh_timer_attr, None)
        if timer is not None and timer.isActive():
            timer.stop()
            self._timer_stopped_hidden = True

    def showEvent(self, event: Any) -> None:
        super().showEvent(event)  # type: ignore[misc]
        if getattr(self, "_timer_stopped_hidden", False):
            self._timer_stopped_hidden = False
            getattr(self, self.refresh_timer_attr).start()
        self.refresh()  # type: ignore[attr-defined]


class LabelBoard:
    """A set of value labels by key that are only touched when their text or colour changes: a style
    sheet re-polishes the widget, far too slow for dozens of labels at 20 Hz. Mixed into a viewer that
    fills ``self.values``."""

    values: dict[str, QLabel]

    def _set(self, key: str, text: str, colour: str) -> None:
        shown = self.__dict__.setdefault("_shown", {})
        if shown.get(key) == (text, colour):
            return
        shown[key] = (text, colour)
        label = self.values[key]
        label.setText(text)
        label.setStyleSheet(f"color: {colour};")
        label.setAccessibleName(text)

    def text_of(self, key: str) -> str:
        """The text shown for ``key``."""
        return self.values[key].text()


class ElidedLabel(QLabel):
    """A one-line plain-text label that elides its end when narrower than its text, and then shows the
    whole text as its tooltip (the only acceptable clipping: where the room truly cannot grow).
    ``full_text()`` is the text it was given; the clipping test reads it."""

    def __init__(self, text: str = "", parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self._full = ""
        self._tip = ""
        self.setTextFormat(Qt.TextFormat.PlainText)
        self.setSizePolicy(QSizePolicy.Policy.Ignored, QSizePolicy.Policy.Preferred)
        self.setMinimumWidth(40)
        self.set_full_text(text)

    def set_full_text(self, text: str, tooltip: str = "") -> None:
        """Show ``text`` (elided when needed); ``tooltip`` is shown always (else the text when elided)."""
        if text == self._full and tooltip == self._tip:
            return
        self._full = text
        self._tip = tooltip
        self.setAccessibleName(text)
        self._elide()

    def full_text(self) -> str:
        return self._full

    def is_elided(self) -> bool:
        return self.text() != self._full

    def sizeHint(self) -> QSize:
        hint = super().sizeHint()
        return QSize(self.fontMetrics().horizontalAdvance(self._full) + 8, hint.height())

    def resizeEvent(self, event: Any) -> None:
        super().resizeEvent(event)
        self._elide()

    def changeEvent(self, event: Any) -> None:
        super().changeEvent(event)
        if event.type() in (QEvent.Type.FontChange, QEvent.Type.StyleChange):
            self._elide()

    def _elide(self) -> None:
        width = self.contentsRect().width() - 2 * self.margin()
        shown = self.fontMetrics().elidedText(self._full, Qt.TextElideMode.ElideRight, max(width, 0))
        if shown != self.text():
            super().setText(shown)
        tip = self._tip or (self._full if shown != self._full else "")
        if tip != self.toolTip():
            self.setToolTip(tip)


class StepSlider(QSlider):
    """A horizontal slider for a value that drives motion or stimulation, that never jumps: a click
    on the groove changes nothing (no page jump), the handle drags relative to where it was taken and
    at most ``max_step`` per mouse event, the wheel one single step per notch, PgUp/PgDn one page
    (= ``max_step``), Home/End at most ``max_step``. Typing into a companion spin box stays the way to
    set a far value deliberately."""

    def __init__(self, max_step: int, parent: QWidget | None = None) -> None:
        super().__init__(Qt.Orientation.Horizontal, parent)
        self.max_step = max_step
        self.setPageStep(max_step)
        self._drag: tuple[float, int] | None = None  # x at the press, value at the press

    def _handle_rect(self) -> Any:
        opt = QStyleOptionSlider()
        self.initStyleOption(opt)
        return self.style().subControlRect(QStyle.ComplexControl.CC_Slider, opt,
                                           QStyle.SubControl.SC_SliderHandle, self)

    def _step_to(self, target: int) -> None:
        v = self.value()
        target = max(v - self.max_step, min(v + self.max_step, target))
        self.setValue(max(self.minimum(), min(self.maximum(), target)))

    def mousePressEvent(self, event: Any) -> None:
        if event.button() == Qt.MouseButton.LeftButton and self._handle_rect().contains(event.position().toPoint()):
            self._drag = (event.position().x(), self.value())
            self.setSliderDown(True)
        event.accept()  # the groove: nothing

    def mouseMoveEvent(self, event: Any) -> None:
        if self._drag is None:
            event.accept()
            return
        x0, v0 = self._drag
        span = max(1, self.width() - self._handle_rect().width())
        self._step_to(v0 + round((event.position().x() - x0) / span * (self.maximum() - self.minimum())))
        event.accept()

    def mouseReleaseEvent(self, event: Any) -> None:
        if self._drag is not None:
            self._drag = None
            self.setSliderDown(False)
        event.accept()

    def wheelEvent(self, event: Any) -> None:
        delta = event.angleDelta().y()
        self._step_to(self.value() + (self.singleStep() if delta > 0 else -self.singleStep() if delta < 0 else 0))
        event.accept()

    def keyPressEvent(self, event: Any) -> None:
        key = event.key()
        steps = {Qt.Key.Key_Home: self.minimum() - self.value(), Qt.Key.Key_End: self.maximum() - self.value(),
                 Qt.Key.Key_PageUp: self.pageStep(), Qt.Key.Key_PageDown: -self.pageStep()}
        if key in steps:
            self._step_to(self.value() + steps[key])
            event.accept()
            return
        super().keyPressEvent(event)  # arrows: one single step


class ClickToPositionStyle(QProxyStyle):
    """For a slider that only shows where one is (a replay's position): a click puts the handle
    where the click was, instead of a page jump towards it."""

    def styleHint(self, hint: Any, option: Any = None, widget: Any = None, data: Any = None) -> int:
        if hint == QStyle.StyleHint.SH_Slider_AbsoluteSetButtons:
            return int(Qt.MouseButton.LeftButton.value)
        return super().styleHint(hint, option, widget, data)


class WheelGuard(QObject):
    """Application-wide: the mouse wheel over a number box or a drop-down list (every QSpinBox, QDoubleSpinBox,
    QComboBox) changes its value only while it has the keyboard focus (clicked or tabbed into). Otherwise the
    wheel scrolls the form around it, as the clinician meant (#36: scrolling a form changed the values under the
    pointer). Such boxes also no longer take the focus from the wheel alone (StrongFocus, not WheelFocus): the
    first notch over a box would otherwise give it the focus and change it."""

    GUARDED = (QAbstractSpinBox, QComboBox)

    def eventFilter(self, obj: QObject, event: QEvent) -> bool:
        kind = event.type()
        if kind == QEvent.Type.Polish and isinstance(obj, self.GUARDED):
            if obj.focusPolicy() == Qt.FocusPolicy.WheelFocus:
                obj.setFocusPolicy(Qt.FocusPolicy.StrongFocus)
        elif kind == QEvent.Type.Wheel and isinstance(obj, QWidget):
            box = obj if isinstance(obj, self.GUARDED) else obj.parentWidget()
            if isinstance(box, self.GUARDED) and not _has_focus(box):
                event.ignore()  # not handled here: Qt passes the wheel on to the parent (the form's scroll area)
                return True
        return False


def _has_focus(widget: QWidget) -> bool:
    focus = QApplication.focusWidget()
    return widget.hasFocus() or (focus is not None and widget.isAncestorOf(focus))


def install_wheel_guard(app: QApplication | None = None) -> WheelGuard | None:
    """Install the application's one :class:`WheelGuard` (again: the same one). None without an application."""
    app = app or QApplication.instance()  # type: ignore[assignment]
    if app is None:
        return None
    guard = app.findChild(WheelGuard)
    if guard is None:
        guard = WheelGuard(app)
        app.installEventFilter(guard)
    return guard
