"""Where does the host's silence go? (issue #16, step 1: evidence before the fix)

Runs the reach exercise headless (``bench/scripts/reach_exercise.py``) with the LINarm simulator hosted
in the app's process (``--host thread``, the layout before #16) or in its own process (``--host process``),
optionally beside two CPU-bound ``yes`` processes, and records on the app's side:

* every write the LINarm driver makes (heartbeats and commands), stamped on the writing thread;
* every pass of the driver's loop (``on_tick``);
* when hosted in-process: every arrival of host bytes at the simulator and every simulator tick;
* per-thread CPU time (``/proc/self/task/*/stat``) over the run.

It prints the largest gaps of each, so a WATCHDOG trip can be attributed: the driver did not write
(driver thread starved), or it wrote but the simulator read late (simulator thread starved).

    .venv/bin/python bench/trace_host_silence.py --host thread --load 2
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common

SCRIPT = common.BENCH / "scripts" / "reach_exercise.py"
CLK = os.sysconf("SC_CLK_TCK")


def thread_cpu() -> dict[int, float]:
    out = {}
    for tid in os.listdir("/proc/self/task"):
        try:
            fields = Path(f"/proc/self/task/{tid}/stat").read_text().rsplit(")", 1)[1].split()
            out[int(tid)] = (int(fields[11]) + int(fields[12])) / CLK
        except (OSError, IndexError, ValueError):
            pass
    return out


def gaps(times: list[float], top: int = 5) -> list[tuple[float, float]]:
    """(gap in ms, time of the gap's start relative to the first) of the largest gaps."""
    if len(times) < 2:
        return []
    t0 = times[0]
    pairs = sorted(((b - a, a - t0) for a, b in itertools.pairwise(times)), reverse=True)[:top]
    return [(g * 1000, s) for g, s in pairs]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", choices=("thread", "process"), default="thread")
    p.add_argument("--load", type=int, default=2, help="CPU-bound `yes` processes beside the run")
    p.add_argument("--record", action="store_true", help="record the session (the recorder's share)")
    args = p.parse_args(argv)
    os.environ["LINARMPP_SIM_HOST"] = args.host

    from app.core.bus import Subscription
    from app.core.config import AppConfig
    from app.core.journal import Record
    from app.scripting.headless import run_headless

    writes: list[tuple[float, str]] = []
    reads: list[tuple[float, float, int]] = []  # LINarm driver reads: entry, return, bytes
    silence_events: list[tuple[float, str, str]] = []
    event_queue: list[Subscription] = []
    ticks: list[float] = []
    sim_in: list[float] = []
    sim_poll: list[float] = []
    names: dict[int, str] = {threading.get_native_id(): "main (Qt + headless loop)"}

    def prepare(manager) -> None:  # type: ignore[no-untyped-def]
        drv = manager.driver("linarm")
        transport_write = drv.transport.write

        def write(data: bytes) -> None:
            writes.append((time.monotonic(), threading.current_thread().name))
            names.setdefault(threading.get_native_id(), threading.current_thread().name)
            transport_write(data)

        drv.transport.write = write
        on_tick = drv.on_tick

        def tick(now: float) -> None:
            names.setdefault(threading.get_native_id(), "driver:linarm")
            ticks.append(now)
            on_tick(now)

        drv.on_tick = tick
        # Silence judgements (#27): every read's entry, return and size, and every silent/alive event, so a
        # "stopped sending data" can be told apart: the device sent nothing, or the read timed out and this
        # thread then waited for the CPU while the device's bytes piled up (the next read found them at once).
        transport_read = drv.transport.read

        def read(timeout: float) -> bytes:
            t_in = time.monotonic()
            data = transport_read(timeout)
            reads.append((t_in, time.monotonic(), len(data)))
            return data

        drv.transport.read = read
        # the LINarm's silent/alive events (stamped when published), drained after the run
        event_queue.append(manager.bus.subscribe("trace silence", (), events=True, maxlen=1_000_000))
        sim = manager.devices["linarm"].simulator
        core = getattr(sim, "core", None)
        if core is not None and hasattr(core, "handle_host_bytes"):
            hb, poll = core.handle_host_bytes, core.poll

            def handle(data: bytes, t: float) -> bytes:
                sim_in.append(time.monotonic())
                return hb(data, t)

            def polled(t: float) -> bytes:
                names.setdefault(threading.get_native_id(), "sim:linarm (1 kHz)")
                sim_poll.append(time.monotonic())
                return poll(t)

            core.handle_host_bytes, core.poll = handle, polled
        for name in ("physio", "fes", "patient_model", "vr"):
            d = manager.driver(name)
            if d is not None:  # name the driver threads: their loop passes run on_tick
                def named_tick(now: float, n: str = name, inner: Any = d.on_tick) -> None:
                    names.setdefault(threading.get_native_id(), f"driver:{n}")
                    inner(now)

                d.on_tick = named_tick

    stalls: list[str] = []
    cpu_seen: dict[int, float] = {}
    stop_sampler = threading.Event()

    def sampler() -> None:
        """Every 20 ms: when the driver loop has not passed for 100 ms, what is its thread doing?"""
        import collections
        import traceback

        seen: collections.Counter[str] = collections.Counter()
        others: collections.Counter[str] = collections.Counter()
        kernel: collections.Counter[str] = collections.Counter()
        while not stop_sampler.wait(0.02):
            for tid, cpu in thread_cpu().items():
                cpu_seen[tid] = max(cpu_seen.get(tid, 0.0), cpu)
            if ticks and time.monotonic() - ticks[-1] > 0.1:
                driver_tid = next((t for t, n in names.items() if n == "driver:linarm"), None)
                ident = next((t.ident for t in threading.enumerate() if t.native_id == driver_tid), None)
                frames = sys._current_frames()
                frame = frames.get(ident) if ident is not None else None
                if frame is None:  # a QThread is not in threading.enumerate(): find it by its frames
                    for f in frames.values():
                        if any("driver.py" in fs.filename and fs.name == "_io_loop"
                               for fs in traceback.extract_stack(f)):
                            frame = f
                if driver_tid is not None:  # the kernel's view: R = runnable (not given a CPU), S = sleeping
                    with contextlib.suppress(OSError, IndexError):
                        state = Path(f"/proc/self/task/{driver_tid}/stat").read_text().rsplit(")", 1)[1].split()[0]
                        wchan = Path(f"/proc/self/task/{driver_tid}/wchan").read_text().strip()
                        kernel[f"{state} {wchan}"] += 1
                if frame is not None:
                    where = " <- ".join(f"{Path(fs.filename).name}:{fs.lineno} {fs.name}"
                                        for fs in reversed(traceback.extract_stack(frame)[-4:]))
                    seen[where] += 1
                for ident, other in frames.items():  # and the others: who else runs Python meanwhile
                    if other is frame or ident == threading.get_ident():
                        continue
                    stack = traceback.extract_stack(other)[-3:]
                    top = " <- ".join(f"{Path(fs.filename).name}:{fs.lineno} {fs.name}" for fs in reversed(stack))
                    others[top] += 1
        stalls.extend(f"{n:4d} x {w}" for w, n in seen.most_common(8))
        stalls.append("  the driver thread's kernel state (state wchan): " + ", ".join(
            f"{k} x{n}" for k, n in kernel.most_common(5)))
        stalls.append("  other threads meanwhile:")
        stalls.extend(f"  {n:4d} x {w}" for w, n in others.most_common(12))

    imports: list[tuple[float, str, str]] = []

    def audit(event: str, args: tuple) -> None:  # which modules are imported while the driver stalls
        if event == "import" and ticks:
            imports.append((time.monotonic(), str(args[0]), threading.current_thread().name))

    sys.addaudithook(audit)
    threading.Thread(target=sampler, daemon=True).start()
    loads = [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(args.load)]
    cpu0, t0 = thread_cpu(), time.monotonic()
    try:
        out: list[str] = []
        code = run_headless(AppConfig(), str(SCRIPT), record_dir=(common.tempfile.mkdtemp() if args.record else None),
                            prepare=prepare, output=lambda _s, text: out.append(text))
    finally:
        for proc in loads:
            proc.kill()
            proc.wait()
    wall = time.monotonic() - t0
    stop_sampler.set()
    time.sleep(0.05)
    cpu1 = {tid: max(c, cpu_seen.get(tid, 0.0)) for tid, c in {**cpu_seen, **thread_cpu()}.items()}
    for t in threading.enumerate():
        if t.native_id is not None:
            names.setdefault(t.native_id, t.name)
    print(f"host={args.host} load={args.load} exit={code} wall={wall:.1f}s "
          f"(shared 2-core machine, load avg {common._read('/proc/loadavg').split()[0]})")
    print("".join(out)[-600:])
    hb_times = [t for t, _n in writes]
    print("largest gaps between LINarm driver writes (ms, at s):", [(round(g), round(s, 1)) for g, s in gaps(hb_times)])
    print("largest gaps between driver loop passes (ms, at s):", [(round(g), round(s, 1)) for g, s in gaps(ticks)])
    if sim_in:
        print("largest gaps between host bytes arriving at the simulator (ms, at s):",
              [(round(g), round(s, 1)) for g, s in gaps(sim_in)])
        print("largest gaps between simulator ticks (ms, at s):", [(round(g), round(s, 1)) for g, s in gaps(sim_poll)])
    worst = sorted(itertools.pairwise(ticks), key=lambda p: p[0] - p[1])[:3]
    for a, b in worst:
        during = [f"{m} ({who})" for t, m, who in imports if a <= t <= b]
        print(f"imports during the driver stall of {1000 * (b - a):.0f} ms at {a - ticks[0]:.1f} s: "
              f"{len(during)}: {', '.join(during[:25])}")
    for queue in event_queue:
        silence_events.extend((item.t_mono, item.kind, item.detail) for item in queue.drain()
                              if isinstance(item, Record) and item.origin == "linarm"
                              and item.kind in ("silent", "alive"))
    print(f"LINarm silence events: {len(silence_events)}")
    for t_event, event, detail in silence_events:
        if event != "silent":
            print(f"  {event} at {t_event - ticks[0]:.2f} s {detail}")
            continue
        before = [r for r in reads if r[1] <= t_event]
        after = [r for r in reads if r[0] >= t_event]
        last, nxt = (before[-1] if before else None), (after[0] if after else None)
        if last is not None:
            print(f"  silent at {t_event - ticks[0]:.2f} s: the last read returned {last[2]} bytes "
                  f"{1000 * (t_event - last[1]):.0f} ms before the judgement "
                  f"(its wait: {1000 * (last[1] - last[0]):.0f} ms); the next read returned "
                  f"{nxt[2] if nxt else '-'} bytes after {1000 * (nxt[1] - nxt[0]) if nxt else float('nan'):.1f} ms")
    print("driver thread while its loop stalled > 100 ms (20 ms samples):")
    print("\n".join("  " + line for line in stalls) or "  (no stall)")
    print("per-thread CPU over the run (s, % of one core):")
    rows = sorted(((cpu1.get(tid, 0) - cpu0.get(tid, 0), tid) for tid in cpu1), reverse=True)
    for cpu, tid in rows[:12]:
        print(f"  {names.get(tid, f'tid {tid}'):40} {cpu:6.2f} s  {100 * cpu / wall:5.1f} %")
    return code


if __name__ == "__main__":
    sys.exit(main())
