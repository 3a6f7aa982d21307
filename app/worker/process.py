"""The worker process's own loop (started by app/worker/service.py; never imported by the application itself).

One task at a time on the main thread; a reader thread takes the application's messages meanwhile (a cancel sets
the running task's flag, ``quit`` or the link closing ends the process at once: whatever a task half-wrote is a
temporary the application removes). A task's failure is one sentence back to the application; a crash is the
application's to report (the link closes).
"""

from __future__ import annotations

import faulthandler
import logging
import os
import queue
import socket
import sys
import threading
import traceback
from typing import Any

from app.worker.context import Cancelled, JobContext, JobError
from app.worker.protocol import LinkClosed, Sender, recv


def _failure(exc: BaseException) -> str:
    from app.core.outputs import OutputError

    if isinstance(exc, JobError | OutputError):
        return str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        where = f" ({exc.filename})" if exc.filename else ""
        return f"{exc.strerror}{where}."
    return f"{type(exc).__name__}: {exc}."


def main(fd: int) -> None:
    sock = socket.socket(fileno=fd)
    sender = Sender(sock)
    try:
        _, init = recv(sock)
    except LinkClosed:
        os._exit(0)
    for entry in reversed(init.get("sys_path") or []):
        if entry not in sys.path:
            sys.path.insert(1, entry)
    if hasattr(os, "sched_setscheduler"):  # never a real-time policy inherited from the application's threads
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass
    nice = int(init.get("nice") or 0)
    if nice and hasattr(os, "setpriority"):
        try:  # absolute: the application's real-time threads it was started from may run raised (app/core/priority.py)
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError:
            pass
        # The worker runs in a session of its own, which Linux schedules as a group of its own (autogroup): its
        # nice value alone would not yield the CPU to the application's group. The group's nice does.
        try:
            with open("/proc/self/autogroup", "w", encoding="ascii") as fh:
                fh.write(str(int(init.get("group_nice", nice))))
        except OSError:
            pass
    faulthandler.enable()  # a crash's stack into the worker's log (its stderr)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(levelname)-7s worker[%(process)d] %(name)s: %(message)s")
    from app.worker import jobs

    jobs.preload()
    sender.send("ready", os.getpid())

    tasks: queue.Queue[tuple[Any, ...]] = queue.Queue()
    flags: dict[int, threading.Event] = {}
    lock = threading.Lock()

    def read() -> None:
        while True:
            try:
                msg = recv(sock)
            except LinkClosed:
                os._exit(0)  # the application has gone (or closed the link): end now, mid-task or not
            if msg[0] == "run":
                with lock:
                    flags[msg[1]] = threading.Event()
                tasks.put(msg)
            elif msg[0] == "cancel":
                with lock:
                    flag = flags.get(msg[1])
                if flag is not None:
                    flag.set()
            elif msg[0] == "quit":
                sys.stderr.flush()
                os._exit(0)

    threading.Thread(target=read, name="worker-link", daemon=True).start()
    while True:
        _, tid, kind, args, kwargs = tasks.get()
        with lock:
            flag = flags.setdefault(tid, threading.Event())
        ctx = JobContext(tid, sender, flag)
        try:
            result = jobs.resolve(kind)(ctx, *args, **kwargs)
            message: tuple[Any, ...] = ("done", tid, result)
        except Cancelled:
            message = ("cancelled", tid)
        except BaseException as exc:  # every failure is an answer, never a dead worker
            from app.session.export import ExportCancelled

            if isinstance(exc, ExportCancelled):
                message = ("cancelled", tid)
            else:
                message = ("failed", tid, _failure(exc), traceback.format_exc())
                logging.getLogger("app.worker").error("task %s (%s) failed:\n%s", tid, kind, message[3])
        with lock:
            flags.pop(tid, None)
        if ctx.retire:  # the application must not send this worker another task: it ends after this answer
            message = (*message, "retire") if message[0] != "cancelled" else (*message, None, None, "retire")
        try:
            sender.send(*message)
        except LinkClosed:
            os._exit(0)
        except Exception as exc:  # a result that cannot be sent
            sender.send("failed", tid, f"the result could not be handed back ({type(exc).__name__}: {exc}).",
                        traceback.format_exc())
        if ctx.retire:
            sys.stderr.flush()
            os._exit(0)
