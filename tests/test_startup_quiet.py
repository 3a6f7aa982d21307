"""A fresh start raises no "stopped sending data" warning (issue #19: physio and linarm warned at
every start): a device that has not sent its first sample yet has not *stopped* sending."""

from __future__ import annotations

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.ui.main_window import MainWindow


# The warnings were real while the simulators ran as threads of the GUI process (3 of 4 starts under
# Xvfb): while the GUI thread held the interpreter they wrote nothing. The app now hosts them in a
# process of their own (issue #16), as it would talk to real hardware: this test starts it that way.
def test_no_silence_warning_at_a_fresh_start(qtbot, monkeypatch) -> None:
    monkeypatch.setenv("LINARMPP_SIM_HOST", "process")  # the app's default (the suite's is threads)
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
