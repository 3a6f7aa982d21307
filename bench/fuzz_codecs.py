"""Full fuzz run: 10^5 inputs per codec (random bytes and mutations of valid frames).

    .venv/bin/python bench/fuzz_codecs.py [--count N] [--seed S]

Prints, per codec, the inputs run, the decoder exceptions (must be 0) and the resync failures (must be 0).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from tests.fuzz_targets import all_targets, fuzz  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--count", type=int, default=100_000)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    bad = 0
    print(f"{'codec':48} {'inputs':>8} {'exceptions':>10} {'resync failures':>16} {'s':>6}")
    for target in all_targets():
        t0 = time.perf_counter()
        try:
            count, failures = fuzz(target, args.count, args.seed)
            exceptions = 0
        except Exception as exc:  # a bug: report it and go on with the others
            count, failures, exceptions = args.count, 0, 1
            print(f"  {target.name}: {exc!r}")
        bad += failures + exceptions
        print(f"{target.name:48} {count:8d} {exceptions:10d} {failures:16d} {time.perf_counter() - t0:6.1f}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
