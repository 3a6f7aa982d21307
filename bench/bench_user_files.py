"""What saving a therapy plan reads on the window's thread (issue #37): the exercise library, an FES profile and
the configuration, through the application's strict YAML loader. Median and p99 over ``--trials``.

    .venv/bin/python bench/bench_user_files.py [--trials 200]

Before libyaml (72692ca): 59.8 ms median quiet; after: 11.6 ms (bench/README.md, "Session 9").
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from app.core import config, fes_profile, yamlschema  # noqa: E402
from app.therapy import exercises  # noqa: E402

RESOURCES = ROOT / "resources"


def read_once() -> None:
    library, problems = exercises.load_library(RESOURCES / "exercises")
    assert library and not problems, problems
    fes_profile.load_profile(RESOURCES / "fes_profiles" / "reaching_by_district.yaml")
    config.load_config(RESOURCES / "config.default.yaml")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=200)
    args = parser.parse_args()
    read_once()  # imports and the first disk reads out of the figures
    times = []
    for _ in range(args.trials):
        t0 = time.perf_counter()
        read_once()
        times.append((time.perf_counter() - t0) * 1e3)
    times.sort()
    p99 = times[min(len(times) - 1, round(0.99 * (len(times) - 1)))]
    parser_name = getattr(yamlschema, "YAML_LOADER", None).__name__ if hasattr(yamlschema, "YAML_LOADER") \
        else "SafeLoader"  # the code before libyaml has no YAML_LOADER
    print(f"parser {parser_name}: "
          f"library + FES profile + configuration: median {statistics.median(times):.1f} ms, p99 {p99:.1f} ms "
          f"({args.trials} trials)")


if __name__ == "__main__":
    main()
