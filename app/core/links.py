"""The serial links' facts, written once (issue #40).

A simulated device's serial link is a file in the run's runtime folder (the pty's name, or the socket's stand-in):
the driver that opens it, the registry that describes it to the simulator process and that process itself must
agree on the path before the process starts, so :func:`simulator_link` is the one place that names it. The serial
rates a link is opened at unless its device fixes its own (the LINarm's in the configuration, ScienceMode's in
``app/devices/rehastim.py``), the range a configured rate must lie in, and the loopback address a simulated link
served on a TCP socket uses (:func:`socket_link_url`) are written here too.

Qt-free (floor: core); the simulator process imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

LOOPBACK: Final = "127.0.0.1"  # where the simulators' links, their helpers and the UDP peers listen by default
DEFAULT_BAUDRATE: Final = 115200  # a serial link's rate when its device does not fix one
BAUDRATE_RANGE: Final = (1200, 4_000_000)  # Bd: what a configuration may give (pyserial's reach on a USB UART)
LINK_SUFFIX: Final = ".tty"


def simulator_link(runtime_dir: Path, device: str) -> Path:
    """Where the simulated ``device`` (its id, ``app.core.streams``) has its serial link in ``runtime_dir``."""
    return runtime_dir / f"{device}{LINK_SUFFIX}"


def socket_link_url(port: int) -> str:
    """The pyserial URL of a simulated serial link served on a loopback TCP ``port`` (where there are no ptys,
    or ``simulation.link: socket``): the simulator host gives it, the driver opens it."""
    return f"socket://{LOOPBACK}:{port}"
