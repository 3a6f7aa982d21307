"""The script kernel's warden: a small parent that owns every process a script starts (standard library only).

Started by :class:`app.scripting.kernel_process.KernelProcess` as
``python -I warden.py SOCK_FD MEMORY_LIMIT CONTROL_FD NICE``
in a session of its own. It makes itself a *child subreaper* (Linux ``prctl(PR_SET_CHILD_SUBREAPER)``), forks,
and the child execs the kernel (``python -I kernel.py SOCK_FD MEMORY_LIMIT``). From then on every process the
script starts stays below the warden, whatever it does: ``setsid``, a double fork, its parent's death — an
orphan is re-parented to the nearest subreaper, i.e. here, never to init. The warden ends them all (SIGKILL,
repeated until none is left):

* when the kernel has ended (however: exit, crash, killed), before it exits itself — with the kernel's own
  status (an exit code, or the same signal), so the application reads the kernel's end from the warden's;
* on ``sweep`` (the end of every script run): every process except the kernel, which serves the prompt on;
* on ``kill`` / ``term`` from the application (Stop's escalation), and when the control link closes — the
  application exited or was killed; the link is an inherited socket, nothing a script can hold open (the
  kernel closes its copy before it execs).

Why not a process group, a cgroup, or a scan for holders of the kernel's socket (decisions.md, "Script
kernel processes"): ``setsid`` leaves any process group (that is how the probe's child outlived Stop for
39 min); cgroups need a delegated hierarchy a desktop session does not always give; a socket or an
environment marker is dropped by one ``close``. The subreaper follows parentage, which a process cannot
leave. What it cannot stop is a script that kills the warden itself (same user): the kernel then dies with
it (``PR_SET_PDEATHSIG``), but the kernel's own children would go to init. A process is not a sandbox.

Control protocol (lines): warden → application ``pid N`` once; application → warden ``sweep`` (answered
``swept N``), ``term``, ``kill``.
"""

from __future__ import annotations

import ctypes
import os
import resource
import select
import signal
import socket
import sys
import time

PR_SET_PDEATHSIG = 1
PR_SET_CHILD_SUBREAPER = 36
KERNEL_FILE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "kernel.py")
SWEEP_LIMIT_S = 2.0  # SIGKILL passes until no descendant is left (a fork bomb converges: killed ones cannot fork)


def _prctl(option: int, value: int) -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(option, ctypes.c_ulong(value), 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0].decode()
    except (OSError, IndexError):
        return "X"


def _children(pid: int) -> list[int] | None:
    """``pid``'s children from /proc/<pid>/task/*/children (None where the kernel does not offer them)."""
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return []
    out: list[int] = []
    for tid in tasks:
        try:
            with open(f"/proc/{pid}/task/{tid}/children", "rb") as f:
                out.extend(int(p) for p in f.read().split())
        except FileNotFoundError:
            return None
        except (OSError, ValueError):
            continue
    return out


def _all_children() -> dict[int, list[int]]:
    """parent → children of every process, from each /proc/<pid>/stat (the slow way: ~13 ms under load)."""
    children: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return children
    for entry in entries:
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as f:
                    ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry))
    return children


def descendants(root: int) -> list[int]:
    """Living (non-zombie) processes below ``root``: walked down from ``root`` (its subtree only), or from a
    scan of every process where /proc/<pid>/task/<tid>/children is missing."""
    table: dict[int, list[int]] | None = None
    out: list[int] = []
    todo = [root]
    seen = {root}
    while todo:
        pid = todo.pop()
        kids = _children(pid) if table is None else table.get(pid, [])
        if kids is None:
            table = _all_children()
            kids = table.get(pid, [])
        for kid in kids:
            if kid not in seen:
                seen.add(kid)
                todo.append(kid)
                if _state(kid) not in ("Z", "X"):
                    out.append(kid)
    return out


class Warden:
    def __init__(self, kernel_pid: int, control: socket.socket) -> None:
        self.kernel = kernel_pid
        self.control = control
        self.kernel_status: int | None = None
        self.me = os.getpid()

    def reap(self) -> None:
        while True:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if pid == 0:
                return
            if pid == self.kernel:
                self.kernel_status = status

    def kill_below(self, spare_kernel: bool) -> int:
        """SIGKILL every descendant (except the kernel when ``spare_kernel``) until none is left."""
        killed: set[int] = set()
        deadline = time.monotonic() + SWEEP_LIMIT_S
        while time.monotonic() < deadline:
            targets = [p for p in descendants(self.me) if not (spare_kernel and p == self.kernel)]
            if not targets:
                break
            for pid in targets:
                try:
                    os.kill(pid, signal.SIGKILL)
                    killed.add(pid)
                except OSError:
                    pass
            self.reap()
            time.sleep(0.002)
        self.reap()
        return len(killed - {self.kernel})

    def signal_kernel(self, sig: int) -> None:
        if self.kernel_status is None:
            try:
                os.kill(self.kernel, sig)
            except OSError:
                pass

    def serve(self) -> None:
        wake_r, wake_w = os.pipe()
        os.set_blocking(wake_w, False)
        signal.set_wakeup_fd(wake_w)
        signal.signal(signal.SIGCHLD, lambda *_: None)  # only to wake the select
        signal.signal(signal.SIGTERM, lambda *_: self.signal_kernel(signal.SIGTERM))
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        buf = b""
        control_open = True
        while True:
            self.reap()
            if self.kernel_status is not None:
                return
            fds = [wake_r] + ([self.control] if control_open else [])
            try:
                ready, _, _ = select.select(fds, [], [], 0.5)
            except InterruptedError:
                continue
            if wake_r in ready:
                try:
                    os.read(wake_r, 512)
                except OSError:
                    pass
            if control_open and self.control in ready:
                try:
                    data = self.control.recv(4096)
                except OSError:
                    data = b""
                if not data:  # the application is gone (or closed the link): nothing may outlive it
                    control_open = False
                    self.signal_kernel(signal.SIGKILL)
                    self.kill_below(spare_kernel=False)
                    continue
                buf += data
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    self.command(line.strip().decode("ascii", "replace"))
                buf = buf[-64:]

    def command(self, text: str) -> None:
        if text == "sweep":
            n = self.kill_below(spare_kernel=True)
            self.send(f"swept {n}\n")
        elif text == "term":
            self.signal_kernel(signal.SIGTERM)
        elif text == "kill":
            self.signal_kernel(signal.SIGKILL)

    def send(self, text: str) -> None:
        try:
            self.control.sendall(text.encode())
        except OSError:
            pass


def _mirror(status: int) -> None:
    """End this process as the kernel ended (the application reads the kernel's end from ours)."""
    if os.WIFSIGNALED(status):
        sig = os.WTERMSIG(status)
        try:
            resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
            signal.signal(sig, signal.SIG_DFL)
        except (OSError, ValueError):
            pass
        signal.pthread_sigmask(signal.SIG_UNBLOCK, [sig])
        os.kill(os.getpid(), sig)
        time.sleep(0.1)
        os._exit(128 + sig)
    os._exit(os.WEXITSTATUS(status) if os.WIFEXITED(status) else 1)


def _ordinary_priority(nice: int) -> None:
    """The script's processes run as an ordinary program: the normal policy at ``nice`` (absolute), whatever the
    application thread that started the warden runs at. That thread may run raised (nice -5, or a device link's
    SCHED_RR: app/core/priority.py, app/devices/realtime.py), and Linux hands a thread's nice value and policy to
    the processes it starts; a busy-waiting script (the seeds' ``waitCondition``) would then share the CPU equally
    with the window and the drivers instead of yielding to them. Lowering is always allowed."""
    if hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        except OSError:
            pass
    if hasattr(os, "setpriority"):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
        except OSError:  # raising back to ``nice`` from a lower priority needs CAP_SYS_NICE: stays lower
            pass


def main(argv: list[str]) -> None:
    sock_fd, memory_limit, control_fd = argv[1], argv[2], int(argv[3])
    _ordinary_priority(int(argv[4]) if len(argv) > 4 else 0)  # before the fork: the kernel inherits it
    _prctl(PR_SET_CHILD_SUBREAPER, 1)  # Linux; elsewhere orphans go to init and only direct children are ended
    warden_pid = os.getpid()
    pid = os.fork()
    if pid == 0:  # the kernel: no way back to the warden's control link, and it dies with the warden
        try:
            os.close(control_fd)
            _prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
            if os.getppid() != warden_pid:
                os._exit(1)
            os.execv(sys.executable, [sys.executable, "-I", KERNEL_FILE, sock_fd, memory_limit])
        finally:
            os._exit(127)
    os.close(int(sock_fd))  # only the kernel (and what it starts) holds the script's link
    control = socket.socket(fileno=control_fd)
    warden = Warden(pid, control)
    warden.send(f"pid {pid}\n")
    warden.serve()
    warden.kill_below(spare_kernel=False)
    assert warden.kernel_status is not None
    _mirror(warden.kernel_status)


if __name__ == "__main__":
    main(sys.argv)
