"""The serial links' facts, written once (issue #40).

A simulated device's serial link is a file in the run's runtime folder (the pty's name, or the socket's stand-in):
the driver that opens it, the registry that describes it to the simulator process and that process itself must
agree on the path before the process starts, so :func:`simulator_link` is the one place that names it. The serial
rates a link is opened at unless its device fixes its own (the LINarm's in the configuration, ScienceMode's in
``app/devices/rehastim.py``), and the range a configured rate must lie in, are written here too.

Qt-free (floor: core); the simulator process imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

DEFAULT_BAUDRATE: Final = 115200  # a serial link's rate when its device does not fix one
BAUDRATE_RANGE: Final = (1200, 4_000_000)  # Bd: what a configuration may give (pyserial's reach on a USB UART)
LINK_SUFFIX: Final = ".tty"


def simulator_link(runtime_dir: Path, device: str) -> Path:
    """Where the simulated ``device`` (its id, ``app.core.streams``) has its serial link in ``runtime_dir``."""
    return runtime_dir / f"{device}{LINK_SUFFIX}"
