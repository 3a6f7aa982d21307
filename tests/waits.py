"""How long a test waits for work that runs in the heavy work's worker process (app/worker), in ms.

The worker runs below every ordinary program on a busy machine (nice 10 in a scheduling group of its own:
app/worker/process.py), so that it never takes the therapy's CPU. The price is paid in time, not in outcome:
measured on the 2-core machine beside two `yes > /dev/null` (load 11), the browser's research exports took 69-101 s
that take 3-8 s quiet, the heavy-work window test 137 s for 21-32 s. Giving the worker an ordinary program's share
instead (the application's scheduling group, nice 0 below the application's -5) made them 2-5x faster there, and the
GUI watch stopped the therapy in both attempts ("the window did not respond for 0.91 s"): the therapy first. A
wait only bounds a hang, so it is sized for the loaded machine; quiet, the tests end as soon as the work does."""

from __future__ import annotations

WORKER_TASK_MS = 240_000
