"""Frame time of the graphs at 8 curves × 60 s × 1 kHz (target ≤ 16 ms for 60 Hz).

Each frame: ~33 new samples per curve arrive (1 kHz at 30 Hz batches), then the frame redraws all
8 curves from the store's min/max envelope and the graphics view repaints synchronously.

    .venv/bin/python bench/bench_plots.py [--frames N] [--window S]
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
    args = parser.parse_args()

    app = QApplication.instance() or QApplication(sys.argv)
    from app.application import configure_qt_identity
    from app.bus import Channel, SampleBatch, StreamSpec
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
    store.feed({spec.name: SampleBatch(spec, t, {c.name: np.sin(t * (i + 1)) + 0.1 * rng.normal(size=n_fill)
                                                 for i, c in enumerate(spec.channels)})})
    frame = PlotsFrame(None, store=store)
    frame.timer.stop()  # frames are driven here
    frame.resize(1200, 700)
    frame.show()
    frame.set_selected([f"bench.main.s{i}" for i in range(args.curves)])
    frame.set_history(args.window)
    app.processEvents()
    per_frame = int(args.rate / 30)
    t_next = t[-1]
    times: list[float] = []
    for k in range(args.frames + 10):
        tb = t_next + (np.arange(per_frame) + 1) / args.rate
        t_next = tb[-1]
        cols = {c.name: np.sin(tb * (i + 1)) for i, c in enumerate(spec.channels)}
        store.feed({spec.name: SampleBatch(spec, tb, cols)})
        t0 = time.perf_counter()
        frame.redraw()
        frame.graphics.viewport().repaint()
        dt = time.perf_counter() - t0
        if k >= 10:  # warm-up
            times.append(dt * 1000)
    arr = np.array(times)
    points = sum(len(c.getData()[0]) for c in frame.curves.values())
    print(f"graphs: {args.curves} curves × {args.window:g} s × {args.rate:g} Hz "
          f"({n_fill} samples each), {points} points drawn, {arr.size} frames, platform {app.platformName()}")
    print(f"frame time: median {np.median(arr):.1f} ms, p99 {np.percentile(arr, 99):.1f} ms, "
          f"max {arr.max():.1f} ms (target ≤ 16 ms)")
    frame.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
