"""Finds clipped text in a widget tree: every visible label, button, check box, group-box title, tab,
header section and item-view cell whose text needs more room than it has. A text elided by
:class:`app.ui.widgets.ElidedLabel` counts as clipped unless its tooltip gives the whole text."""

from __future__ import annotations

from PySide6.QtCore import QModelIndex, Qt
from PySide6.QtGui import QFontMetrics, QTextDocument
from PySide6.QtWidgets import (
    QAbstractButton,
    QCheckBox,
    QComboBox,
    QGroupBox,
    QHeaderView,
    QLabel,
    QListWidget,
    QPushButton,
    QRadioButton,
    QStyle,
    QTabBar,
    QTableView,
    QTreeView,
    QWidget,
)

from app.ui.widgets import ElidedLabel

SLACK = 2  # px: rounding between the style's and the font's metrics


def _plain(text: str) -> str:
    return text.replace("&&", "\0").replace("&", "").replace("\0", "&")


def _rich_width(label: QLabel) -> float:
    doc = QTextDocument()
    doc.setDefaultFont(label.font())
    doc.setDocumentMargin(0)
    doc.setHtml(label.text())
    return doc.idealWidth()


def _name(w: QWidget) -> str:
    parts = []
    p: QWidget | None = w
    while p is not None and len(parts) < 4:
        parts.append(p.objectName() or type(p).__name__)
        p = p.parentWidget()
    return "/".join(reversed(parts))


def _shown(w: QWidget) -> bool:
    return w.isVisible() and w.width() > 0 and w.height() > 0 and not w.visibleRegion().isEmpty()


def clipped_texts(root: QWidget, checked: list[int] | None = None) -> list[str]:
    """Descriptions of every clipped text under ``root``; ``checked[0]`` counts the widgets looked at."""
    found: list[str] = []
    for w in [root, *root.findChildren(QWidget)]:
        if not _shown(w):
            continue
        if checked is not None:
            checked[0] += 1
        if isinstance(w, QLabel | QAbstractButton) and (w.text() if hasattr(w, "text") else ""):
            seen = w.visibleRegion().boundingRect()
            if seen.height() + SLACK < w.height() or seen.width() + SLACK < w.width():
                if not _inside_scrolled_list(w):
                    found.append(f"{_name(w)}: {w.text()[:50]!r} partly hidden ({seen.width()}×{seen.height()} "
                                 f"of {w.width()}×{w.height()} shown)")
                    continue
        if isinstance(w, ElidedLabel):
            if w.is_elided() and w.full_text() not in w.toolTip():
                found.append(f"{_name(w)}: elided {w.text()!r} without the whole text in its tooltip")
            continue
        if isinstance(w, QLabel):
            text = w.text()
            if not text or (w.pixmap() is not None and not w.pixmap().isNull()):
                continue
            avail = w.contentsRect().width() - 2 * w.margin() - max(w.indent(), 0) * 0
            if w.wordWrap():
                need_h = w.heightForWidth(w.width())
                if need_h > w.height() + SLACK:
                    found.append(f"{_name(w)}: wrapped text {text[:60]!r} needs {need_h} px height, has {w.height()}")
                continue
            rich = ("<" in text and ">" in text) or w.textFormat() == Qt.TextFormat.RichText
            if rich and w.textFormat() != Qt.TextFormat.PlainText:
                need = _rich_width(w)
            else:
                fm = QFontMetrics(w.font())
                need = max(fm.horizontalAdvance(line) for line in _plain(text).split("\n"))
            if need > avail + SLACK:
                found.append(f"{_name(w)}: {text[:70]!r} needs {need:.0f} px, has {avail}")
            continue
        if isinstance(w, QAbstractButton) and w.text():
            fm = QFontMetrics(w.font())
            need = fm.horizontalAdvance(_plain(w.text()))
            style = w.style()
            if isinstance(w, QCheckBox | QRadioButton):
                ind = style.pixelMetric(QStyle.PixelMetric.PM_IndicatorWidth, None, w)
                need += ind + style.pixelMetric(QStyle.PixelMetric.PM_CheckBoxLabelSpacing, None, w)
            elif isinstance(w, QPushButton):
                need += 2 * style.pixelMetric(QStyle.PixelMetric.PM_ButtonMargin, None, w) // 2
                if not w.icon().isNull():
                    need += w.iconSize().width() + 4
                if w.menu() is not None:
                    need += style.pixelMetric(QStyle.PixelMetric.PM_MenuButtonIndicator, None, w)
            if need > w.width() + SLACK:
                found.append(f"{_name(w)}: button {w.text()!r} needs {need} px, has {w.width()}")
            continue
        if isinstance(w, QGroupBox) and w.title():
            need = QFontMetrics(w.font()).horizontalAdvance(_plain(w.title())) + (24 if w.isCheckable() else 8)
            if need > w.width() + SLACK:
                found.append(f"{_name(w)}: group title {w.title()!r} needs {need} px, has {w.width()}")
            continue
        if isinstance(w, QComboBox) and w.count():
            fm = QFontMetrics(w.font())
            need = fm.horizontalAdvance(w.currentText()) + 28
            if need > w.width() + SLACK:
                found.append(f"{_name(w)}: combo text {w.currentText()!r} needs {need} px, has {w.width()}")
            continue
        if isinstance(w, QTabBar) and w.count():
            if w.sizeHint().width() > w.width() + SLACK and w.shape() in (QTabBar.Shape.RoundedNorth,
                                                                          QTabBar.Shape.RoundedSouth):
                found.append(f"{_name(w)}: tabs need {w.sizeHint().width()} px, have {w.width()} "
                             f"(some hidden behind scroll arrows)")
            fm = QFontMetrics(w.font())
            for i in range(w.count()):
                if fm.horizontalAdvance(_plain(w.tabText(i))) > w.tabRect(i).width():
                    found.append(f"{_name(w)}: tab {w.tabText(i)!r} elided")
            continue
        if isinstance(w, QHeaderView) and w.orientation() == Qt.Orientation.Horizontal:
            model = w.model()
            if model is None:
                continue
            fm = QFontMetrics(w.font())
            for col in range(model.columnCount()):
                if w.isSectionHidden(col) or w.sectionSize(col) == 0:
                    continue
                text = str(model.headerData(col, Qt.Orientation.Horizontal) or "")
                need = fm.horizontalAdvance(text) + 12
                if need > w.sectionSize(col) + SLACK:
                    found.append(f"{_name(w)}: header {text!r} needs {need} px, has {w.sectionSize(col)}")
            continue
        if isinstance(w, QTreeView | QTableView):
            found += _view_items(w)
        elif isinstance(w, QListWidget):
            fm = QFontMetrics(w.font())
            avail = w.viewport().width()
            for i in range(min(w.count(), 200)):
                text = w.item(i).text()
                if fm.horizontalAdvance(text) + 8 > avail + SLACK and text not in w.item(i).toolTip():
                    found.append(f"{_name(w)}: list item {text[:60]!r} clipped without tooltip")
    return found


def _inside_scrolled_list(w: QWidget) -> bool:
    """A widget inside a scroll area meant to scroll (a long list of rows) may be partly shown."""
    p = w.parentWidget()
    while p is not None:
        if p.property("scrolls") is True:
            return True
        p = p.parentWidget()
    return False


def _view_items(view: QTreeView | QTableView) -> list[str]:
    """Every shown cell: its text (plus check box / icon) against the part of its cell on screen."""
    out: list[str] = []
    model = view.model()
    if model is None:
        return out
    fm = QFontMetrics(view.font())
    check = view.style().pixelMetric(QStyle.PixelMetric.PM_IndicatorWidth, None, view) + 6
    vp = view.viewport().rect()
    stack = [QModelIndex()]
    seen = 0
    while stack and seen < 2000:
        parent = stack.pop()
        for row in range(model.rowCount(parent)):
            for col in range(model.columnCount(parent)):
                index = model.index(row, col, parent)
                seen += 1
                rect = view.visualRect(index)
                if rect.isEmpty() or not rect.intersects(vp):
                    continue
                text = str(model.data(index, Qt.ItemDataRole.DisplayRole) or "")
                if not text:
                    continue
                need = fm.horizontalAdvance(text.split("\n")[0]) + 6
                if model.data(index, Qt.ItemDataRole.CheckStateRole) is not None:
                    need += check
                if model.data(index, Qt.ItemDataRole.DecorationRole) is not None:
                    need += view.iconSize().width() + 4 if view.iconSize().width() > 0 else 20
                room = min(rect.right(), vp.right()) - max(rect.left(), vp.left())
                tip = str(model.data(index, Qt.ItemDataRole.ToolTipRole) or "")
                if need > room + SLACK and text not in tip:  # elided, and the tooltip does not say it
                    out.append(f"{_name(view)}: cell {text[:40]!r} needs {need} px, has {room}")
            if isinstance(view, QTreeView) and view.isExpanded(model.index(row, 0, parent)):
                stack.append(model.index(row, 0, parent))
    return out


# The smallest useful sizes of widgets that show data (issue #30: panes squashed so far they showed
# nothing). A table or tree shows at least MIN_VIEW_ROWS rows (or all it has); a graph is as tall as the
# plots frame's own pane minimum; any other plot at least MIN_PLOT_PX high and wide.
MIN_VIEW_ROWS = 3
MIN_PLOT_PX = 80


def squashed_data_widgets(root: QWidget, checked: list[int] | None = None) -> list[str]:
    """Every visible data view in ``root`` smaller than its minimum useful size, as readable lines."""
    import pyqtgraph as pg

    from app.ui.plots_frame import MIN_PANE_HEIGHT_PX, PlotsFrame

    found: list[str] = []
    seen = 0
    for view in root.findChildren(QTableView) + root.findChildren(QTreeView):
        if not _shown(view) or view.model() is None:
            continue
        rows = view.model().rowCount()
        if rows == 0:
            continue
        seen += 1
        need = min(rows, MIN_VIEW_ROWS)
        row_h = view.rowHeight(0) if isinstance(view, QTableView) else view.rowHeight(view.model().index(0, 0))
        visible = view.viewport().visibleRegion().boundingRect().height()
        if row_h > 0 and visible + SLACK < need * row_h:
            found.append(f"{_name(view)}: shows {visible // max(1, row_h)} of {rows} rows "
                         f"({visible} px, needs {need * row_h})")
    panes = {id(p) for f in root.findChildren(PlotsFrame) for p in f.plots.values()}
    for widget in root.findChildren(pg.GraphicsView):
        if not _shown(widget):
            continue
        for item in widget.scene().items():
            if not isinstance(item, pg.PlotItem) or not item.isVisible():
                continue
            seen += 1
            h, w = item.size().height(), item.size().width()
            minimum = MIN_PANE_HEIGHT_PX if id(item) in panes else MIN_PLOT_PX
            if h + SLACK < minimum or w + SLACK < MIN_PLOT_PX:
                title = item.getAxis("left").labelText or item.titleLabel.text or "plot"
                found.append(f"{_name(widget)}: plot {title!r} is {w:.0f}×{h:.0f} px (needs height {minimum})")
    if checked is not None:
        checked[0] += seen
    return found
