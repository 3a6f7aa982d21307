"""The script kernel's link, chosen by measurement: round trip of a sample-sized JSON line between this
process and a child Python process, over an AF_UNIX socket pair, a pair of pipes, and a
multiprocessing Pipe (pickle); plus the cost of encoding/decoding one sample as a JSON line.

    .venv/bin/python bench/bench_kernel_link.py [--n N]

Each round trip: the parent writes one line (a VSA sample: 7 floats, ~120 bytes), the child reads it,
decodes it, and writes it back; the parent reads it. Median and p99 in µs.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common

from app.core.streams import LINARM_VSA

SAMPLE = {"op": "sample", "s": LINARM_VSA, "v": [0.25012, 0.02, 900.0, 0.2501, -0.0012, 1.234, 12.3456]}

ECHO = r"""
import json, os, sys
rfd, wfd = int(sys.argv[1]), int(sys.argv[2])
r = os.fdopen(rfd, "rb", buffering=0)
buf = b""
while True:
    data = os.read(rfd, 65536)
    if not data:
        break
    buf += data
    while b"\n" in buf:
        line, buf = buf.split(b"\n", 1)
        msg = json.loads(line)
        os.write(wfd, (json.dumps(msg, separators=(",", ":")) + "\n").encode())
"""

MP_ECHO = r"""
import sys
from multiprocessing.connection import Connection
c = Connection(int(sys.argv[1]))
while True:
    try:
        c.send(c.recv())
    except EOFError:
        break
"""


def round_trips(write: object, read: object, n: int) -> list[float]:
    line = (json.dumps(SAMPLE, separators=(",", ":")) + "\n").encode()
    out = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        write(line)  # type: ignore[operator]
        got = b""
        while not got.endswith(b"\n"):
            got += read()  # type: ignore[operator]
        out.append((time.perf_counter_ns() - t0) / 1000)
    return out


def socketpair_case(n: int) -> list[float]:
    parent, child = socket.socketpair()
    proc = subprocess.Popen([sys.executable, "-I", "-c", ECHO, str(child.fileno()), str(child.fileno())],
                            pass_fds=(child.fileno(),))
    child.close()
    try:
        return round_trips(parent.sendall, lambda: parent.recv(65536), n)
    finally:
        parent.close()
        proc.wait(5)


def pipes_case(n: int) -> list[float]:
    to_child_r, to_child_w = os.pipe()
    from_child_r, from_child_w = os.pipe()
    proc = subprocess.Popen([sys.executable, "-I", "-c", ECHO, str(to_child_r), str(from_child_w)],
                            pass_fds=(to_child_r, from_child_w))
    os.close(to_child_r)
    os.close(from_child_w)
    try:
        return round_trips(lambda b: os.write(to_child_w, b), lambda: os.read(from_child_r, 65536), n)
    finally:
        os.close(to_child_w)
        proc.wait(5)
        os.close(from_child_r)


def mp_pipe_case(n: int) -> list[float]:
    from multiprocessing import Pipe

    parent, child = Pipe()
    proc = subprocess.Popen([sys.executable, "-I", "-c", MP_ECHO, str(child.fileno())], pass_fds=(child.fileno(),))
    child.close()
    out = []
    try:
        for _ in range(n):
            t0 = time.perf_counter_ns()
            parent.send(SAMPLE)
            parent.recv()
            out.append((time.perf_counter_ns() - t0) / 1000)
    finally:
        parent.close()
        proc.wait(5)
    return out


def codec_cost(n: int) -> tuple[float, float]:
    line = (json.dumps(SAMPLE, separators=(",", ":")) + "\n").encode()
    t0 = time.perf_counter_ns()
    for _ in range(n):
        (json.dumps(SAMPLE, separators=(",", ":")) + "\n").encode()
    enc = (time.perf_counter_ns() - t0) / n / 1000
    t0 = time.perf_counter_ns()
    for _ in range(n):
        json.loads(line)
    dec = (time.perf_counter_ns() - t0) / n / 1000
    return enc, dec


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=3000)
    args = parser.parse_args()
    common.print_machine("script kernel link: round trip of one sample-sized message to a child process")
    for name, case in (("AF_UNIX socket pair, JSON lines", socketpair_case), ("two pipes, JSON lines", pipes_case),
                       ("multiprocessing Pipe (pickle)", mp_pipe_case)):
        values = case(args.n)
        s = common.stats(values[100:])
        print(f"  {name:34s} median {s.median:6.1f} µs   p99 {s.p99:7.1f} µs   (n={s.n})", flush=True)
    enc, dec = codec_cost(20000)
    print(f"  JSON line of one VSA sample: encode {enc:.1f} µs, decode {dec:.1f} µs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
