"""The emulated MPS2 AN385 board with the firmware's image, from the host's side: qemu-system-arm with UART0 (the
LINarm protocol) and UART1 (the board console: STATUS, RESET, lockstep) on loopback TCP sockets. Used by
tests/test_firmware_mcu.py and bench/bench_mcu.py; the console's commands are listed in
firmware/host/mps2/board_main.cpp."""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

from app.devices.sim.host import free_tcp_port, qemu_mps2_command


class McuBoard:
    """qemu-system-arm running the image: UART0 (the protocol) and UART1 (the board console) on loopback TCP."""

    def __init__(self, image: Path, icount: int | None = None) -> None:
        self.uart0_port, console_port = free_tcp_port(), free_tcp_port()
        self.proc = subprocess.Popen(
            qemu_mps2_command(image, self.uart0_port,
                              f"tcp:127.0.0.1:{console_port},server=on,wait=off,nodelay=on", icount),
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            self.uart0 = self._connect(self.uart0_port)
            self.console = self._connect(console_port)
            self._console_buffer = b""
            self.hello = self._line(10.0)  # the UARTs are enabled: bytes may go now
            assert self.hello.startswith("HELLO "), self.hello
        except Exception:
            self.close()
            raise

    def _connect(self, port: int) -> socket.socket:
        deadline = time.monotonic() + 10.0
        while True:
            try:
                sock = socket.create_connection(("127.0.0.1", port), timeout=10.0)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                return sock
            except OSError:
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"qemu-system-arm did not listen on {port} (exit {self.proc.poll()})") from None
                time.sleep(0.05)

    def ask(self, line: str, timeout_s: float = 30.0) -> str:
        """One console command; its one-line answer."""
        self.console.sendall(line.encode() + b"\n")
        while True:
            answer = self._line(timeout_s)
            if not answer.startswith("HELLO "):  # greetings sent before the board heard us
                return answer

    def _line(self, timeout_s: float) -> str:
        self.console.settimeout(timeout_s)
        while b"\n" not in self._console_buffer:
            chunk = self.console.recv(4096)
            if not chunk:
                raise RuntimeError("the board console closed")
            self._console_buffer += chunk
        answer, self._console_buffer = self._console_buffer.split(b"\n", 1)
        return answer.decode()

    def status(self) -> dict[str, int]:
        words = self.ask("STATUS").split()
        assert words[0] == "STATUS", words
        return {k: int(v) for k, v in (w.split("=") for w in words[1:])}

    def read_uart0(self, count: int, timeout_s: float = 30.0) -> bytes:
        data = b""
        self.uart0.settimeout(timeout_s)
        while len(data) < count:
            chunk = self.uart0.recv(count - len(data))
            if not chunk:
                raise RuntimeError("UART0 closed")
            data += chunk
        return data

    def close(self) -> None:
        for name in ("uart0", "console"):
            sock = getattr(self, name, None)
            if sock is not None:
                sock.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if self.proc.stderr is not None:
            self.proc.stderr.close()
