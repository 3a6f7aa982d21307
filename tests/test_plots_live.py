"""The live graphs keep up (issue #37): following the live data, the curves are stroked off the GUI thread into one
image per pane (app.ui.plot_render) — drawn exactly where the curve items draw them when paused; a pane scrolled
out of view is neither reduced nor drawn; the renderer's thread rests when no frame comes."""

from __future__ import annotations

import time

import numpy as np
from PySide6.QtGui import QImage, QPen

from app.ui.plot_render import CurveRenderer, PaneJob
from app.ui.plots_frame import FastCurve
from tests.test_plots_frame import make_frame, synthetic_store


def _pixels(image: QImage) -> np.ndarray:
    image = image.convertToFormat(QImage.Format.Format_RGB32)
    data = np.frombuffer(image.constBits(), dtype=np.uint32, count=image.width() * image.height())
    return data.reshape(image.height(), image.width()).copy()


def test_live_curves_are_drawn_off_the_gui_thread_where_the_items_draw_them(qtbot) -> None:
    store, _data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce"])
    frame.redraw()
    assert frame._image_mode and all(not c.isVisibleTo(frame.plots["m"].vb) or c.drawn_elsewhere
                                     for c in frame.curves.values())
    qtbot.waitUntil(lambda: all(i.image is not None for i in frame.images.values()), timeout=3000)
    qtbot.wait(200)  # the panes' layout settles (a resized pane is drawn again at the next tick)
    qtbot.waitUntil(lambda: not frame._dirty and frame._shown_seq == frame._frame_seq, timeout=3000)
    x, y = frame.curves["linarm.vsa.handlePos"].getData()  # the points are kept for the crosshair and saving
    assert len(x) > 100 and np.isfinite(y).all()
    live_image = frame.graphics.grab().toImage()
    live = _pixels(live_image)
    frame.set_paused(True)  # the same data, drawn by the curve items on the GUI thread
    assert not frame._image_mode and all(i.image is None for i in frame.images.values())
    qtbot.wait(50)
    paused_image = frame.graphics.grab().toImage()
    paused = _pixels(paused_image)
    import os
    if os.environ.get("PLOTS_LIVE_DEBUG"):
        live_image.save(os.environ["PLOTS_LIVE_DEBUG"] + "-live.png")
        paused_image.save(os.environ["PLOTS_LIVE_DEBUG"] + "-paused.png")
    assert live.shape == paused.shape
    values, counts = np.unique(paused, return_counts=True)
    background = values[counts.argmax()]
    drawn = (paused != background) | (live != background)
    differ = (paused != live) & drawn
    assert drawn.sum() > 1000
    assert differ.sum() <= 0.02 * drawn.sum(), f"{differ.sum()} of {drawn.sum()} drawn pixels differ"


def test_a_pane_out_of_view_is_not_drawn(qtbot) -> None:
    store, _data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.resize(900, 220)  # room for about one and a half panes: the third is out of view
    frame.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce", "physio.main.heartRate"])
    qtbot.wait(300)  # laid out
    frame.timer.stop()  # frames driven here
    qtbot.wait(100)  # a frame still being drawn is shown
    for image in frame.images.values():
        image.set_image(None)
    frame._dirty = True
    frame.redraw()
    qtbot.waitUntil(lambda: frame.images["m"].image is not None, timeout=3000)
    qtbot.wait(100)
    assert frame.images["bpm"].image is None  # scrolled out of view: not drawn
    assert len(frame.curves["physio.main.heartRate"].getData()[0]) == 0  # ... nor reduced (#37: the window's turn)
    assert len(frame.curves["linarm.vsa.handlePos"].getData()[0]) > 100
    frame.graphs_scroll.verticalScrollBar().setValue(frame.graphs_scroll.verticalScrollBar().maximum())
    assert frame._dirty  # scrolled: the next frame draws what came into view, new samples or not
    qtbot.wait(50)
    frame.redraw()
    qtbot.waitUntil(lambda: frame.images["bpm"].image is not None, timeout=3000)
    assert len(frame.curves["physio.main.heartRate"].getData()[0]) > 100


def test_the_renderer_draws_the_newest_frame_and_rests(qtbot) -> None:
    renderer = CurveRenderer(idle_exit_s=0.1)
    got: list[tuple[int, dict]] = []
    renderer.rendered.connect(lambda frame, images: got.append((frame, images)))
    try:
        pen = QPen()
        pen.setCosmetic(True)
        x = np.linspace(0.0, 1.0, 50)
        from PySide6.QtGui import QTransform

        transform = QTransform()
        transform.scale(100, 50)
        for frame in (1, 2, 3):
            renderer.submit(frame, [PaneJob("p", 100, 50, 1.0, transform, [(pen, x, x, True)])])
        qtbot.waitUntil(lambda: any(f == 3 for f, _i in got), timeout=3000)
        image = dict(got)[3]["p"]
        assert image.width() == 100 and image.height() == 50
        alpha = np.frombuffer(image.constBits(), dtype=np.uint32, count=100 * 50) >> 24
        assert 50 <= (alpha > 0).sum() < 1000  # the diagonal drawn, the rest transparent
        qtbot.waitUntil(lambda: not renderer.running, timeout=3000)
    finally:
        renderer.close()


def test_a_curve_hidden_from_its_legend_stays_hidden_when_drawn_elsewhere() -> None:
    curve = FastCurve(QPen(), "x")
    curve.setVisible(False)  # the legend's sample
    curve.set_drawn_elsewhere(True)
    curve.set_drawn_elsewhere(False)
    assert not curve.isVisible() and not curve.user_visible



def test_ticking_a_signal_keeps_the_other_panes(qtbot) -> None:
    """Building a pane costs ~25 ms of the GUI thread: ticking or unticking one signal touches its own pane only
    (it re-built all of them before #37: 0.3-0.5 s with eleven panes, a stall the GUI watch would judge)."""
    store, _data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce", "linarm.vsa.equilibriumPos"])
    panes = dict(frame.plots)
    assert list(panes) == ["m", "N"]
    frame.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce"])  # one "m" curve less
    assert frame.plots == panes and set(frame.curves) == {"linarm.vsa.handlePos", "linarm.vsa.interactionForce"}
    assert len(frame.plots["m"].legend.items) == 1
    frame.set_selected(["linarm.vsa.handlePos", "linarm.vsa.interactionForce", "physio.main.heartRate"])
    assert list(frame.plots) == ["m", "N", "bpm"] and all(frame.plots[u] is panes[u] for u in ("m", "N"))
    assert frame.plots["bpm"].getAxis("bottom").style["showValues"]  # the time axis moved to the new last pane
    assert not frame.plots["N"].getAxis("bottom").style["showValues"]
    frame.set_selected(["linarm.vsa.interactionForce"])
    assert list(frame.plots) == ["N"] and frame.plots["N"] is panes["N"]
    frame.redraw()
    x, _y = frame.curves["linarm.vsa.interactionForce"].getData()
    assert len(x) > 100


def test_the_drawing_thread_ends_when_the_frame_is_hidden_and_comes_back_with_it(qtbot) -> None:
    """A hidden frame draws nothing: its thread ends at once instead of idling a second (a closed window's
    thread outlived it by that second — ~1 s of teardown in ~40 tests of the suite)."""
    store, _data = synthetic_store()
    frame = make_frame(qtbot, store)
    frame.set_selected(["linarm.vsa.handlePos"])
    frame.redraw()
    qtbot.waitUntil(lambda: frame.renderer.running, timeout=3000)
    assert frame.renderer.idle_exit_s >= 1.0  # what it would idle otherwise
    t0 = time.monotonic()
    frame.hide()
    qtbot.waitUntil(lambda: not frame.renderer.running, timeout=900)
    assert time.monotonic() - t0 < frame.renderer.idle_exit_s
    frame.show()
    frames = frame.renderer.frames
    frame.redraw()
    qtbot.waitUntil(lambda: frame.renderer.frames > frames, timeout=3000)  # drawing again once shown
