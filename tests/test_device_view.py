"""Frame 3: the picture follows the live state and the target; offscreen it is the 2D drawing
(never a GL widget); under Xvfb (xcb) the 3D scene renders."""

from __future__ import annotations

import numpy as np
import pytest
from PySide6.QtGui import QGuiApplication, QImage

from app.ui.device_view import DeviceView, spring_points
from tests.test_values_frame import make_stub_manager, publish_scene


def pixels(image: QImage, step: int = 4) -> np.ndarray:
    return np.array([image.pixel(x, y) for x in range(0, image.width(), step) for y in range(0, image.height(), step)])


def test_spring_zigzag_spans_the_gap() -> None:
    pts = spring_points(0.1, 0.3, 0.01, coils=5)
    assert pts[0, 0] == 0.1 and pts[-1, 0] == 0.3
    assert np.all(np.diff(pts[:, 0]) >= 0) and np.abs(pts[:, 1]).max() == 0.01
    assert np.count_nonzero(pts[:, 1]) == 10


def test_scene_follows_state_and_target(qtbot) -> None:
    manager, drivers = make_stub_manager()
    view = DeviceView(manager)
    qtbot.addWidget(view)
    assert view.state.handle is None and "no robot data" in view.caption.text()
    publish_scene(drivers)
    view.refresh()
    s = view.state
    assert (s.motor0, s.motor1, s.handle, s.target) == (0.16, 0.34, 0.231, 0.3)
    assert "handle 0.231 m" in view.caption.text() and "target 0.300 m" in view.caption.text()
    view.set_target(0.12)  # the API overrides the VR renderer's target ...
    assert view.state.target == 0.12
    view.set_target(None)  # ... until cleared
    assert view.state.target == 0.3
    view.set_target(-0.0001)  # issue #19: "-0.000 m"
    assert "target 0.000 m" in view.caption.text()


def test_fallback_is_a_2d_drawing_that_moves(qtbot) -> None:
    """Offscreen there is no GL at all; under Xvfb the same fallback is forced, so it is tested in both."""
    manager, drivers = make_stub_manager()
    view = DeviceView(manager, allow_gl=False)
    qtbot.addWidget(view)
    assert view.gl_view is None and view.canvas is not None  # no GL widget was ever built
    view.resize(600, 300)
    view.show()
    qtbot.waitExposed(view)
    publish_scene(drivers)
    view.refresh()
    first = view.render_image()
    assert len(np.unique(pixels(first))) > 20
    drivers["linarm"].put("linarm.vsa", 2.0, handlePos=0.4, equilibriumPos=0.4, delta=0.01)
    view.refresh()
    second = view.render_image()
    assert not np.array_equal(pixels(first, 2), pixels(second, 2))


@pytest.mark.gl
def test_gl_scene_renders(require_gl, qtbot) -> None:
    assert QGuiApplication.platformName() == "xcb"
    manager, drivers = make_stub_manager()
    publish_scene(drivers)
    view = DeviceView(manager)
    qtbot.addWidget(view)
    assert view.gl_view is not None and view.canvas is None
    view.resize(600, 400)
    view.show()
    qtbot.waitExposed(view)
    qtbot.waitUntil(view.gl_view.isExposed)  # the 3D scene's own native window
    view.refresh()
    image = view.render_image()
    assert image.width() > 0 and len(np.unique(pixels(image))) > 20
    array = view.gl_view.renderToArray((300, 200))
    assert sorted(array.shape[:2]) == [200, 300] and len(np.unique(array.reshape(-1, array.shape[-1]), axis=0)) > 20


def test_the_picture_is_repainted_only_when_something_moves_by_half_a_pixel(qtbot) -> None:
    from app.ui.device_view import RobotCanvas, SceneState

    canvas = RobotCanvas((0.0, 0.6))
    qtbot.addWidget(canvas)
    canvas.resize(624, 200)  # 600 px of rail: 1 px per mm
    repaints: list[int] = []
    canvas.update = lambda: repaints.append(1)  # type: ignore[method-assign]
    canvas.set_state(SceneState(0.1, 0.4, 0.25, None, True))
    assert len(repaints) == 1
    canvas.set_state(SceneState(0.1, 0.4, 0.2501, None, True))  # 0.1 mm: no pixel changes
    assert len(repaints) == 1 and canvas.state.handle == 0.2501  # the state is kept for the next paint
    canvas.set_state(SceneState(0.1, 0.4, 0.252, None, True))  # 2 mm: repainted
    assert len(repaints) == 2
    canvas.set_state(SceneState(0.1, 0.4, 0.252, None, False))  # connection lost: repainted
    canvas.set_state(SceneState(0.1, 0.4, 0.252, 0.3, False))  # a target appears: repainted
    assert len(repaints) == 4


def test_during_an_exercise_the_target_is_where_the_robot_takes_the_handle(qtbot) -> None:
    """Issue #30: the 3D view showed the VR game's target (0.1/0.4 m) during an exercise moving the handle
    between 0.15 and 0.35 m. While a run is running, the target is the robot's last moveCentreTo."""
    from app.core.runs import Program, RunLog, text_hash

    manager, drivers = make_stub_manager()
    manager.runs = RunLog()
    view = DeviceView(manager)
    qtbot.addWidget(view)
    publish_scene(drivers)  # the VR game's target: 0.3 m
    manager.devices["linarm"].driver.centre_target_m = 0.35
    view.refresh()
    assert view.state.target == 0.3  # no exercise running: the VR game's target
    run = manager.runs.start(Program("exercise", "trigger_reaching", "Trigger reaching", text_hash("")), [],
                             "exercises_tab", "op")
    view.refresh()
    assert view.state.target == 0.35 and "target 0.350 m" in view.caption.text()
    manager.runs.end(run.run_id, "finished")
    view.refresh()
    assert view.state.target == 0.3
