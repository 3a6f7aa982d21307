"""The log's writer (app/core/logging_setup.py): a log call queues its line and returns, whatever the disk or the
console does; every queued line is written, in order, before the process ends — a forced ``os._exit`` included."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

from app.core.logging_setup import LOG_FORMAT, BackgroundHandler

ROOT = Path(__file__).resolve().parent.parent


class BlockedDisk(logging.Handler):
    """A handler whose writes wait until ``unblocked`` is set: a stuck disk or a console pipe nobody reads."""

    def __init__(self) -> None:
        super().__init__()
        self.unblocked = threading.Event()
        self.lines: list[str] = []
        self.writer_threads: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        self.unblocked.wait(10.0)
        self.writer_threads.add(threading.current_thread().name)
        self.lines.append(self.format(record))


def test_a_log_call_does_not_wait_for_the_disk_and_every_line_is_written_in_order() -> None:
    disk = BlockedDisk()
    disk.setFormatter(logging.Formatter(LOG_FORMAT))
    handler = BackgroundHandler([disk])
    logger = logging.getLogger("test.logging_setup.blocked")
    logger.propagate = False
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    returned = threading.Event()

    def heartbeat_thread() -> None:  # as a driver's real-time thread logs a late heartbeat
        for i in range(50):
            logger.warning("late heartbeat %d", i)
        returned.set()

    caller = threading.Thread(target=heartbeat_thread, name="heartbeat")
    try:
        caller.start()
        assert returned.wait(5.0), "a log call waited for the blocked disk"
        assert disk.lines == []  # nothing written yet: the disk is still blocked
        disk.unblocked.set()
    finally:
        disk.unblocked.set()
        caller.join(5.0)
        logger.removeHandler(handler)
        handler.close()  # drains the queue and ends the writer
    assert [line.rsplit(" ", 1)[1] for line in disk.lines] == [str(i) for i in range(50)]
    assert all(" heartbeat test.logging_setup.blocked: late heartbeat" in line for line in disk.lines), disk.lines[0]
    assert "heartbeat" not in disk.writer_threads  # written by the writer, not by the caller
    assert handler.listener is None


def test_lines_queued_before_a_forced_exit_are_in_the_file(tmp_path: Path) -> None:
    """The application's signal and shutdown paths end with ``logging.shutdown()`` then ``os._exit``."""
    code = textwrap.dedent("""
        import logging, os, threading
        from app.core.logging_setup import setup_logging
        path = setup_logging(console=False)
        print(path, flush=True)
        log = logging.getLogger("app.devices.linarm")
        t = threading.Thread(target=lambda: [log.warning("line %d", i) for i in range(2000)])
        t.start(); t.join()
        logging.shutdown()
        os._exit(3)
    """)
    env = {**os.environ, "LINARMPP_HOME": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT, env=env)
    assert done.returncode == 3, done.stderr
    lines = Path(done.stdout.strip()).read_text(encoding="utf-8").splitlines()
    assert [line.rsplit(" ", 1)[1] for line in lines if "app.devices.linarm" in line] == [str(i) for i in range(2000)]
