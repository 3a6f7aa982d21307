"""Shared helpers of the benchmarks: statistics, the machine, CPU and memory of a process, the wire taps.

Every benchmark runs with the application's interpreter (``.venv/bin/python bench/<name>.py``); the
benchmark-only extras (psutil, PyCmdMessenger, pyinstrument, py-spy) live in ``bench/.venv`` and are
appended to ``sys.path`` here, after the application's own packages, so they never shadow them.

Timestamps are ``time.monotonic_ns()``. "The wire" is the simulator's side of a link: a
:class:`WireTap` wraps a simulator core and stamps the bytes the core receives from the host (what
the driver wrote) and the bytes it emits (what the device wrote), on the simulator thread.
"""

from __future__ import annotations

import datetime
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
BENCH = ROOT / "bench"
PROFILES = BENCH / "profiles"
EXTRAS = BENCH / ".venv" / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ.setdefault("LINARMPP_HOME", tempfile.mkdtemp(prefix="linarmpp-bench-"))


def use_extras() -> bool:
    """Make bench/.venv's packages importable (appended: the app's own versions win). False if absent."""
    if EXTRAS.is_dir():
        if str(EXTRAS) not in sys.path:
            sys.path.append(str(EXTRAS))
        return True
    return False


# ---------------------------------------------------------------------------------------------- figures
@dataclass(frozen=True)
class Stats:
    n: int
    median: float
    p99: float
    max: float
    mean: float


def percentile(values: list[float], q: float) -> float:
    """Linear interpolation between closest ranks (numpy's default), without numpy."""
    data = sorted(values)
    if not data:
        return float("nan")
    pos = (len(data) - 1) * q / 100.0
    lo = int(pos)
    hi = min(lo + 1, len(data) - 1)
    return data[lo] + (data[hi] - data[lo]) * (pos - lo)


def stats(values: list[float]) -> Stats:
    if not values:
        nan = float("nan")
        return Stats(0, nan, nan, nan, nan)
    return Stats(len(values), statistics.median(values), percentile(values, 99.0), max(values),
                 statistics.fmean(values))


def verdict(value: float, target: float, higher_is_better: bool = False) -> str:
    """'met' or 'MISSED by X (Y %)' against a target (≤ target unless ``higher_is_better``)."""
    if value != value:
        return "no data"
    ok = value >= target if higher_is_better else value <= target
    if ok:
        return "met"
    gap = abs(value - target)
    return f"MISSED by {gap:.3g} ({100.0 * gap / target:.0f} %)"


def report(name: str, values_ms: list[float], target_ms: float | None = None, unit: str = "ms") -> Stats:
    s = stats(values_ms)
    line = (f"  {name:64} n={s.n:4d}  median {s.median:8.2f} {unit}  p99 {s.p99:8.2f} {unit}"
            f"  max {s.max:8.2f} {unit}")
    if target_ms is not None:
        line += f"  | target p99 ≤ {target_ms:g} {unit}: {verdict(s.p99, target_ms)}"
    print(line, flush=True)
    return s


# ---------------------------------------------------------------------------------------------- the machine
def _read(path: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return ""


def machine() -> dict[str, str]:
    cpu = next((line.split(":", 1)[1].strip() for line in _read("/proc/cpuinfo").splitlines()
                if line.startswith("model name")), platform.processor() or platform.machine())
    mem_kb = next((int(line.split()[1]) for line in _read("/proc/meminfo").splitlines()
                   if line.startswith("MemTotal:")), 0)
    os_name = next((line.split("=", 1)[1].strip().strip('"') for line in _read("/etc/os-release").splitlines()
                    if line.startswith("PRETTY_NAME=")), platform.system())
    try:
        import PySide6
        from PySide6 import QtCore

        qt = f"Qt {QtCore.qVersion()} (PySide6 {PySide6.__version__})"
    except ImportError:
        qt = "Qt not importable"
    load = " ".join(_read("/proc/loadavg").split()[:3])
    return {
        "date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"),
        "cpu": f"{cpu}, {os.cpu_count()} logical cores",
        "ram": f"{mem_kb / 1024 / 1024:.1f} GiB",
        "os": f"{os_name}, Linux {platform.release()}",
        "python": f"Python {platform.python_version()} ({sys.implementation.name})",
        "qt": qt,
        "load": f"load average {load} at start",
    }


def print_machine(title: str) -> None:
    m = machine()
    print(f"== {title} ==")
    print(f"   {m['date']} | {m['cpu']} | {m['ram']} | {m['os']} | {m['python']} | {m['qt']} | {m['load']}",
          flush=True)


# ---------------------------------------------------------------------------------------------- CPU and memory
_CLK_TCK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
_PAGE = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096


def cpu_seconds(pid: int | None = None) -> float:
    """User + system CPU time (s) of a process (this one by default), from /proc."""
    if pid is None:
        t = os.times()
        return t.user + t.system
    fields = _read(f"/proc/{pid}/stat").rsplit(")", 1)[-1].split()
    if len(fields) < 13:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK  # utime, stime (fields 14, 15 of stat)


def thread_cpu_seconds(native_id: int) -> float:
    """User + system CPU time (s) of one thread of this process, from /proc/self/task."""
    fields = _read(f"/proc/self/task/{native_id}/stat").rsplit(")", 1)[-1].split()
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK if len(fields) >= 13 else 0.0


def thread_cpu_table() -> dict[int, tuple[str, float]]:
    """Every thread of this process: native id -> (OS thread name, user + system CPU seconds)."""
    out: dict[int, tuple[str, float]] = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            name = _read(f"/proc/self/task/{tid}/comm").strip()
        except OSError:
            continue  # the thread ended meanwhile
        out[int(tid)] = (name, thread_cpu_seconds(int(tid)))
    return out


def thread_cpu_percent(before: dict[int, tuple[str, float]], after: dict[int, tuple[str, float]],
                       seconds: float) -> list[tuple[str, float]]:
    """CPU (% of one core) of each thread between two :func:`thread_cpu_table` snapshots, grouped by thread
    name (the drivers' QThreads are named ``driver:<device>``, truncated to 15 characters by Linux)."""
    by_name: dict[str, float] = {}
    for tid, (name, cpu) in after.items():
        used = cpu - before.get(tid, (name, 0.0))[1]
        by_name[name] = by_name.get(name, 0.0) + 100.0 * used / max(1e-9, seconds)
    return sorted(by_name.items(), key=lambda kv: -kv[1])


def simulator_threads() -> list[int]:
    """Native ids of the device simulators' threads (in the app's process only because simulated)."""
    return [t.native_id for t in threading.enumerate() if t.name.startswith("sim:") and t.native_id is not None]


def rss_bytes(pid: int | None = None) -> int:
    """Resident set size of a process (this one by default), from /proc."""
    fields = _read(f"/proc/{pid or 'self'}/statm").split()
    return int(fields[1]) * _PAGE if len(fields) > 1 else 0


class CpuMeter:
    """CPU of one or more processes over a wall-clock interval, as a percentage of one core."""

    def __init__(self, pids: list[int | None]) -> None:
        self.pids = pids
        self.start()

    def start(self) -> None:
        self._t0 = time.monotonic()
        self._c0 = [cpu_seconds(p) for p in self.pids]

    def percent(self) -> list[float]:
        dt = max(1e-9, time.monotonic() - self._t0)
        return [100.0 * (cpu_seconds(p) - c0) / dt for p, c0 in zip(self.pids, self._c0, strict=True)]


# ---------------------------------------------------------------------------------------------- the wire
class WireTap:
    """Wraps a simulator core; stamps (monotonic_ns) what the host sent it and what it emitted.

    ``on_host(t_ns, data)`` / ``on_device(t_ns, data)`` run on the simulator thread: keep them short."""

    def __init__(self, inner: Any, on_host: Callable[[int, bytes], None] | None = None,
                 on_device: Callable[[int, bytes], None] | None = None, keep: bool = True) -> None:
        self.inner = inner
        self.on_host = on_host
        self.on_device = on_device
        self.keep = keep
        self.host: list[tuple[int, bytes]] = []
        self.device: list[tuple[int, bytes]] = []

    def handle_host_bytes(self, data: bytes, t: float) -> bytes:
        now = time.monotonic_ns()
        if self.keep:
            self.host.append((now, data))
        if self.on_host is not None:
            self.on_host(now, data)
        return self.inner.handle_host_bytes(data, t)

    def poll(self, t: float) -> bytes:
        out = self.inner.poll(t)
        if out:
            now = time.monotonic_ns()
            if self.keep:
                self.device.append((now, out))
            if self.on_device is not None:
                self.on_device(now, out)
        return out

    def __getattr__(self, name: str) -> Any:  # the rest of the core's API (with_core users)
        return getattr(self.inner, name)


def tap(simulator: Any, **kwargs: Any) -> WireTap:
    """Put a WireTap around ``simulator``'s core (under its lock) and return it."""
    wrapper: WireTap | None = None

    def swap(_core: Any) -> None:
        nonlocal wrapper
        wrapper = WireTap(simulator.core, **kwargs)
        simulator.core = wrapper

    simulator.with_core(swap)
    assert wrapper is not None
    return wrapper


class RemoteWire:
    """The wire of a simulator hosted in its own process (the app's default): the rows its SerialSimulator
    logged there — host bytes as it read them, device bytes as it wrote them — stamped with time.monotonic() in
    the simulator process (CLOCK_MONOTONIC: one clock for every process). ``host`` / ``device`` are
    (monotonic_ns, bytes) lists like WireTap's, brought up to date by :meth:`refresh`; ``on_host`` is called
    for each new host row on refresh."""

    def __init__(self, simulator: Any, host: bool = True, device: bool = False,
                 on_host: Callable[[int, bytes], None] | None = None) -> None:
        self.sim = simulator
        self.want_host, self.want_device = host, device
        self.on_host = on_host
        self.host: list[tuple[int, bytes]] = []
        self.device: list[tuple[int, bytes]] = []
        if host:
            simulator.keep_host_log = True
        if device:
            simulator.device_log(keep=True)

    def refresh(self) -> None:
        if self.want_host:
            rows = self.sim.host_bytes_log
            new = [(round(t * 1e9), data) for t, data in rows[len(self.host):]]
            self.host.extend(new)
            if self.on_host is not None:
                for t_ns, data in new:
                    self.on_host(t_ns, data)
        if self.want_device:
            first, rows = self.sim.device_log(since=len(self.device))
            del self.device[first:]
            self.device.extend((round(t * 1e9), data) for t, data in rows)


def wire(simulator: Any, host: bool = True, device: bool = False,
         on_host: Callable[[int, bytes], None] | None = None) -> Any:
    """The simulator's wire, stamped on its side: a RemoteWire (own process) or a WireTap (a thread here)."""
    if hasattr(simulator, "process"):
        return RemoteWire(simulator, host, device, on_host)
    tapped = tap(simulator, on_host=on_host, keep=on_host is None)
    tapped.refresh = lambda: None  # type: ignore[attr-defined]
    return tapped


def hosting() -> str:
    """Where the simulators run in this benchmark ('process': the app's default; 'thread')."""
    return os.environ.get("LINARMPP_SIM_HOST") or "process"


def link_kind() -> str:
    """The simulators' links: in-process hosting always uses ptys; the process the configured link."""
    return "pty" if hosting() == "thread" else (os.environ.get("LINARMPP_SIM_LINK") or "socket")


# ---------------------------------------------------------------------------------------------- the app
def bench_config(**device_changes: Any) -> Any:
    """The default configuration (every device simulated), with ``devices`` fields replaced."""
    from dataclasses import replace

    from app.core.config import AppConfig

    cfg = AppConfig()
    if device_changes:
        cfg = replace(cfg, devices=replace(cfg.devices, **device_changes))
    return cfg


def qt_app() -> Any:
    from PySide6.QtWidgets import QApplication

    if QApplication.instance() is None:
        from app.application import prepare_qt

        prepare_qt()  # as the application does, before the QApplication exists
    app = QApplication.instance() or QApplication([sys.argv[0]])
    from app.application import configure_qt_identity

    configure_qt_identity()
    try:  # as the application does: the collector on the main thread only (#38)
        from app.main_thread_gc import collect_on_the_main_thread
    except ImportError:  # the code before it
        pass
    else:
        collect_on_the_main_thread(app)
    return app


def run_qt_for(seconds: float) -> None:
    """Run the Qt event loop for ``seconds`` with no timer of the benchmark's own: what the CPU figures
    measure is then only the application (run_qt_until's 5 ms polling woke the GUI thread 200 times a
    second, which the application does not do)."""
    from PySide6.QtCore import QEventLoop, QTimer

    loop = QEventLoop()
    QTimer.singleShot(max(0, int(seconds * 1000)), loop.quit)
    loop.exec()


def run_qt_until(predicate: Callable[[], bool], timeout_s: float, poll_ms: int = 5) -> bool:
    """Run the Qt event loop (the GUI thread keeps painting) until ``predicate()`` or the timeout."""
    from PySide6.QtCore import QEventLoop, QTimer

    loop = QEventLoop()
    deadline = time.monotonic() + timeout_s
    result = {"ok": False}

    def check() -> None:
        if predicate():
            result["ok"] = True
            loop.quit()
        elif time.monotonic() > deadline:
            loop.quit()

    timer = QTimer()
    timer.setInterval(poll_ms)
    timer.timeout.connect(check)
    timer.start()
    check()
    if not result["ok"] and time.monotonic() <= deadline:
        loop.exec()
    timer.stop()
    return result["ok"]


def start_manager(config: Any, timeout_s: float = 15.0) -> Any:
    """A started LinarmppManager whose devices are all connected (raises otherwise)."""
    from app.manager import LinarmppManager

    manager = LinarmppManager(config)
    manager.start()
    if not run_qt_until(manager.all_connected, timeout_s):
        missing = [n for n, h in manager.devices.items() if not h.driver.connected]
        manager.shutdown()
        raise RuntimeError(f"devices not connected within {timeout_s:g} s: {missing}")
    return manager


def open_window(manager: Any, load: bool, refresh_hz: float = 120.0, history_s: float = 60.0) -> Any:
    """The real MainWindow, offscreen. ``load``: every signal in the graphs, redrawn at ``refresh_hz``."""
    from app.ui.main_window import MainWindow

    window = MainWindow(manager)
    window.resize(1600, 1000)
    window.show()
    set_gui_load(window, load, refresh_hz, history_s)
    return window


def set_gui_load(window: Any, load: bool, refresh_hz: float = 120.0, history_s: float = 60.0) -> int:
    """Select every signal (load) or none (idle) in the graphs; returns how many are drawn."""
    plots = window.frames.get("PlotsFrame")
    if plots is None or not hasattr(plots, "set_selected"):
        return 0
    keys = [info.key for info in plots.store.signals()] if load else []
    plots.set_selected(keys)
    if load:
        plots.set_history(min(history_s, plots.store.history_s))
    plots.timer.setInterval(max(0, int(1000.0 / refresh_hz)))
    if not hasattr(plots, "_bench_redraws"):
        plots._bench_redraws = 0

        def count() -> None:
            plots._bench_redraws += 1

        plots.timer.timeout.connect(count)
    return len(keys)


def redraw_count(window: Any) -> int:
    """Graph redraws so far (the graphs' timer ticks since set_gui_load first ran)."""
    plots = window.frames.get("PlotsFrame")
    return int(getattr(plots, "_bench_redraws", 0))


def shutdown(manager: Any, window: Any = None) -> None:
    if window is not None:
        window.close()
    manager.shutdown()


def thread_dump_hint() -> str:
    return ", ".join(sorted(t.name for t in threading.enumerate()))


# ---------------------------------------------------------------------------------------------- profiles
def py_spy_path() -> Path | None:
    exe = BENCH / ".venv" / "bin" / "py-spy"
    return exe if exe.exists() else None


def start_py_spy(name: str, duration_s: float, pid: int | None = None, rate_hz: int = 250) -> Any:
    """Sample a process (this one by default) with py-spy for ``duration_s``, every thread, into
    bench/profiles/<name>.raw (collapsed stacks). Returns the Popen, or None without py-spy."""
    import subprocess

    exe = py_spy_path()
    if exe is None:
        print("  (no py-spy: create bench/.venv as bench/README.md says to get a profile)")
        return None
    PROFILES.mkdir(exist_ok=True)
    out = PROFILES / f"{name}.raw"
    cmd = [str(exe), "record", "--pid", str(pid or os.getpid()), "--duration", str(max(1, round(duration_s))),
           "--rate", str(rate_hz), "--format", "raw", "--threads", "--nonblocking", "--output", str(out)]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def summarise_py_spy(name: str, thread: str = "MainThread", top: int = 25) -> Path | None:
    """Inclusive sample counts per function of one thread, from bench/profiles/<name>.raw, into <name>.txt."""
    raw = PROFILES / f"{name}.raw"
    if not raw.exists():
        return None
    total = 0
    inclusive: dict[str, int] = {}
    for line in raw.read_text(encoding="utf-8", errors="replace").splitlines():
        stack, _, count_text = line.rpartition(" ")
        if not stack or not count_text.isdigit():
            continue
        frames = stack.split(";")
        if not frames or thread not in frames[0]:
            continue
        count = int(count_text)
        total += count
        for frame in set(frames[1:]):
            inclusive[frame] = inclusive.get(frame, 0) + count
    lines = [f"py-spy profile '{name}', thread {thread}: {total} samples (inclusive share of each function)"]
    for frame, count in sorted(inclusive.items(), key=lambda kv: -kv[1])[:top]:
        lines.append(f"{100.0 * count / max(1, total):5.1f} %  {frame}")
    out = PROFILES / f"{name}.txt"
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return out
