"""Frame time of the graphs at 8 curves × 60 s × 1 kHz (target ≤ 16 ms for 60 Hz).

Each frame: ~33 new samples per curve arrive (1 kHz at 30 Hz batches), then the frame redraws all
8 curves from the store's min/max envelope and the graphics view repaints synchronously.

Two ways of drawing (issue #37), ``--where``: ``thread`` (the default since #37: the GUI thread reduces the
samples and blits each pane's image; a renderer thread strokes the curves, its time printed apart) and ``gui``
(the curves stroked in the window's paint, on the GUI thread, as before #37). ``--noise`` makes the signals noisy
(the costly case: a zig-zag of full-height segments); ``--curves 49`` is every signal of the app's devices.

    .venv/bin/python bench/bench_plots.py [--frames N] [--window S] [--curves N] [--noise] [--where gui|thread|both]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("LINARMPP_HOME", tempfile.mkdtemp(prefix="linarmpp-bench-"))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import numpy as np
from PySide6.QtWidgets import QApplication


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--curves", type=int, default=8)
    parser.add_argument("--rate", type=float, default=1000.0)
    parser.add_argument("--window", type=float, default=60.0, help="visible history (s)")
    parser.add_argument("--noise", action="store_true", help="noisy signals (dense zig-zags: the costly case)")
    parser.add_argument("--where", choices=("gui", "thread", "both"), default="both",
                        help="stroke the curves in the GUI thread's paint, on the renderer thread, or measure both")
    args = parser.parse_args()
    for where in (("gui", "thread") if args.where == "both" else (args.where,)):
        run(args, where)
    return 0


def run(args: argparse.Namespace, where: str) -> None:

    app = QApplication.instance() or QApplication(sys.argv)
    from app.application import configure_qt_identity
    from app.core.bus import Channel, SampleBatch, StreamSpec
    from app.ui.plots_frame import PlotsFrame
    from app.ui.signal_store import SignalStore

    configure_qt_identity()
    spec = StreamSpec("bench.main", tuple(Channel(f"s{i}", "V" if i % 2 else "N", f"Signal {i}")
                                          for i in range(args.curves)), args.rate)
    store = SignalStore(history_s=args.window)
    store.add_stream(spec, "bench")
    rng = np.random.default_rng(0)
    n_fill = int(args.window * args.rate)
    t = np.arange(n_fill) / args.rate
    noise = 1.0 if args.noise else 0.1
    store.feed({spec.name: SampleBatch(spec, t, {c.name: np.sin(t * (i + 1)) + noise * rng.normal(size=n_fill)
                                                 for i, c in enumerate(spec.channels)})})
    frame = PlotsFrame(None, store=store)
    frame.timer.stop()  # frames are driven here
    frame.render_off_thread = where == "thread"
    frame.resize(1200, 700)
    frame.show()
    frame.set_selected([f"bench.main.s{i}" for i in range(args.curves)])
    frame.set_history(args.window)
    app.processEvents()
    per_frame = int(args.rate / 30)
    t_next = t[-1]
    times: list[float] = []
    render: list[float] = []
    cpu: list[float] = []
    for k in range(args.frames + 10):
        tb = t_next + (np.arange(per_frame) + 1) / args.rate
        t_next = tb[-1]
        cols = {c.name: np.sin(tb * (i + 1)) + noise * rng.normal(size=len(tb)) for i, c in enumerate(spec.channels)}
        store.feed({spec.name: SampleBatch(spec, tb, cols)})
        renderer = getattr(frame, "renderer", None)  # None: the code before #37
        drawn = renderer.frames if renderer is not None else 0
        t0, c0 = time.perf_counter(), time.thread_time()
        frame.redraw()
        frame.graphics.viewport().repaint()
        dt, dc = time.perf_counter() - t0, time.thread_time() - c0
        if where == "thread" and renderer is not None:  # the next frame starts when this one is drawn
            deadline = time.monotonic() + 2.0
            while renderer.frames == drawn and time.monotonic() < deadline:
                app.processEvents()
                time.sleep(0.0005)
            app.processEvents()
            render.append(renderer.render_cost_s * 1000)
        if k >= 10:  # warm-up
            times.append(dt * 1000)
            cpu.append(dc * 1000)
    arr = np.array(times)
    points = sum(len(c.getData()[0]) for c in frame.curves.values())
    how = "curves stroked on the renderer thread" if where == "thread" else "curves stroked on the GUI thread"
    print(f"graphs ({how}):"
          f" {args.curves} curves × {args.window:g} s × {args.rate:g} Hz ({n_fill} samples each"
          f"{', noisy' if args.noise else ''}), {points} points, {arr.size} frames, platform {app.platformName()}")
    print(f"  GUI thread per frame (reduce + paint): median {np.median(arr):.1f} ms, "
          f"p99 {np.percentile(arr, 99):.1f} ms, max {arr.max():.1f} ms (target ≤ 16 ms); its CPU time: median "
          f"{np.median(cpu):.1f} ms, p99 {np.percentile(cpu, 99):.1f} ms (what a quiet machine would take)")
    if render:
        print(f"  renderer thread per frame, CPU time (smoothed): median {np.median(render):.1f} ms, "
              f"max {max(render):.1f} ms")
    if getattr(frame, "renderer", None) is not None:
        frame.renderer.close()
    frame.close()


if __name__ == "__main__":
    sys.exit(main())
