"""The script console (commands frame, tab "Script"): the seed's Linarm++ Manager plugin (D2.2 Fig. 17)
grown up — an editor with Python highlighting and line numbers, open/save, Start/Stop, an output pane
(print output, errors and tracebacks whose line numbers are links into the editor) and an interactive
prompt that runs in the script's namespace, with completion of the API's names and a history.

Scripts and prompt statements run in the script kernel, a child Python process (app.scripting.runner,
app/scripting/kernel.py); completion asks the kernel's live namespace. This widget only drains their output
on a timer, so the window stays responsive whatever the script does — and a script that crashes its process
ends as an error here while the window carries on.
"""

from __future__ import annotations

import collections
import html
import keyword
import re
import time
from pathlib import Path
from typing import Any

from PySide6.QtCore import QRect, QSize, QStringListModel, Qt, QTimer, QUrl, Signal
from PySide6.QtGui import (
    QColor,
    QFont,
    QFontDatabase,
    QKeyEvent,
    QPainter,
    QPaintEvent,
    QResizeEvent,
    QSyntaxHighlighter,
    QTextCharFormat,
    QTextCursor,
    QTextDocument,
    QTextFormat,
)
from PySide6.QtWidgets import (
    QCheckBox,
    QCompleter,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QLineEdit,
    QMessageBox,
    QPlainTextEdit,
    QPushButton,
    QSplitter,
    QTextBrowser,
    QTextEdit,
    QVBoxLayout,
    QWidget,
)

from app.core.config import RESOURCES
from app.scripting.api import API_NAMES
from app.scripting.runner import ScriptResult, ScriptRunner
from app.ui.widgets import ElidedLabel

EXAMPLES_DIR = RESOURCES / "scripts"
_TRACE_LINE = re.compile(r'File "([^"]+)", line (\d+)')
_WORD_BEFORE_CURSOR = re.compile(r"[A-Za-z_][\w.]*$")


START_TIP = "Run the script in the editor (in the script kernel, a process of its own)"
_SOURCE_WORDS = {"exercises_tab": "Exercises tab", "script_tab": "Script tab", "recover": "Recover",
                 "console": "console", "headless": "headless runner", "plan": "therapy plan"}


def _mono_font() -> QFont:
    font = QFontDatabase.systemFont(QFontDatabase.SystemFont.FixedFont)
    font.setPointSize(max(font.pointSize(), 10))
    return font


# ---------------------------------------------------------------------------------------------- highlighting

class StatusLabel(ElidedLabel):
    """The run's status beside the buttons: elided (whole in its tooltip) rather than widening the Commands
    frame — "Running trigger_exercise.py — 34 s" pushed the Values frame from 660 to 545 px (issue #30).
    ``setText``/``text`` keep a plain label's interface, on the whole text."""

    def setText(self, text: str) -> None:  # type: ignore[override]
        self.set_full_text(text)

    def text(self) -> str:  # type: ignore[override]
        return self.full_text()

    def _elide(self) -> None:
        width = self.contentsRect().width() - 2 * self.margin()
        shown = self.fontMetrics().elidedText(self.full_text(), Qt.TextElideMode.ElideRight, max(width, 0))
        if shown != QLabel.text(self):
            QLabel.setText(self, shown)
        tip = self.full_text() if shown != self.full_text() else ""
        if tip != self.toolTip():
            self.setToolTip(tip)

    def is_elided(self) -> bool:
        return QLabel.text(self) != self.full_text()

class PythonHighlighter(QSyntaxHighlighter):
    """Keywords, builtins, the script API's objects, strings, numbers and comments."""

    def __init__(self, document: QTextDocument) -> None:
        super().__init__(document)

        def fmt(colour: str, bold: bool = False, italic: bool = False) -> QTextCharFormat:
            f = QTextCharFormat()
            f.setForeground(QColor(colour))
            if bold:
                f.setFontWeight(QFont.Weight.Bold)
            f.setFontItalic(italic)
            return f

        words = r"\b(" + "|".join(keyword.kwlist) + r")\b"
        builtins_ = r"\b(print|range|len|abs|min|max|float|int|str|list|dict|tuple|eval|globals|locals|round|" \
                    r"isinstance|enumerate|zip|sum|sorted|True|False|None|waitCondition|wait)\b"
        api = r"\b(" + "|".join(API_NAMES) + r"|manager)\b"
        self.rules: list[tuple[re.Pattern[str], QTextCharFormat]] = [
            (re.compile(words), fmt("#1f4fbf", bold=True)),
            (re.compile(builtins_), fmt("#7a3e9d")),
            (re.compile(api), fmt("#0b7a3e", bold=True)),
            (re.compile(r"\b[A-Z][A-Z0-9_]{2,}\b"), fmt("#8a5a00")),  # enums and constants
            (re.compile(r"\b\d+(\.\d*)?([eE][-+]?\d+)?\b"), fmt("#b0306a")),
        ]
        self.string_format = fmt("#a33b00")
        self.comment_format = fmt("#6b7a8a", italic=True)
        single = r"'[^'\\\n]*(?:\\.[^'\\\n]*)*'"
        double = r'"[^"\\\n]*(?:\\.[^"\\\n]*)*"'
        self._strings = re.compile(f"({single}|{double})")

    def highlightBlock(self, text: str) -> None:
        for pattern, f in self.rules:
            for m in pattern.finditer(text):
                self.setFormat(m.start(), m.end() - m.start(), f)
        string_spans = []
        for m in self._strings.finditer(text):
            self.setFormat(m.start(), m.end() - m.start(), self.string_format)
            string_spans.append((m.start(), m.end()))
        for m in re.finditer("#", text):
            if not any(a <= m.start() < b for a, b in string_spans):
                self.setFormat(m.start(), len(text) - m.start(), self.comment_format)
                break


# ---------------------------------------------------------------------------------------------- editor
class _LineNumberArea(QWidget):
    def __init__(self, editor: CodeEditor) -> None:
        super().__init__(editor)
        self.editor = editor

    def sizeHint(self) -> QSize:
        return QSize(self.editor.line_number_width(), 0)

    def paintEvent(self, event: QPaintEvent) -> None:
        self.editor.paint_line_numbers(event)


class CodeEditor(QPlainTextEdit):
    """A plain-text editor with line numbers, 4-space indentation and an error-line marker."""

    def __init__(self) -> None:
        super().__init__()
        self.setFont(_mono_font())
        self.setLineWrapMode(QPlainTextEdit.LineWrapMode.NoWrap)
        self.setTabStopDistance(4 * self.fontMetrics().horizontalAdvance(" "))
        self.numbers = _LineNumberArea(self)
        self.highlighter = PythonHighlighter(self.document())
        self.error_line: int | None = None
        self.blockCountChanged.connect(lambda _n: self._update_margin())
        self.updateRequest.connect(self._scroll_numbers)
        self.cursorPositionChanged.connect(self._mark_lines)
        self._update_margin()

    def line_number_width(self) -> int:
        digits = max(3, len(str(self.blockCount())))
        return 10 + self.fontMetrics().horizontalAdvance("9") * digits

    def _update_margin(self) -> None:
        self.setViewportMargins(self.line_number_width(), 0, 0, 0)

    def _scroll_numbers(self, rect: QRect, dy: int) -> None:
        if dy:
            self.numbers.scroll(0, dy)
        else:
            self.numbers.update(0, rect.y(), self.numbers.width(), rect.height())

    def resizeEvent(self, event: QResizeEvent) -> None:
        super().resizeEvent(event)
        cr = self.contentsRect()
        self.numbers.setGeometry(QRect(cr.left(), cr.top(), self.line_number_width(), cr.height()))

    def paint_line_numbers(self, event: QPaintEvent) -> None:
        painter = QPainter(self.numbers)
        palette = self.palette()
        painter.fillRect(event.rect(), palette.alternateBase())
        block = self.firstVisibleBlock()
        number = block.blockNumber()
        top = round(self.blockBoundingGeometry(block).translated(self.contentOffset()).top())
        bottom = top + round(self.blockBoundingRect(block).height())
        height = self.fontMetrics().height()
        while block.isValid() and top <= event.rect().bottom():
            if block.isVisible() and bottom >= event.rect().top():
                is_error = self.error_line == number + 1
                painter.setPen(QColor("#c0392b") if is_error else palette.placeholderText().color())
                painter.drawText(0, top, self.numbers.width() - 5, height, Qt.AlignmentFlag.AlignRight,
                                 str(number + 1))
            block = block.next()
            top = bottom
            bottom = top + round(self.blockBoundingRect(block).height())
            number += 1

    def keyPressEvent(self, event: QKeyEvent) -> None:
        if event.key() == Qt.Key.Key_Tab and not event.modifiers():
            self.insertPlainText("    ")
            return
        if event.key() in (Qt.Key.Key_Return, Qt.Key.Key_Enter):
            line = self.textCursor().block().text()
            indent = line[: len(line) - len(line.lstrip(" "))]
            if line.rstrip().endswith(":"):
                indent += "    "
            super().keyPressEvent(event)
            self.insertPlainText(indent)
            return
        super().keyPressEvent(event)

    def go_to_line(self, line: int) -> None:
        block = self.document().findBlockByNumber(max(0, line - 1))
        cursor = QTextCursor(block)
        self.setTextCursor(cursor)
        self.centerCursor()
        self.setFocus()

    def set_error_line(self, line: int | None) -> None:
        self.error_line = line
        self._mark_lines()
        self.numbers.update()

    def _mark_lines(self) -> None:
        selections = []
        if self.error_line is not None:
            sel = QTextEdit.ExtraSelection()
            sel.format.setBackground(QColor(192, 57, 43, 60))
            sel.format.setProperty(QTextFormat.Property.FullWidthSelection, True)
            sel.cursor = QTextCursor(self.document().findBlockByNumber(self.error_line - 1))
            selections.append(sel)
        self.setExtraSelections(selections)


# ---------------------------------------------------------------------------------------------- prompt
class PromptLine(QLineEdit):
    """One line of the interactive prompt: Enter runs it, Up/Down walk the history, Tab completes."""

    submitted = Signal(str)

    def __init__(self, completions: Any) -> None:
        super().__init__()
        self.setFont(_mono_font())
        self.history: list[str] = []
        self._index = 0
        self._completions = completions
        self.model = QStringListModel(self)
        self.completer = QCompleter(self.model, self)
        self.completer.setCompletionMode(QCompleter.CompletionMode.PopupCompletion)
        self.completer.setCaseSensitivity(Qt.CaseSensitivity.CaseSensitive)
        self.completer.setWidget(self)
        self.completer.activated.connect(self._insert_completion)
        self.returnPressed.connect(self._submit)

    def _submit(self) -> None:
        text = self.text()
        if text.strip() and (not self.history or self.history[-1] != text):
            self.history.append(text)
        self._index = len(self.history)
        self.clear()
        self.submitted.emit(text)

    def keyPressEvent(self, event: QKeyEvent) -> None:
        popup = self.completer.popup()
        if popup.isVisible() and event.key() in (Qt.Key.Key_Return, Qt.Key.Key_Enter, Qt.Key.Key_Tab):
            index = popup.currentIndex()
            if index.isValid():
                self._insert_completion(index.data())
            popup.hide()
            return
        if event.key() == Qt.Key.Key_Tab:
            self.complete()
            return
        if event.key() == Qt.Key.Key_Up and self.history:
            self._index = max(0, self._index - 1)
            self.setText(self.history[self._index])
            return
        if event.key() == Qt.Key.Key_Down and self.history:
            self._index = min(len(self.history), self._index + 1)
            self.setText(self.history[self._index] if self._index < len(self.history) else "")
            return
        super().keyPressEvent(event)

    def focusNextPrevChild(self, _next: bool) -> bool:
        return False  # Tab completes here; it does not move the focus

    def current_word(self) -> str:
        m = _WORD_BEFORE_CURSOR.search(self.text()[: self.cursorPosition()])
        return m.group(0) if m else ""

    def complete(self) -> list[str]:
        """Offer the completions of the word before the cursor; a single one is inserted at once."""
        word = self.current_word()
        options = self._completions(word) if word else []
        if len(options) == 1:
            self._insert_completion(options[0])
        elif options:
            self.model.setStringList(options)
            self.completer.setCompletionPrefix(word)
            self.completer.complete(QRect(0, 0, max(self.width() // 2, 240), self.height()))
        return options

    def _insert_completion(self, completion: str) -> None:
        word = self.current_word()
        pos = self.cursorPosition()
        text = self.text()
        self.setText(text[: pos - len(word)] + completion + text[pos:])
        self.setCursorPosition(pos - len(word) + len(completion))


# ---------------------------------------------------------------------------------------------- console
class ScriptConsole(QWidget):
    """Editor + Start/Stop + output + prompt over one :class:`ScriptRunner` of ``manager``."""

    DRAIN_MS = 50

    def __init__(self, manager: Any) -> None:
        super().__init__()
        self.manager = manager
        self._pending: collections.deque[tuple[str, str]] = collections.deque()
        self.runner = ScriptRunner(manager, self._pending_output)
        self.path: Path | None = None
        self._was_running = False
        self._started_at = 0.0
        self._run: Any = None  # the run this tab started (app.core.runs.ExerciseRun), for its status line
        self._continuation: list[str] = []

        self.open_button = QPushButton("Open…")
        self.save_button = QPushButton("Save")
        self.save_as_button = QPushButton("Save as…")
        self.start_button = QPushButton("▶ Start")
        self.stop_button = QPushButton("■ Stop")
        self.home_first = QCheckBox("Home the robot first")
        self.home_first.setChecked(True)
        self.home_first.setToolTip("Before the script starts, home the LINarm if the controller says it is not homed, "
                                   "and give it back its default stiffness, admittance and assistance")
        self.status = StatusLabel("No script running")
        self.file_label = QLabel("(unsaved script)")
        self.start_button.setToolTip(START_TIP)
        self.stop_button.setToolTip("Stop the script at once; the FES stops and the robot goes to its safe state")
        self.stop_button.setEnabled(False)
        self.start_button.setStyleSheet("QPushButton { font-weight: bold; }")
        self.stop_button.setStyleSheet("QPushButton { font-weight: bold; }")

        bar = QHBoxLayout()
        bar.setContentsMargins(0, 0, 0, 0)
        for w in (self.open_button, self.save_button, self.save_as_button, self.start_button, self.stop_button):
            bar.addWidget(w)
        bar.addWidget(self.home_first)
        self.status.setAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
        bar.addWidget(self.status, 1)  # the room left, and no more: elided beyond it

        self.editor = CodeEditor()
        self.editor.setPlaceholderText(
            "# an exercise script: linarm, physiologicalSensors, fes, patientModel, VRUnity…")
        self.output = QTextBrowser()
        self.output.setFont(_mono_font())
        self.output.setOpenLinks(False)
        self.output.anchorClicked.connect(self._anchor_clicked)
        self.output.document().setMaximumBlockCount(5000)
        self.prompt_label = QLabel(">>>")
        self.prompt_label.setFont(_mono_font())
        self.prompt = PromptLine(self.runner.completions)
        self.prompt.setPlaceholderText("Python in the script's namespace (Tab completes, ↑/↓ history)")
        self.prompt.submitted.connect(self.run_prompt_line)

        bottom = QWidget()
        bl = QVBoxLayout(bottom)
        bl.setContentsMargins(0, 0, 0, 0)
        bl.addWidget(self.output, 1)
        pl = QHBoxLayout()
        pl.addWidget(self.prompt_label)
        pl.addWidget(self.prompt, 1)
        bl.addLayout(pl)
        top = QWidget()
        tl = QVBoxLayout(top)
        tl.setContentsMargins(0, 0, 0, 0)
        tl.addWidget(self.file_label)
        tl.addWidget(self.editor, 1)
        splitter = QSplitter(Qt.Orientation.Vertical)
        splitter.addWidget(top)
        splitter.addWidget(bottom)
        splitter.setStretchFactor(0, 3)
        splitter.setStretchFactor(1, 2)
        lay = QVBoxLayout(self)
        lay.setContentsMargins(2, 2, 2, 2)
        lay.addLayout(bar)
        lay.addWidget(splitter, 1)

        self.open_button.clicked.connect(lambda: self.open_file())
        self.save_button.clicked.connect(lambda: self.save_file(self.path))
        self.save_as_button.clicked.connect(lambda: self.save_file(None))
        self.start_button.clicked.connect(self.start_script)
        self.stop_button.clicked.connect(self.stop_script)
        self.timer = QTimer(self)
        self.timer.setInterval(self.DRAIN_MS)
        self.timer.timeout.connect(self._tick)
        self.timer.start()
        add_hook = getattr(manager, "add_shutdown_hook", None)
        if callable(add_hook):  # closing the application stops a running script (and its callbacks) first
            add_hook(self.runner.close)
        example = EXAMPLES_DIR / "trigger_exercise.py"
        if example.is_file():
            self.load_file(example)

    # ------------------------------------------------------------------ files
    def load_file(self, path: str | Path) -> None:
        path = Path(path)
        self.editor.setPlainText(path.read_text(encoding="utf-8"))
        self.editor.document().setModified(False)
        self.editor.set_error_line(None)
        self.path = path
        self.file_label.setText(str(path))

    def has_unsaved_changes(self) -> bool:
        """Whether the editor holds edits not saved to a file (the window asks before quitting)."""
        return self.editor.document().isModified() and bool(self.editor.toPlainText().strip())

    def open_file(self, path: str | Path | None = None) -> None:
        if path is None:
            start = str(self.path.parent if self.path else EXAMPLES_DIR)
            path, _ = QFileDialog.getOpenFileName(self, "Open a script", start, "Python scripts (*.py);;All files (*)")
            if not path:
                return
        try:
            self.load_file(path)
        except OSError as exc:
            QMessageBox.warning(self, "Open a script", f"Cannot read {path}: {exc}")

    def save_file(self, path: str | Path | None = None) -> bool:
        if path is None:
            start = str(self.path or EXAMPLES_DIR / "exercise.py")
            path, _ = QFileDialog.getSaveFileName(self, "Save the script", start, "Python scripts (*.py)")
            if not path:
                return False
        path = Path(path)
        try:
            path.write_text(self.editor.toPlainText(), encoding="utf-8")
        except OSError as exc:
            QMessageBox.warning(self, "Save the script", f"Cannot write {path}: {exc}")
            return False
        self.path = path
        self.file_label.setText(str(path))
        self.editor.document().setModified(False)
        return True

    # ------------------------------------------------------------------ running
    def hold_reason(self) -> str:
        """Why no script may start now ("" when it may): a latched e-stop or an open STOP alarm (Recover first)."""
        from app.core.ownership import start_problem

        return start_problem(self.runner.manager, ())

    def editor_text(self) -> str:
        """The editor's text now (Recover says whether it differs from what ran)."""
        return self.editor.toPlainText()

    def start_script(self) -> bool:
        if self.runner.running:
            return False
        hold = self.hold_reason()
        if hold:  # nothing recorded: no refused run (#36)
            self._append("stderr", f"Not started: {hold}.\n")
            return False
        self.editor.set_error_line(None)
        filename = str(self.path) if self.path is not None else "<editor>"
        self.runner.home_first = self.home_first.isChecked()
        try:
            self._run = self.runner.start(self.editor.toPlainText(), filename, run_source="script_tab")
        except SyntaxError as exc:
            self._append("stderr", f'  File "{filename}", line {exc.lineno}\nSyntaxError: {exc.msg}\n')
            if exc.lineno:
                self.editor.set_error_line(exc.lineno)
            return False
        except RuntimeError as exc:  # a script runs already (started from the Exercises tab)
            self._append("stderr", f"Not started: {exc}\n")
            return False
        name = self.path.name if self.path else "the script"
        self._append("info", f"── {time.strftime('%H:%M:%S')} starting {name} ──\n")
        self._started_at = time.monotonic()
        self._was_running = True
        self._sync_buttons()
        return True

    def restart_problem(self, run: Any) -> str:
        """Why ``run`` cannot be started again exactly from here ("" when it can): console code is not kept."""
        if run.program.kind not in ("script_file",):
            return run.program.changed_on_disk() or f"{run.title} is not a script of this tab"
        return run.program.changed_on_disk()

    def restart_run(self, run: Any, continue_: bool = False) -> bool:
        """Run ``run``'s program again, exactly the text that ran (even if the file or the editor changed since),
        with its parameters; recorded as a restart ("recover") of ``run``."""
        if self.runner.running or self.restart_problem(run):
            return False
        program = run.program
        filename = program.path or "<editor>"
        self.editor.set_error_line(None)
        self.runner.home_first = self.home_first.isChecked()
        try:
            self._run = self.runner.start(program.text, filename, run.params_dict() or None, program=program,
                                          parameters=run.parameters, run_source="recover",
                                          restart_of=run.run_id)
        except (SyntaxError, RuntimeError) as exc:
            self._append("stderr", f"Not restarted: {exc}\n")
            return False
        self._append("info", f"── {time.strftime('%H:%M:%S')} restarting {program.title} (Recover) ──\n")
        self._started_at = time.monotonic()
        self._was_running = True
        self._sync_buttons()
        return True

    def stop_script(self) -> None:
        if self.runner.running:
            self.runner.request_stop("stopped by the operator")
            self.status.setText("Stopping…")

    def run_prompt_line(self, text: str) -> None:
        """Run a prompt line; lines of a block are collected until a blank line completes it."""
        self._append("prompt", ("... " if self._continuation else ">>> ") + text + "\n")
        self._continuation.append(text)
        source = "\n".join(self._continuation)
        try:
            thread = self.runner.execute(source)
        except SyntaxError as exc:
            self._continuation.clear()
            self._append("stderr", f"SyntaxError: {exc.msg}\n")
        else:
            if thread is None:
                self.prompt_label.setText("...")
                return
            self._continuation.clear()
        self.prompt_label.setText(">>>")

    # ------------------------------------------------------------------ output
    def _pending_output(self, stream: str, text: str) -> None:
        self._pending.append((stream, text))  # any thread: a deque append is atomic; drained on the GUI thread

    def _tick(self) -> None:
        self._drain()
        running = self.runner.running
        if running:
            self.status.setText(self.running_text())
        elif self._was_running:
            self._was_running = False
            self._drain()
            self._show_result(self.runner.result)
        elif self.status.text().startswith("Busy:"):  # another tab's run has ended: this tab ran nothing
            self.status.setText("No script running")
        self._sync_buttons()

    def _drain(self) -> None:
        for _ in range(2000):
            try:
                stream, text = self._pending.popleft()
            except IndexError:
                return
            self._append(stream, text)

    def running_text(self) -> str:
        """The run in progress, from the run itself: this tab's ("Running x.py — waiting for the grip — 12 s")
        or another tab's (the Exercises tab shares the runner: this tab then runs nothing of its own)."""
        opened = getattr(self.runner, "run", None)
        runs = getattr(self.manager, "runs", None)
        run = runs.get(opened.run_id) if opened is not None and runs is not None else None
        if run is None:
            return f"Running {self.path.name if self.path else 'the script'} — " \
                   f"{time.monotonic() - self._started_at:.0f} s"
        mine = self._run is not None and self._run.run_id == run.run_id
        if not mine:
            return f"Busy: {run.title} runs (started from the {_SOURCE_WORDS.get(run.source, run.source)})"
        state = "" if run.state in ("running", "starting") else f" — {run.state_text()}"
        progress = getattr(getattr(self.manager, "progress", None), "state", None)
        # the progress area's elapsed time (pauses not counted) when it follows this run
        elapsed = progress.elapsed_s() if getattr(progress, "run_id", "") == run.run_id else run.elapsed_s()
        return f"Running {run.title}{state} — {elapsed:.0f} s"

    def _show_result(self, result: ScriptResult | None) -> None:
        if result is None:
            self.status.setText("Script ended")
            return
        texts = {"finished": "Finished", "stopped": "Stopped", "error": "Error", "refused": "Refused by safety"}
        where = f" at line {result.line}" if result.line and not result.ok else ""
        runs = getattr(self.manager, "runs", None)
        run = runs.get(self._run.run_id) if self._run is not None and runs is not None else None
        if run is not None and not run.running and run.end_reason != "finished":
            reason = run.end_text().split(":", 1)[0]  # "emergency stop", "script error", …
            self.status.setText(f"{reason[:1].upper()}{reason[1:]}{where} ({result.duration_s:.1f} s)")
        else:
            self.status.setText(f"{texts.get(result.status, result.status)}{where} ({result.duration_s:.1f} s)")
        if result.line and not result.ok and self._is_editor_file(result.filename):
            self.editor.set_error_line(result.line)

    def _sync_buttons(self) -> None:
        running = self.runner.running
        hold = "" if running else self.hold_reason()
        self.start_button.setEnabled(not running and not hold)
        tip = f"Start is disabled: {hold}." if hold else START_TIP
        if self.start_button.toolTip() != tip:
            self.start_button.setToolTip(tip)
            if hold:
                self.status.setText(f"Start is disabled: {hold}.")
            elif self.status.text().startswith("Start is disabled"):
                self.status.setText("No script running")
        self.stop_button.setEnabled(running)
        self.open_button.setEnabled(not running)

    def _is_editor_file(self, filename: str) -> bool:
        return filename == (str(self.path) if self.path is not None else "<editor>")

    def _append(self, stream: str, text: str) -> None:
        colours = {"stdout": "", "stderr": "#c0392b", "info": "#1f6fb2", "prompt": "#555555"}
        colour = colours.get(stream, "")
        parts = []
        for line in text.splitlines(keepends=True):
            escaped = html.escape(line.rstrip("\n"))
            m = _TRACE_LINE.search(line)
            if m and stream == "stderr":
                target = f"line:{m.group(2)}:{m.group(1)}"
                link = f'<a href="{html.escape(target)}">line {m.group(2)}</a>'
                escaped = escaped.replace(f"line {m.group(2)}", link, 1)
            parts.append(escaped)
        body = "<br>".join(parts).replace("  ", "&nbsp;&nbsp;")
        style = f' style="color:{colour}"' if colour else ""
        cursor = self.output.textCursor()
        cursor.movePosition(QTextCursor.MoveOperation.End)
        self.output.setTextCursor(cursor)
        self.output.insertHtml(f"<span{style}>{body}</span>")
        if text.endswith("\n"):
            self.output.insertPlainText("\n")
        self.output.verticalScrollBar().setValue(self.output.verticalScrollBar().maximum())

    def _anchor_clicked(self, url: QUrl) -> None:
        target = url.toString()
        if not target.startswith("line:"):
            return
        _, line, filename = target.split(":", 2)
        if not self._is_editor_file(filename):
            path = Path(filename)
            if path.is_file() and not self.runner.running and not self.editor.document().isModified():
                self.load_file(path)
            else:
                return
        self.editor.go_to_line(int(line))

    def output_text(self) -> str:
        return self.output.toPlainText()

    # ------------------------------------------------------------------ lifecycle
    def closeEvent(self, event: Any) -> None:
        if self.runner.running:
            self.runner.stop("the console was closed", wait_s=0.5)
        super().closeEvent(event)

    def shutdown(self) -> None:
        """End the runner's kernel processes (the window is going away)."""
        self.runner.close()
