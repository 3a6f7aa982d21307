"""Saving a therapy plan: what the window's thread spends in it (issue #37). A plan of ``--steps`` steps (every
second one with FES, whose profile is read and checked) saved ``--trials`` times in the plan form, the window's
event loop turning meanwhile; per save: the time in the Save call itself, and the window thread's longest stall from
Save to the form closed (the longest gap between two turns of its event loop, as the GUI heartbeat would see it).
Median and p99.

    QT_QPA_PLATFORM=offscreen .venv/bin/python bench/bench_plan_save.py [--trials 100] [--steps 6] [--rev <commit>]

``--rev``: the plan form as it was at that commit (read with ``git show``) as well, its saves alternating with this
tree's in one process (the machine's load then weighs on both alike): the figures before and after.
"""

from __future__ import annotations

import argparse
import itertools
import statistics
import subprocess
import sys
import tempfile
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from PySide6.QtCore import QEventLoop, QTimer  # noqa: E402
from PySide6.QtWidgets import QApplication, QDialogButtonBox  # noqa: E402

from app.core.config import AppConfig  # noqa: E402
from app.therapy.patients import PatientProfile, load_patient, save_patient  # noqa: E402

SAFETY = AppConfig().safety


def plan_form_at(rev: str | None) -> types.ModuleType:
    if rev is None:
        from app.ui import plan_dialog

        return plan_dialog
    source = subprocess.run(["git", "show", f"{rev}:app/ui/plan_dialog.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    module = types.ModuleType(f"plan_dialog_at_{rev}")
    module.__file__ = str(ROOT / "app" / "ui" / "plan_dialog.py")
    sys.modules[module.__name__] = module
    exec(compile(source, module.__file__, "exec"), module.__dict__)  # the project's own file, as it was
    return module


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def idle_stall(duration_s: float) -> float:
    """The window thread's longest stall over ``duration_s`` with nothing saved (the machine's own share, ms)."""
    turns: list[float] = []
    ticker = QTimer()
    ticker.setInterval(0)
    ticker.timeout.connect(lambda: turns.append(time.perf_counter()))
    loop = QEventLoop()
    QTimer.singleShot(max(1, round(duration_s * 1000)), loop.quit)
    turns.append(time.perf_counter())
    ticker.start()
    loop.exec()
    ticker.stop()
    turns.append(time.perf_counter())
    return max(b - a for a, b in itertools.pairwise(turns)) * 1e3


def one_save(form: types.ModuleType, folder: Path, steps: int = 6) -> tuple[float, float, float]:
    """(ms in the Save call, ms of the window thread's longest stall from Save to the form closed, s it took)."""
    save_patient(PatientProfile(patient_id="PZ-BENCH"), folder, SAFETY)  # the same plan saved each time
    dialog = form.PlanDialog(load_patient("PZ-BENCH", SAFETY, folder), SAFETY, folder)
    for k in range(steps):  # half of them stimulate: each reads and checks its FES profile
        dialog.add_step("assisted_reaching_fes" if k % 2 else "trigger_reaching")
    dialog.show()
    QApplication.processEvents()
    turns: list[float] = []
    ticker = QTimer()
    ticker.setInterval(0)
    ticker.timeout.connect(lambda: turns.append(time.perf_counter()))
    ticker.start()
    loop = QEventLoop()
    dialog.finished.connect(loop.quit)
    save = dialog.buttons.button(QDialogButtonBox.StandardButton.Save)
    stamps: dict[str, float] = {}

    def click() -> None:  # Save clicked from the event loop, as a person does
        stamps["t0"] = time.perf_counter()
        turns.append(stamps["t0"])
        save.click()
        stamps["t1"] = time.perf_counter()

    QTimer.singleShot(20, click)
    guard = QTimer()  # a save that never answers ends this trial (and fails it below)
    guard.setSingleShot(True)
    guard.timeout.connect(loop.quit)
    guard.start(10_000)
    loop.exec()
    turns.append(time.perf_counter())
    guard.stop()
    ticker.stop()
    t0, t1 = stamps["t0"], stamps["t1"]
    turns = [t for t in turns if t >= t0]
    assert dialog.saved is not None, dialog.error_label.text()
    dialog.deleteLater()
    QApplication.processEvents()
    stall = max(b - a for a, b in itertools.pairwise(turns))
    return (t1 - t0) * 1e3, stall * 1e3, turns[-1] - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--steps", type=int, default=6, help="the plan's steps (every second one with FES)")
    parser.add_argument("--rev", default=None, help="the plan form at this commit (the figure before)")
    args = parser.parse_args()
    app = QApplication.instance() or QApplication([])
    forms = {"this tree": plan_form_at(None)}
    if args.rev:
        forms[f"at {args.rev}"] = plan_form_at(args.rev)
    figures: dict[str, tuple[list[float], list[float], list[float]]] = {name: ([], [], []) for name in forms}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for form in forms.values():
            one_save(form, folder, args.steps)  # imports and the first disk reads out of the figures
        for _ in range(args.trials):
            for name, form in forms.items():
                call, stall, took = one_save(form, folder, args.steps)
                calls, stalls, idle = figures[name]
                calls.append(call)
                stalls.append(stall)
                idle.append(idle_stall(took))  # as long again, nothing saved: what the machine alone costs
    for name, (calls, stalls, idle) in figures.items():
        print(f"plan form {name}, {args.trials} saves of {args.steps} steps: "
              f"Save call median {statistics.median(calls):.1f} ms, p99 {percentile(calls, 0.99):.1f} ms; "
              f"longest stall of the window's thread per save median {statistics.median(stalls):.1f} ms, "
              f"p99 {percentile(stalls, 0.99):.1f} ms; idle as long, nothing saved: median "
              f"{statistics.median(idle):.1f} ms, p99 {percentile(idle, 0.99):.1f} ms")
    app.quit()


if __name__ == "__main__":
    main()
