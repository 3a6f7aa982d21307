"""A fresh start raises no "stopped sending data" warning (issue #19: physio and linarm warned at
every start): a device that has not sent its first sample yet has not *stopped* sending."""

from __future__ import annotations

import pytest

from app.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow


# The warnings are real on this shared 2-core machine (3 of 4 runs under Xvfb, 1 of 5 offscreen): the
# simulators run as threads of the GUI process and, while the GUI thread holds the interpreter (window
# construction; llvmpipe GL paints under Xvfb), they write nothing, so the drivers see 0.25 s of
# silence. Real serial bytes would wait in the OS buffer. The fix belongs to the simulator hosting
# (issue #16: simulators out of the GUI process); until then this documents it without failing CI.
@pytest.mark.xfail(reason="in-process simulators starved by the GUI thread (issue #16)", strict=False)
def test_no_silence_warning_at_a_fresh_start(qtbot) -> None:
    manager = LinarmppManager(AppConfig())
    manager.start()
    window = MainWindow(manager)
    qtbot.addWidget(window)
    window.show()
    try:
        qtbot.waitUntil(manager.all_connected, timeout=20000)
        qtbot.wait(3000)  # the startup, plus ten silence timeouts
        silent = [a.text for a in manager.supervisor.alarms() if "stopped sending" in a.text]
        assert not silent, silent
        assert window.alarm_banner.current is None or "stopped sending" not in window.alarm_banner.label.full_text()
    finally:
        window.close()
        manager.shutdown()
