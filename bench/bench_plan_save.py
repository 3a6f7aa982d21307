"""Saving a therapy plan: what the window's thread spends in it (issue #37). A two-step plan (one FES step, whose
profile is read and checked) saved ``--trials`` times in the plan form, the window's event loop turning meanwhile;
per save: the time in the Save call itself, and the window thread's longest stall from Save to the form closed (the
longest gap between two turns of its event loop, as the GUI heartbeat would see it). Median and p99.

    QT_QPA_PLATFORM=offscreen .venv/bin/python bench/bench_plan_save.py [--trials 100] [--rev <commit>]

``--rev``: the plan form as it was at that commit (read with ``git show``), for the figure before.
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
from PySide6.QtWidgets import QApplication  # noqa: E402

from app.core.config import AppConfig  # noqa: E402
from app.therapy.patients import PatientProfile, load_patient, save_patient  # noqa: E402

SAFETY = AppConfig().safety


def plan_form_at(rev: str | None) -> types.ModuleType:
    if rev is None:
        from app.ui import plan_dialog

        return plan_dialog
    source = subprocess.run(["git", "show", f"{rev}:app/ui/plan_dialog.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    module = types.ModuleType("app.ui.plan_dialog")
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


def one_save(form: types.ModuleType, folder: Path) -> tuple[float, float]:
    """(ms in the Save call, ms of the window thread's longest stall from Save to the form closed, s it took)."""
    dialog = form.PlanDialog(load_patient("PZ-BENCH", SAFETY, folder), SAFETY, folder)
    dialog.add_step("trigger_reaching")
    dialog.add_step("assisted_reaching_fes")
    dialog.show()
    QApplication.processEvents()
    turns: list[float] = []
    ticker = QTimer()
    ticker.setInterval(0)
    ticker.timeout.connect(lambda: turns.append(time.perf_counter()))
    loop = QEventLoop()
    dialog.finished.connect(loop.quit)
    ticker.start()
    QApplication.processEvents()
    t0 = time.perf_counter()
    turns.append(t0)
    dialog.accept()
    t1 = time.perf_counter()
    if dialog.isVisible():
        QTimer.singleShot(10_000, loop.quit)
        loop.exec()
    turns.append(time.perf_counter())
    ticker.stop()
    assert dialog.saved is not None, dialog.error_label.text()
    dialog.deleteLater()
    QApplication.processEvents()
    stall = max(b - a for a, b in itertools.pairwise(turns))
    return (t1 - t0) * 1e3, stall * 1e3, turns[-1] - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--rev", default=None, help="the plan form at this commit (the figure before)")
    args = parser.parse_args()
    app = QApplication.instance() or QApplication([])
    form = plan_form_at(args.rev)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        save_patient(PatientProfile(patient_id="PZ-BENCH"), folder, SAFETY)
        one_save(form, folder)  # imports and the first disk reads out of the figures
        calls, stalls, idle = [], [], []
        for _ in range(args.trials):
            call, stall, took = one_save(form, folder)
            calls.append(call)
            stalls.append(stall)
            idle.append(idle_stall(took))  # as long again, nothing saved: what the machine alone costs
    print(f"plan form {'at ' + args.rev if args.rev else 'of this tree'}, {args.trials} saves: "
          f"Save call median {statistics.median(calls):.1f} ms, p99 {percentile(calls, 0.99):.1f} ms; "
          f"longest stall of the window's thread per save median {statistics.median(stalls):.1f} ms, "
          f"p99 {percentile(stalls, 0.99):.1f} ms; idle as long, nothing saved: median "
          f"{statistics.median(idle):.1f} ms, p99 {percentile(idle, 0.99):.1f} ms")
    app.quit()


if __name__ == "__main__":
    main()
