"""Suite-wide set-up: a headless Qt platform when there is no display, a private data folder, and
the OpenGL rule (GL tests run only on xcb, e.g. under Xvfb; offscreen GL segfaults uncatchably)."""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
# Never write into the developer's real data folder or QSettings.
os.environ["LINARMPP_HOME"] = tempfile.mkdtemp(prefix="linarmpp-test-home-")
os.environ.setdefault("PYDEVD_DISABLE_FILE_VALIDATION", "1")
# A crash prints every thread's stack: pytest's faulthandler does it for this process (and faulthandler_timeout
# in pyproject.toml for a test that hangs); the Python processes the tests start (the app, the simulators, the
# helpers) inherit this. The script kernel runs isolated (-I) and ignores it.
os.environ.setdefault("PYTHONFAULTHANDLER", "1")
# The simulated devices run in a process of their own, as in the app: the test's process holds only the
# drivers, as it would with real hardware (and a loaded machine does not slow the simulators through this
# process's interpreter lock). Tests that look at the far end of a link (the bytes a simulator received, a
# fault injected into its core) host them as threads: modules in SIM_IN_THREAD_MODULES, tests marked
# ``sim_in_thread``.
os.environ.setdefault("LINARMPP_SIM_HOST", "process")
SIM_IN_THREAD_MODULES = {"test_device_loss", "test_device_loss_more", "test_fes_exit_paths", "test_physio_viewer"}

from app.application import prepare_qt  # noqa: E402 - must run before pytest-qt creates the app
from app.devices.sim.base import HOMED_ENV  # noqa: E402
from tests import rigs  # noqa: E402
from tests.rigs import _children, _os_threads, _python_threads  # noqa: E402

prepare_qt()


def screenshot_path(name: str) -> Path:
    """Where a test saves a screenshot: docs/screenshots when LINARMPP_SCREENSHOTS=1 (to refresh the
    docs), else a temporary folder, so a test run never changes the working tree."""
    if os.environ.get("LINARMPP_SCREENSHOTS") == "1":
        folder = ROOT / "docs" / "screenshots"
    else:
        folder = Path(tempfile.gettempdir()) / "linarmpp-test-screenshots"
    folder.mkdir(parents=True, exist_ok=True)
    return folder / name


def gl_available() -> bool:
    from PySide6.QtGui import QGuiApplication

    return QGuiApplication.platformName() == "xcb"


@pytest.fixture
def require_gl(qapp) -> None:
    """Skip before any GL widget exists unless Qt runs on a real X server."""
    if not gl_available():
        pytest.skip(f"OpenGL needs xcb (Xvfb); platform is {qapp.platformName()!r}")


@pytest.fixture(autouse=True, scope="session")
def _qt_identity(qapp):
    from app.application import configure_qt_identity

    configure_qt_identity()
    from app.main_thread_gc import collect_on_the_main_thread

    # As in the app: the collector runs on this (the main) thread only, from the application's timer during a
    # test's waits and after each test (below) -- a widget of an earlier test caught in a cycle was destroyed on a
    # dialog's loading thread by an automatic collection there: a segmentation fault in the suite (#38).
    # A full walk of a worker's heap (every earlier test's objects: 100-300 ms) only between tests, never inside a
    # turn a test measures (the window's heap policy plays this part in the app).
    collect_on_the_main_thread(qapp).full_allowed = lambda: _BETWEEN_TESTS[0]
    yield


_BETWEEN_TESTS = [False]


# A modal question nobody answers in a test's teardown (a window closed after a failure asks "Stop it and quit?")
# held the worker until the timeout, and pytest-timeout could not end a nested Qt event loop: the run hung. It is
# answered here after MODAL_TEARDOWN_S, with the button that lets the teardown go on, and the test fails saying so.
MODAL_TEARDOWN_S = 5.0


def _answer_modal_questions(started: float, answered: list[str]) -> None:
    from PySide6.QtWidgets import QApplication, QDialog, QMessageBox

    modal = QApplication.activeModalWidget()
    if modal is None or time.monotonic() - started < MODAL_TEARDOWN_S:
        return
    answered.append(f"{type(modal).__name__} {modal.windowTitle()!r}: "
                    f"{modal.text() if isinstance(modal, QMessageBox) else ''}")
    if isinstance(modal, QMessageBox):
        for button in modal.buttons():
            if modal.buttonRole(button) in (QMessageBox.ButtonRole.YesRole, QMessageBox.ButtonRole.AcceptRole,
                                            QMessageBox.ButtonRole.DestructiveRole):
                button.click()
                return
    if isinstance(modal, QDialog):
        modal.reject()
    else:
        modal.close()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):  # type: ignore[no-untyped-def]
    from PySide6.QtCore import QCoreApplication, QTimer

    answered: list[str] = []
    timer = None
    if QCoreApplication.instance() is not None:
        started = time.monotonic()
        timer = QTimer()
        timer.setInterval(250)
        timer.timeout.connect(lambda: _answer_modal_questions(started, answered))
        timer.start()
    try:
        result = yield
    finally:
        if timer is not None:
            timer.stop()
            timer.deleteLater()
    if answered:
        raise AssertionError(f"a modal dialog waited in the teardown, answered after {MODAL_TEARDOWN_S:g} s: "
                             + "; ".join(answered))
    return result


@pytest.hookimpl(trylast=True, specname="pytest_runtest_teardown")
def pytest_runtest_teardown_collect(item, nextitem) -> None:  # type: ignore[no-untyped-def]
    from PySide6.QtCore import QCoreApplication, QEvent

    from app.main_thread_gc import collections

    # The test's widgets are destroyed in its own teardown. pytest-qt closes them and calls deleteLater(); its
    # processEvents() outside an event loop does not run deferred deletions, so they waited for the next event loop
    # of a later test: a worker's windows of several earlier tests (7 main windows, ~7 600 Destroy/ChildRemoved
    # events) were destroyed in one turn of tests/test_archive_browser_blocks.py's listing, 143-685 ms of its GUI
    # thread's CPU. Asked for explicitly, Qt runs the deletions posted outside any event loop here.
    if QCoreApplication.instance() is not None:
        QCoreApplication.sendPostedEvents(None, QEvent.Type.DeferredDelete)
    main_thread = collections()
    if main_thread is not None:
        _BETWEEN_TESTS[0] = True
        try:
            main_thread.collect_due()
        finally:
            _BETWEEN_TESTS[0] = False


# ------------------------------------------------------------------------------ reruns: realtime tests only
# Modules whose tests run simulated devices on the wall clock (their timing depends on the machine's load).
# Only these, and tests marked ``realtime``, get one rerun; a logic test that fails once fails.
REALTIME_MODULES = {
    "test_app_real_devices", "test_device_loss", "test_device_loss_more", "test_driver_base", "test_estop_wire",
    "test_fes_exit_paths", "test_firmware_sil", "test_linarm_driver", "test_metrics_e2e", "test_patient_model_link",
    "test_physio_driver", "test_rehastim_driver", "test_run_recover", "test_safety_properties", "test_seed_scripts",
    "test_sim_host",
}


# ------------------------------------------------------------------------------ realtime tests run ahead
# In the clinic the real-time process runs ahead of ordinary programs (app/core/priority.py: nice -5). In the suite
# the other test workers are those programs, and they ran at the same nice: the clinician's day, needing most of a
# core, then got a third of the machine beside two busy workers and its window missed the GUI watch's heartbeat
# (0.35-0.74 s stalls at random places: a paint, a layout, the idle loop; every quiet run of session 14). A test
# marked ``realtime`` runs with every thread of its worker at REALTIME_TEST_NICE, ahead of the workers running logic
# tests, and back at the worker's own priority after it. Where raising is refused, nothing changes.
REALTIME_TEST_NICE = -10


def _set_thread_nices(nice: int) -> bool:
    """Every thread of this worker at ``nice``; False where the system refuses (no CAP_SYS_NICE / RLIMIT_NICE)."""
    from app.core.priority import _thread_ids

    try:
        for tid in _thread_ids():
            with contextlib.suppress(ProcessLookupError):
                os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (PermissionError, AttributeError):
        return False
    return True


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):  # type: ignore[no-untyped-def]
    raised = False
    if item.get_closest_marker("realtime") is not None and os.path.isdir("/proc/self/task"):
        base = os.getpriority(os.PRIO_PROCESS, 0)
        raised = base > REALTIME_TEST_NICE and _set_thread_nices(REALTIME_TEST_NICE)
    yield
    if raised:
        from app.core import priority

        outcome = priority._outcome  # raised for the process by a manager during the test: it stays raised
        _set_thread_nices(min(base, priority.REALTIME_NICE) if outcome is not None and outcome.raised else base)


# A rerun says why: the first attempt's failure, printed at the end of the run (pytest-rerunfailures lists the
# rerun tests only, and a flake that is not seen cannot be fixed).
_RERUN_REASONS: list[str] = []


def pytest_runtest_logreport(report) -> None:  # type: ignore[no-untyped-def]
    if report.outcome != "rerun":
        return
    crash = getattr(report.longrepr, "reprcrash", None)
    text = crash.message if crash is not None else str(report.longrepr)
    where = f" ({crash.path}:{crash.lineno})" if crash is not None else ""
    _RERUN_REASONS.append(f"{report.nodeid} [{report.when}]{where}: {' / '.join(text.splitlines()[:6])[:600]}")


def _scheduling_granted() -> str:
    """What the OS grants the suite's processes (CI's container may refuse both): real-time scheduling for the
    device links' threads (app/devices/realtime.py) and a raised nice for the real-time process
    (app/core/priority.py). Asked from a throwaway thread, so nothing of this process changes."""
    import threading

    answers: list[str] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_RR, os.sched_param(1))
            answers.append("real-time scheduling granted")
        except (OSError, AttributeError):
            answers.append("real-time scheduling refused")
        try:
            os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) - 1)
            answers.append("raised priority granted")
        except (OSError, AttributeError):
            answers.append("raised priority refused")

    thread = threading.Thread(target=probe, name="scheduling probe")
    thread.start()
    thread.join()
    return ", ".join(answers)


def pytest_terminal_summary(terminalreporter) -> None:  # type: ignore[no-untyped-def]
    if not hasattr(terminalreporter.config, "workerinput"):  # timing tests read differently without them
        terminalreporter.write_line(f"[suite] {_scheduling_granted()}")
    if _RERUN_REASONS:
        terminalreporter.write_sep("=", "why each rerun was needed")
        for line in _RERUN_REASONS:
            terminalreporter.write_line(line)


# ------------------------------------------------------------------------------ builds ahead
def pytest_configure(config) -> None:  # type: ignore[no-untyped-def]
    """The pytest-xdist controller of a whole-suite run makes the firmware's builds while its workers start
    (tests/firmware_builds.py): not at full priority beside the real-time tests later."""
    whole_suite = not config.args or any(Path(a).resolve() == ROOT / "tests" for a in config.args)
    controller = getattr(config.option, "numprocesses", None) and not hasattr(config, "workerinput")
    if controller and whole_suite:
        from tests import firmware_builds

        config._firmware_prebuild = firmware_builds.prebuild()
    if hasattr(config, "workerinput"):
        config.pluginmanager.register(_XdistGroupIds(), "linarmpp-xdist-group-ids")


class _XdistGroupIds:
    """pytest-xdist 3.8 groups a test (``--dist loadgroup``) by appending ``@group`` to ``item._nodeid``; pytest 9
    reads a node's id from ``item._id`` instead, so no group reached the scheduler and every xdist_group was split
    over the workers (each built the module's rig, installed venv or server again). This copies the grouped id
    where pytest 9 reads it, after xdist's own hook."""

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, items) -> None:  # type: ignore[no-untyped-def]
        try:
            from _pytest.nodes import coerce_node_id
        except ImportError:  # pytest 8: the id is _nodeid itself
            return
        for item in items:
            grouped = getattr(item, "_nodeid", None)
            if isinstance(grouped, str) and "@" in grouped and grouped != item.nodeid:
                item._id = coerce_node_id(grouped)


def pytest_unconfigure(config) -> None:  # type: ignore[no-untyped-def]
    thread = getattr(config, "_firmware_prebuild", None)
    if thread is not None:  # no CMake left running after the suite
        from tests.firmware_builds import BUILD_TIMEOUT_S

        thread.join(BUILD_TIMEOUT_S)


# ------------------------------------------------------------------------------ order and workers
# The modules with a test marked ``slow`` (or listed here) run first, whole, in their usual order: the long
# tests start early on both pytest-xdist workers, and the short ones fill in at the end (no long tail of one
# worker); a module's tests stay together, so its module-scoped fixtures are built once per worker.
SLOW_MODULES = {"test_clinician_day"}
# Modules that share one worker, one after the other (one xdist group). The emulated board's qemu runs at SCHED_RR
# (app/devices/sim/host.py: its timing needs it) and keeps up to a core busy per thread: beside it on the 2-core
# machine the clinician's day's window was starved for 0.7 s, and its GUI watch stopped the therapy as it must
# (quiet suites of session 14; the day beside test_firmware_mcu alone: 3 stall warnings, 0 with qemu not RR).
ONE_WORKER = {"test_clinician_day": "the emulated board and the clinician's day",
              "test_firmware_mcu": "the emulated board and the clinician's day"}


def _module_name(item) -> str:  # type: ignore[no-untyped-def]
    return item.module.__name__.rsplit(".", 1)[-1] if item.module is not None else ""


def _uses_its_module_fixture(item) -> bool:  # type: ignore[no-untyped-def]
    """Whether the test uses a module- or class-scoped fixture defined in its own module (not a conftest's)."""
    info = getattr(item, "_fixtureinfo", None)
    module_id = item.nodeid.split("::", 1)[0]
    return info is not None and any(
        fixture.scope in ("module", "class") and fixture.baseid == module_id
        for fixtures in info.name2fixturedefs.values() for fixture in fixtures)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist's worker turns the xdist_group marks into its groups
def pytest_collection_modifyitems(config, items) -> None:  # type: ignore[no-untyped-def]
    reruns = config.pluginmanager.hasplugin("rerunfailures")
    xdist = config.pluginmanager.hasplugin("xdist")
    slow_modules = set(SLOW_MODULES)
    for item in items:
        module = _module_name(item)
        if module in REALTIME_MODULES and item.get_closest_marker("realtime") is None:
            item.add_marker(pytest.mark.realtime)
        if reruns and item.get_closest_marker("realtime") is not None and item.get_closest_marker("flaky") is None:
            item.add_marker(pytest.mark.flaky(reruns=1, reruns_delay=1))
        if item.get_closest_marker("slow") is not None:
            slow_modules.add(module)
        if xdist and module in ONE_WORKER and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(name=ONE_WORKER[module]))
        # A module's shared rig (tests/rigs.py) is built once: its tests go to one worker (--dist loadgroup).
        if xdist and "shared_manager" in getattr(item, "fixturenames", ()) \
                and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(name=f"rig:{module}"))
        # So is any module-scoped fixture the module defines (an installed venv, a PostgreSQL server, a window):
        # split over two workers, each built its own (test_install installed the wheel twice, ~20 s each).
        if xdist and item.get_closest_marker("xdist_group") is None and _uses_its_module_fixture(item):
            item.add_marker(pytest.mark.xdist_group(name=f"module:{module}"))
    order = {id(item): n for n, item in enumerate(items)}
    items.sort(key=lambda item: (_module_name(item) not in slow_modules, order[id(item)]))


@pytest.fixture(autouse=True, scope="module")
def _simulators_for_the_module(request):  # type: ignore[no-untyped-def]
    """Module scope, so that module-scoped rigs are built with it too: the simulators as threads
    (SIM_IN_THREAD_MODULES), a homed LINarm (``pytestmark = pytest.mark.sim_homed``)."""
    module = request.module.__name__.rsplit(".", 1)[-1] if request.module is not None else ""
    with pytest.MonkeyPatch.context() as patch:
        if module in SIM_IN_THREAD_MODULES:
            patch.setenv("LINARMPP_SIM_HOST", "thread")
        if request.node.get_closest_marker("sim_homed") is not None:
            patch.setenv(HOMED_ENV, "1")
        yield


@pytest.fixture(autouse=True)
def _simulators_for_the_test(request, monkeypatch):  # type: ignore[no-untyped-def]
    if request.node.get_closest_marker("sim_in_thread") is not None:
        monkeypatch.setenv("LINARMPP_SIM_HOST", "thread")
    if request.node.get_closest_marker("sim_homed") is not None:
        monkeypatch.setenv(HOMED_ENV, "1")
    yield


# ------------------------------------------------------------------------------ rigs (tests/rigs.py)
# How a test gets its devices (issue #38; docs/decisions.md "Tests: the suite in 7 minutes"):
# * ``shared_manager``: the module's connected rig (one LinarmppManager and its simulators for the module's
#   tests), put back in its known state before and after the test, and checked (a reset that fails, fails the
#   test). Which rig: override the module-scoped ``shared_rig_spec`` fixture (default: LINarm + FES, homed).
# * ``fresh_manager``, or ``shared_manager`` in a test marked ``fresh_rig``: a manager of its own from the same
#   spec (for a test that kills, reconfigures or needs the power-up state), shut down after it.
# * a homed LINarm without a rig: ``pytest.mark.sim_homed`` on the test or the module (LINARMPP_SIM_HOMED).
# * anything else: build a LinarmppManager in the test as before (and shut it down).
@pytest.fixture(scope="module")
def shared_rig_spec():  # type: ignore[no-untyped-def]
    from tests.rigs import RigSpec

    return RigSpec()


@pytest.fixture(scope="module")
def _shared_rig(shared_rig_spec, qapp, _simulators_for_the_module):  # type: ignore[no-untyped-def]
    from tests.rigs import SharedRig

    rig = SharedRig(shared_rig_spec)
    try:
        yield rig
    finally:
        rig.close()


@pytest.fixture
def shared_manager(request):  # type: ignore[no-untyped-def]
    if request.node.get_closest_marker("fresh_rig") is not None:
        yield request.getfixturevalue("fresh_manager")
        return
    rig = request.getfixturevalue("_shared_rig")
    rig.reset()
    yield rig.manager
    rig.reset()


@pytest.fixture
def fresh_manager(shared_rig_spec, qapp):  # type: ignore[no-untyped-def]
    from tests.rigs import build_manager

    manager = build_manager(shared_rig_spec)
    try:
        yield manager
    finally:
        manager.shutdown()


# ------------------------------------------------------------------------------ the station's archive
@pytest.fixture
def no_station_left():  # type: ignore[no-untyped-def]
    """A test that installs a station archive (app.archive.station) leaves none installed, and closes it."""
    yield
    from app.archive import station

    left = station.uninstall()
    if left is not None:
        left.close()


# ------------------------------------------------------------------------------ logging set up by a test
@pytest.fixture(autouse=True)
def _logging_set_up_by_the_test():  # type: ignore[no-untyped-def]
    """The application configures the root logger once per process (app/core/logging_setup.py): a test that runs an
    entry point in-process would leave its console handler writing to that test's captured stderr, which pytest
    then closes — and every later log record, from any thread, printed "--- Logging error ---" into whichever
    test ran next (880 lines in a headless test's one-sentence stderr). The set-up is undone after the test."""
    import logging

    from app.core import logging_setup

    configured = logging_setup._configured
    root = logging.getLogger()
    level, before = root.level, set(root.handlers)
    yield
    if logging_setup._configured is configured:
        return
    for handler in [h for h in root.handlers if h not in before]:
        if type(handler) is logging.StreamHandler or isinstance(handler, logging_setup._PrivateRotatingFileHandler):
            root.removeHandler(handler)
            handler.close()
    root.setLevel(level)
    logging_setup._configured = configured


# ------------------------------------------------------------------------------ nothing left running
LEFTOVER_GRACE_S = 3.0
# A script kernel retired as its test ended (a window closed, a runner closed) ends on its own path, bounded by
# END_BOUND_S (kill included): its threads and processes get that long. On a loaded machine a kernel still
# starting took longer than LEFTOVER_GRACE_S (test_fault_policy's "left running" in loaded suites, #38).


@pytest.fixture(autouse=True)
def _nothing_left_running(request):  # type: ignore[no-untyped-def]
    """Fail a test that leaves a thread, a QThread (driver) or a child process running after it ends."""
    threads0, os_threads0, children0 = _python_threads(), _os_threads(), _children()
    owned = rigs.OWNED  # a shared rig's threads and processes, built before or during the test, are not its own
    yield
    from app.core import logging_setup

    if logging_setup.log_file() is not None:  # an entry point run in-process configured the application's log
        logging_setup.shutdown()  # its writer thread ends with the test
    from app.scripting.kernel_process import END_BOUND_S, THREAD_PREFIX

    start = time.monotonic()
    while True:
        rig_threads = owned.thread_idents()
        threads = {k: v for k, v in _python_threads().items() if k not in threads0 and k not in rig_threads}
        drivers = {k: v for k, v in _os_threads().items()
                   if k not in os_threads0 and k not in owned.tids and v.startswith("driver:")}
        children = {k: v for k, v in _children().items() if k not in children0 and k not in owned.pids}
        if not (threads or drivers or children):
            break
        ending_kernel = any(name.startswith(THREAD_PREFIX) for name in threads.values())
        if time.monotonic() - start > (max(LEFTOVER_GRACE_S, END_BOUND_S) if ending_kernel else LEFTOVER_GRACE_S):
            break
        time.sleep(0.05)
    left = [f"thread {n!r}" for n in threads.values()] + [f"QThread {n!r}" for n in drivers.values()] + \
        [f"process {pid} ({cmd})" for pid, cmd in children.items()]
    if left:
        import traceback

        frames = sys._current_frames()
        where = "".join(f"\n--- {name}:\n" + "".join(traceback.format_stack(frames[ident])[-4:])
                        for ident, name in threads.items() if ident in frames)
        pytest.fail(f"{request.node.nodeid} left running after it ended: {', '.join(left)}{where}", pytrace=False)
