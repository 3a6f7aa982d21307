"""What :meth:`app.session.recording.SessionRecorder.start` uses of the application (app.therapy.services.SessionHost),
around
test drivers: a stream bus with their streams declared, the supervisor, the devices, a fault policy and a
shutdown hook that do nothing. A :class:`tests.fakes.ListenerDriver`'s listeners publish on that bus, so a test
that feeds samples through them (``for fn in driver.listeners: fn(stream, t, sample)``) records them."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from app.core.bus import StreamBus
from app.core.config import AppConfig
from app.safety.supervisor import SafetySupervisor


def recorder_host(config: AppConfig, devices: dict[str, Any], supervisor: SafetySupervisor | None = None,
                  bus: StreamBus | None = None) -> SimpleNamespace:
    bus = bus or StreamBus()
    for name, driver in devices.items():
        bus.declare(driver.streams)
        listeners = getattr(driver, "listeners", None)
        if isinstance(listeners, list):  # a ListenerDriver: what it is fed goes on the bus
            listeners.append(lambda stream, t, sample: bus.publish(stream, t, sample))
        events = getattr(driver, "event_listeners", None)
        if isinstance(events, list):
            events.append(lambda event, detail, device=name: bus.event(device, event, detail))
    return SimpleNamespace(config=config, bus=bus, supervisor=supervisor or SafetySupervisor(config.safety),
                           devices={n: SimpleNamespace(driver=d, simulated=True) for n, d in devices.items()},
                           fault_policy=SimpleNamespace(recording_failed=lambda folder, error: None),
                           add_shutdown_hook=lambda fn: None)
