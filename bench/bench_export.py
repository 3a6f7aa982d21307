"""Research export (issue #41): a long session exported to BIDS, XDF and EDF+ — time and peak memory.

    .venv/bin/python bench/bench_export.py                 # a 2-hour session, the three formats
    .venv/bin/python bench/bench_export.py --minutes 40 --formats xdf edf

The session is synthesised in the recorder's on-disk format (tests/research_export_data.synth_session: every
stream at its default rate, 6.4 million samples in two hours) and cached in --cache. Each export runs in a child
process that measures its own resident memory after its imports and its peak at the end (VmHWM): the growth is
what the export itself needed. The CPU time is printed too: on a shared machine the wall time mostly says how busy
it was. Figures for bench/README.md, "Session 6 (#41)".
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _status_mb(field: str) -> float:
    """VmRSS (resident now) or VmHWM (the peak of this process image: unlike ru_maxrss it does not inherit the
    parent's peak across fork and exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    return 0.0


def child(fmt: str, folder: str, out: str, block_bytes: int = 0) -> dict[str, float]:
    """Run one export in this process, as the command line does; return its seconds and its memory growth (MB)."""
    sys.path.insert(0, str(ROOT))
    import pandas  # noqa: F401  - imports first: their memory is not the export's
    import pyedflib  # noqa: F401

    from app.research_export import bids, edf, xdf
    from app.research_export.common import release_memory_promptly
    from app.research_export.source import FolderSource, open_session

    release_memory_promptly()
    base = _status_mb("VmRSS")
    t0, c0 = time.perf_counter(), time.process_time()
    session = open_session(FolderSource(folder))
    if block_bytes:
        session.block_bytes = block_bytes
    if fmt == "bids":
        bids.export_bids([session], Path(out))
    elif fmt == "xdf":
        xdf.export_xdf(session, Path(out))
    else:
        edf.export_edf(session, Path(out))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    peak = _status_mb("VmHWM")
    return {"seconds": seconds, "cpu_s": cpu, "growth_mb": peak - base, "base_mb": base, "peak_mb": peak}


def child_all(folder: str, out: str, block_bytes: str = "0") -> dict[str, dict[str, float]]:
    """The three exports one after the other in this process, the peak reset before each (Linux: writing 5 to
    /proc/self/clear_refs resets VmHWM), so each format's growth is its own."""
    import gc

    figures = {}
    for fmt in ("xdf", "edf", "bids"):
        gc.collect()
        Path("/proc/self/clear_refs").write_text("5")
        figures[fmt] = child(fmt, folder, str(Path(out) / f"out.{fmt}"), int(block_bytes))
    return figures


def measure_all(folder: Path, out: Path, block_bytes: int = 0) -> dict[str, dict[str, float]]:
    """:func:`child_all` in a child process (one interpreter start for the three formats)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child-all", str(folder), str(out),
                           str(block_bytes)],
                          capture_output=True, text=True, check=False, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"the exports failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def measure(fmt: str, folder: Path, out: Path) -> dict[str, float]:
    """One export in a child process (a fresh interpreter: the peak is this export's)."""
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", fmt, str(folder), str(out)],
                          capture_output=True, text=True, check=False, timeout=600)
    if proc.returncode != 0:
        raise RuntimeError(f"the {fmt} export failed:\n{proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def session(cache: Path, minutes: float) -> Path:
    sys.path.insert(0, str(ROOT))
    from tests.research_export_data import synth_session

    folder = cache / f"bench-{minutes:g}min" / "PB-001" / "20260301-100000"
    if not (folder / "manifest.json").exists():
        shutil.rmtree(folder.parent.parent, ignore_errors=True)
        t0 = time.perf_counter()
        synth_session(folder.parent.parent, "PB-001", minutes * 60.0)
        print(f"synthesised {minutes:g} min in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    clock_estimates(folder)
    return folder


def clock_estimates(folder: Path, every_s: float = 0.5) -> None:
    """A ``clocks.csv`` as the recorder keeps it (an estimate of each device's clock about twice a second: 14 400
    lines per device in two hours) when the synthesised session has none, so the XDF headers carry what a recorded
    session's do (desc/device_clock) and the device-clock form has its offsets."""
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from app.session import recording

    path = folder / recording.CLOCK_FILE
    if path.exists():
        return
    manifest = json.loads((folder / recording.MANIFEST_FILE).read_text())
    start = float(manifest["start"]["t_mono_s"])
    end = float((manifest.get("end") or {}).get("t_mono_s") or start)
    host = np.arange(start, end + every_s, every_s)
    lines = [",".join(recording.CLOCK_COLUMNS) + "\n"]
    for device, device0, ppm in (("linarm", 4000.0, 80.0), ("physio", 123.456, -50.0)):
        drift = -ppm * 1e-6 + np.random.default_rng(len(device)).normal(0.0, 2e-6, len(host))
        device_s = device0 + (host - start) * (1 + ppm * 1e-6)
        lines += [f"{h!r},{device},{d!r},{k!r}\n" for h, d, k in zip(host.tolist(), device_s.tolist(),
                                                                      drift.tolist(), strict=True)]
    path.write_text("".join(lines))


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        print(json.dumps(child(*sys.argv[2:5])))
        return 0
    if len(sys.argv) > 1 and sys.argv[1] == "--child-all":
        print(json.dumps(child_all(*sys.argv[2:5])))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=120.0)
    parser.add_argument("--formats", nargs="+", default=["bids", "xdf", "edf"])
    parser.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "linarmpp-bench-export")
    args = parser.parse_args()
    folder = session(args.cache, args.minutes)
    size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20
    import os

    print(f"session: {args.minutes:g} min, {size:.0f} MB of CSV; load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory(dir=args.cache) as tmp:
        for fmt in args.formats:
            out = Path(tmp) / f"out.{fmt}"
            r = measure(fmt, folder, out)
            written = sum(p.stat().st_size for p in ([out] if out.is_file() else out.rglob("*")) if p.is_file())
            print(f"{fmt:4s}: {r['seconds']:6.1f} s ({r['cpu_s']:.1f} s of CPU), peak RSS growth "
                  f"{r['growth_mb']:6.1f} MB (base {r['base_mb']:.0f} MB), written {written / 2**20:.0f} MB")
            shutil.rmtree(out, ignore_errors=True) if out.is_dir() else out.unlink(missing_ok=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
