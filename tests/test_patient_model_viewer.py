"""The patient-model viewer renders offscreen with a decision path; the screenshot goes to docs/."""

from __future__ import annotations

from app.devices.patient_model import PatientModelSample
from app.devices.sim.patient_model.decision_tree import DecisionTree
from app.ui.patient_model_viewer import DecisionTreeView, PatientModelViewer
from tests.conftest import screenshot_path

SCREENSHOT = screenshot_path("patient-model-viewer.png")


def sample_from_tree(tree: DecisionTree, score: float, tpi: float, mpi: float, pti: float) -> PatientModelSample:
    d = tree.decide(score, tpi, mpi, pti)
    return PatientModelSample(alpha=d.alpha, a_r=0.6 * d.alpha, a_f=0.3 * d.alpha, tpi=tpi, mpi=mpi, pti=pti,
                              alphaMin=d.alphaRange[0], alphaMax=d.alphaRange[1], pathCode=d.path_code,
                              path=d.leaf, level=d.level, valid=True, fallback=False, seq=0, ackSeq=0,
                              roundTrip=0.001)


def test_viewer_shows_the_decision_path_and_the_history(qtbot) -> None:
    viewer = PatientModelViewer(refresh_hz=50.0)
    qtbot.addWidget(viewer)
    viewer.clinical_score = 40
    viewer.resize(1500, 720)
    tree = DecisionTree()
    # A session: the patient fails sub-tasks (level up, TPI down), then recovers.
    last = None
    for i in range(600):
        t = i * 0.1
        if i and i % 60 == 0:
            tree.record_subtask(success=i < 300 and i % 120 == 0)
        tpi = max(0.0, 0.7 - i / 800) if i < 360 else 0.25 + (i - 360) / 1000
        last = sample_from_tree(tree, 40, tpi, 0.45 + 0.1 * (i % 50) / 50, min(1.0, i / 500))
        viewer.feed(t, last)
    viewer.show()
    viewer.refresh()
    qtbot.waitExposed(viewer)
    assert viewer.tree.path == last.path and last.path.startswith("in_between/")
    assert viewer.values["alpha"].text() == f"{last.alpha:.3f}"
    assert len(viewer.curves["alpha"].getData()[0]) == 600
    SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
    assert viewer.grab().save(str(SCREENSHOT))
    assert SCREENSHOT.stat().st_size > 10_000


def test_the_taken_leaf_is_drawn_in_the_highlight_colour(qtbot) -> None:
    view = DecisionTreeView()
    qtbot.addWidget(view)
    view.resize(800, 400)
    tree = DecisionTree()
    d = tree.decide(10, 0.9, 0.1, 0.0)  # assist / tpi high / mpi low / pti low
    view.set_decision(d.leaf, d.alpha, d.alphaRange, d.level, {"clinical_score": 10, "tpi": 0.9})
    pos, *_ = view._layout()
    image = view.grab().toImage()
    ratio = image.width() / view.width()
    taken, other = pos[d.leaf], pos["resist/tpi_low/mpi_low/pti_low"]

    def rim(pt) -> tuple[int, int, int]:  # a pixel on the node's outline, right of its centre
        radius = max(5.0, min(9.0, (800 - 166) / 24 * 0.32))
        c = image.pixelColor(int((pt.x() + radius) * ratio), int(pt.y() * ratio))
        return c.red(), c.green(), c.blue()

    assert rim(taken)[0] > 150 and rim(taken)[1] < 100  # red highlight
    assert rim(other)[0] < 150 or rim(other)[1] > 100


def test_a_viewer_on_a_hidden_tab_does_no_refresh_work_and_catches_up_when_shown(qtbot) -> None:
    from PySide6.QtWidgets import QLabel, QTabWidget

    tabs = QTabWidget()
    viewer = PatientModelViewer(refresh_hz=100.0)
    tabs.addTab(QLabel("another panel"), "Robot")
    tabs.addTab(viewer, "Patient model")
    qtbot.addWidget(tabs)
    tabs.resize(1200, 700)
    tabs.show()
    qtbot.waitExposed(tabs)
    viewer.refresh()  # nothing fed yet: empty curves
    tree = DecisionTree()
    last = None
    for i in range(50):
        last = sample_from_tree(tree, 40, 0.5, 0.5, i / 50)
        viewer.feed(i * 0.1, last)

    def drawn() -> int:
        x = viewer.curves["alpha"].getData()[0]
        return 0 if x is None else len(x)

    qtbot.wait(100)  # ten timer periods while hidden
    viewer._tick()
    assert drawn() == 0 and viewer.values["alpha"].text() == "–" and viewer.tree.path == ""
    tabs.setCurrentWidget(viewer)  # shown: everything at once, without waiting for the timer
    assert drawn() == 50 and viewer.values["alpha"].text() == f"{last.alpha:.3f}" and viewer.tree.path == last.path
