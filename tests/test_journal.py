"""One journal (issue #40): every origin's records reach one bus subscription in publish order; the supervisor, the
fault policy and the exercise's progress are Qt-free; no QObject in app/ overrides ``QObject.event``; a driver's
device event reaches the bus and its Qt signal from one call."""

from __future__ import annotations

import ast
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from app.core import journal, streams
from app.core.bus import StreamBus
from app.core.config import AppConfig, SafetyConfig
from app.core.journal import Record
from app.core.progress import ExerciseProgress
from app.safety.fault_policy import FaultPolicy
from app.safety.supervisor import AlarmLevel, SafetySupervisor, StopAction
from tests.test_architecture import APP, import_graph, reachable

QT_FREE = ("app.core.journal", "app.safety.supervisor", "app.safety.fault_policy", "app.core.progress")


def test_records_of_each_origin_reach_one_subscription_in_order() -> None:
    bus = StreamBus()
    supervisor = SafetySupervisor(SafetyConfig(), bus=bus)
    stopped: list[str] = []
    supervisor.add_stop_action(StopAction("FES Stop", stopped.append))
    policy = FaultPolicy(supervisor, bus, lambda _name: None)
    progress = ExerciseProgress(lambda kind, **data: bus.record(journal.PROGRESS, kind, data))
    with bus.subscribe("test", (), events=True, records=True) as sub:
        bus.event(streams.LINARM, journal.CONNECTED, "serial")  # a device
        supervisor.record(journal.DEVICE_TOGGLED, device="fes", running=True)  # the application, through safety
        supervisor.raise_alarm(AlarmLevel.STOP, "fes", "stimulator lost")  # the supervisor, then the fault policy
        bus.record(journal.RUN, journal.RUN_START, {"run_id": "run-1"})  # a run
        progress.begin("reach.py", 2)
        progress.start_repetition(1)  # the exercise's progress
        bus.event(streams.LINARM, journal.CONTROLLER_ERROR, "LINarm error: WATCHDOG")
        got = [(r.origin, r.kind) for r in sub.drain() if isinstance(r, Record)]
    assert got == [
        ("linarm", "connected"),
        ("safety", "device_toggled"),
        ("safety", "alarm"),
        ("safety", "fault"),  # what the policy did follows what it answered
        ("safety", "safe_state_action"),
        ("run", "run_start"),
        ("progress", "repetition_start"),
        ("linarm", "controller_error"),
    ]
    assert stopped == ["fes: stimulator lost"] and policy.last_cause == "fes: stimulator lost"


def test_the_session_records_queue_never_drops_a_journal_record() -> None:
    bus = StreamBus()
    with bus.subscribe("slow", (), events=True, records=True, keep_records=True, maxlen=3) as sub:
        bus.record(journal.SAFETY, journal.ALARM, {"text": "kept"})
        for k in range(10):
            bus.event("dev", journal.SILENT, str(k))
        items = sub.drain()
    assert [(r.kind, r.detail) for r in items if isinstance(r, Record) and r.from_device] == [
        ("silent", "8"), ("silent", "9")]
    assert [r.data["text"] for r in items if isinstance(r, Record) and not r.from_device] == ["kept"]
    assert sub.dropped == 8
    with bus.subscribe("display", (), events=True, records=True, maxlen=3) as display:  # a display's: bounded
        for k in range(5):
            bus.record(journal.SAFETY, journal.ROBOT_COMMAND, {"k": k})
        assert [r.data["k"] for r in display.drain() if isinstance(r, Record)] == [2, 3, 4]
        assert display.dropped == 2


def test_the_supervisor_the_fault_policy_and_the_progress_import_no_qt() -> None:
    internal, external = import_graph()
    for name in QT_FREE:
        for module, via in {name: name, **reachable(internal, name)}.items():
            qt = external.get(module, set()) & {"PySide6", "shiboken6", "pyqtgraph"}
            assert not qt, f"{name} imports Qt through {module} (imported by {via})"
    for cls in (SafetySupervisor, FaultPolicy, ExerciseProgress):
        assert all(base.__module__.partition(".")[0] != "PySide6" for base in cls.__mro__), cls


# The wire's facts (protocol tables, codecs, constants): the ground floor, below the safety floor (layout of #40).
WIRE = frozenset({"app.wire.cmdmessenger", "app.wire.linarm_constants", "app.wire.linarm_protocol",
                  "app.wire.sciencemode", "app.wire.physio_codec", "app.wire.udp_frames"})


def test_the_fault_policy_does_not_import_the_drivers_even_for_types() -> None:
    internal, _external = import_graph()
    upward = {m for m in internal["app.safety.fault_policy"] if m.startswith("app.devices") and m not in WIRE}
    assert not upward, upward


CLASS_LINE = re.compile(r"^[ \t]*class[ \t]+(\w+)[ \t]*\(([^)]*)\)", re.MULTILINE)


def _qobject_classes(sources: dict[Path, str]) -> set[str]:
    """Every class of app/ deriving from a Qt class (a base named Q…), directly or through another class of app/
    (read with a regular expression: quick, and a class line is simple enough)."""
    bases = {name: {b.strip().rpartition(".")[2] for b in text.split(",") if b.strip()}
             for source in sources.values() for name, text in CLASS_LINE.findall(source)}
    qt: set[str] = set()
    changed = True
    while changed:
        changed = False
        for name, names in bases.items():
            if name not in qt and any((b.startswith("Q") and b[1:2].isupper()) or b in qt for b in names):
                qt.add(name)
                changed = True
    return qt


def qobject_event_overrides(root: Path = APP) -> list[str]:
    sources = {p: p.read_text(encoding="utf-8") for p in sorted(root.rglob("*.py"))}
    qt = _qobject_classes(sources)
    found = []
    for path, source in sources.items():
        if "def event(" not in source:
            continue
        for node in ast.walk(ast.parse(source, str(path))):
            if isinstance(node, ast.ClassDef) and node.name in qt:
                found += [f"{path.relative_to(root.parent)}:{item.lineno} {node.name}.event" for item in node.body
                          if isinstance(item, ast.FunctionDef) and item.name == "event"]
    return found


def test_no_qobject_in_app_overrides_qobject_event() -> None:
    """``QObject.event(QEvent) -> bool`` is how Qt delivers its events: an override with another meaning (the old
    ``SafetySupervisor.event(kind, **data)``) logs every Qt event as a safety event and answers None."""
    assert qobject_event_overrides() == []


def test_the_ast_check_sees_an_override(tmp_path: Path) -> None:
    (tmp_path / "app").mkdir()
    (tmp_path / "app" / "mod.py").write_text(
        "from PySide6.QtCore import QObject\n\nclass Base(QObject):\n    pass\n\n"
        "class Supervisor(Base):\n    def event(self, kind, **data):\n        pass\n", encoding="utf-8")
    assert qobject_event_overrides(tmp_path / "app") == ["app/mod.py:7 Supervisor.event"]


def test_a_driver_event_reaches_the_bus_and_its_signal_from_one_call(qtbot) -> None:
    from app.devices.linarm import LinarmDriver

    class NoLink:  # the driver is never started: only its publishing call is used
        pass

    bus = StreamBus()
    driver = LinarmDriver(NoLink(), SafetySupervisor(AppConfig().safety, bus=bus), bus=bus)  # type: ignore[arg-type]
    said: list[str] = []
    driver.controller_error.connect(said.append)
    with bus.subscribe("test", (), events=True) as sub:
        record = driver._fire_event(journal.CONTROLLER_ERROR, "LINarm error: TRACKING_ERROR")
        got = sub.drain()
    assert got == [record] and record.origin == "linarm" and record.detail == "LINarm error: TRACKING_ERROR"
    assert said == ["LINarm error: TRACKING_ERROR"]


def test_the_stimulators_records_and_their_qt_faces_come_from_one_call(qtbot) -> None:
    from app.devices.rehastim import FesDriver

    class NoLink:  # the driver is never started: only its publishing call is used
        pass

    bus = StreamBus()
    driver = FesDriver(NoLink(), SafetySupervisor(AppConfig().safety, bus=bus), bus=bus)  # type: ignore[arg-type]
    records: list[tuple[str, str, dict[str, Any]]] = []
    bus.listen("test", lambda r: records.append((r.origin, r.kind, dict(r.data))))
    faults: list[str] = []
    changes: list[bool] = []
    driver.fault.connect(faults.append)
    driver.stimulation_changed.connect(changes.append)
    driver._record(journal.FES_FAULT, ("link lost",), text="link lost")
    driver._record(journal.FES_STOPPED, (False,), reason="link lost", source="fes driver")
    assert records == [("safety", "fes_fault", {"text": "link lost"}),
                       ("safety", "fes_stopped", {"reason": "link lost", "source": "fes driver"})]
    assert faults == ["link lost"] and changes == [False]


def test_a_journal_listener_hears_the_supervisors_records_until_it_is_closed() -> None:
    """The supervisor's records reach a listener on its bus (the one publishing path: it keeps no subscriber list of
    its own), and a closed listener hears nothing more and leaves no subscription behind."""

    class Log:
        def __init__(self) -> None:
            self.kinds: list[str] = []

        def on(self, kind: str, data: Mapping[str, Any]) -> None:
            self.kinds.append(kind)

    supervisor = SafetySupervisor(SafetyConfig())
    seen = Log()
    listener = supervisor.bus.listen("test", lambda r: seen.on(r.kind, r.data))
    supervisor.emergency_stop("test")
    listener.close()
    supervisor.reset_emergency_stop("tester")
    assert seen.kinds == ["emergency_stop", "alarm"] and supervisor.bus.subscriptions() == []


def test_the_adapter_turns_the_supervisors_records_into_the_windows_signals(qtbot) -> None:
    """An e-stop from a script's thread reaches the window's adapter as ``estop_changed`` at its next tick, with the
    alarm (the supervisor's own object) and the lease changes beside it."""
    import threading

    from app.core.ownership import ROBOT, Lease
    from app.ui.qt_bus import QtBus

    bus = StreamBus()
    supervisor = SafetySupervisor(SafetyConfig(), bus=bus)
    adapter = QtBus(bus, alarms=supervisor.alarm)
    alarms: list[Any] = []
    leases: list[bool] = []
    adapter.alarm_raised.connect(alarms.append)
    adapter.lease_changed.connect(lambda: leases.append(True))
    with qtbot.waitSignal(adapter.estop_changed, timeout=1000) as latched:
        worker = threading.Thread(target=supervisor.emergency_stop, args=("api", "from a script"))
        worker.start()
        worker.join()
    assert latched.args == [True, "from a script (api)"]
    assert [a.text for a in alarms] == ["Emergency stop: from a script"] and alarms[0] is supervisor.alarms()[0]
    supervisor.reset_emergency_stop("tester")
    supervisor.take_lease(Lease("run-1", "the exercise", frozenset({ROBOT}), ("exercise",)))
    with qtbot.waitSignal(adapter.estop_changed, timeout=1000) as reset:
        pass
    assert reset.args == [False, ""]
    qtbot.waitUntil(lambda: leases == [True], timeout=1000)
    adapter.close()
