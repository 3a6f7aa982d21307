"""Issue #17 point 3: a recorder that cannot write raises a STOP alarm within 1 s naming the folder and
the error (the fault policy then stops FES, the robot and the script), keeps its events, never aborts
the app, and says so in the manifest; too little free space refuses the session; an unwritable folder
headless is one line and exit 4."""

from __future__ import annotations

import errno
import json
import os
import time
from dataclasses import replace

import pytest

from app.core.config import AppConfig
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.session.recording import RecordingError, check_free_space
from tests.fakes import counter_factory
from tests.test_fault_policy import fill_the_disk


@pytest.fixture
def manager(tmp_path, qtbot):
    m = LinarmppManager(AppConfig(), factories={"physio": counter_factory(tmp_path, "physio")})
    m.start()
    qtbot.waitUntil(m.all_connected, timeout=10000)
    yield m
    m.shutdown()


def test_disk_full_is_a_stop_alarm_within_1_s_and_events_survive(tmp_path, qtbot, manager) -> None:
    safe: list[str] = []
    manager.supervisor.register_estop_action("probe", safe.append)
    folder = manager.start_session("DISK01", "tester", root=tmp_path / "sessions")
    t0 = time.monotonic()
    fill_the_disk(manager.recorder)
    # The alarm is listed as it is raised; the policy's safe-state actions follow on the GUI thread's
    # loop: both within the second (under two CPU-bound processes the second came a moment later).
    qtbot.waitUntil(lambda: bool(safe) and any(a.level == AlarmLevel.STOP and "Recording failed" in a.text
                                                for a in manager.supervisor.alarms()), timeout=1000)
    elapsed = time.monotonic() - t0
    alarm = next(a for a in manager.supervisor.alarms() if "Recording failed" in a.text)
    assert str(folder) in alarm.text and "No space left on device" in alarm.text
    assert "Recording failed" in safe[0]  # the fault policy's safe state
    manager.record_event("after_the_failure", note="kept in memory")
    manager.end_session()  # no exception, no abort
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    assert manifest["status"] == "failed"
    assert "No space left" in manifest["recording_failure"]["error"] and manifest["recording_failure"]["t_wall"]
    kinds = [json.loads(ln)["kind"] for ln in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()]
    # written again once the disk had room (a fresh handle): the failure, the safe state and what followed
    assert {"recording_failed", "safe_state_action", "after_the_failure", "session_stop"} <= set(kinds)
    assert elapsed < 1.0


def test_free_space_thresholds(tmp_path, monkeypatch) -> None:
    from app.session import recording

    monkeypatch.setattr(recording, "free_space_mib", lambda folder: 500.0)
    assert "500 MiB free" in check_free_space(tmp_path, 1024, 100)
    monkeypatch.setattr(recording, "free_space_mib", lambda folder: 50.0)
    with pytest.raises(RecordingError) as info:
        check_free_space(tmp_path, 1024, 100)
    assert info.value.errno == errno.ENOSPC and str(tmp_path) in info.value.strerror


def test_low_disk_space_is_a_warning_alarm(tmp_path, qtbot, manager, monkeypatch) -> None:
    from app.session import recording

    monkeypatch.setattr(recording, "free_space_mib", lambda folder: 500.0)
    manager.start_session("DISK04", "tester", root=tmp_path / "sessions")
    assert [a for a in manager.supervisor.alarms() if a.level == AlarmLevel.WARNING and "500 MiB free" in a.text]
    manager.end_session()


def test_a_session_is_refused_when_the_disk_is_nearly_full(tmp_path, qtbot, manager, monkeypatch) -> None:
    from app.session import recording

    monkeypatch.setattr(recording, "free_space_mib", lambda folder: 10.0)
    with pytest.raises(RecordingError, match="MiB free"):
        manager.start_session("DISK02", "tester", root=tmp_path / "sessions")
    assert manager.recorder is None


def test_headless_unwritable_record_folder_is_one_line_and_exit_4(tmp_path, capsys) -> None:
    from app.scripting import headless

    blocker = tmp_path / "not-a-folder"  # unwritable even for root (a read-only mount behaves the same)
    blocker.write_text("", encoding="utf-8")
    script = tmp_path / "s.py"
    script.write_text("x = 1\n", encoding="utf-8")
    code = headless.run_headless(AppConfig(), str(script), record_dir=str(blocker / "rec"))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == headless.EXIT_RECORDING == 4
    assert len(err) == 1 and err[0].startswith("Cannot record:") and "Traceback" not in err[0]


def test_config_holds_the_free_space_figures() -> None:
    rec = AppConfig().recording
    assert (rec.warn_free_mib, rec.min_free_mib) == (1024.0, 100.0)
    assert replace(rec, min_free_mib=5).min_free_mib == 5


@pytest.fixture
def small_tmpfs(tmp_path):
    """A 1 MiB tmpfs (needs root and a kernel that lets us mount); skipped otherwise. The session's space
    reserve (256 KiB) fits; :func:`fill` then takes the rest, as another program filling the disk would."""
    import subprocess

    mount = tmp_path / "tiny"
    mount.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)],
                                           capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], capture_output=True)


def fill(mount) -> None:
    """Every free block of the tmpfs into one file (raw writes: nothing buffered that could still land)."""
    fd = os.open(mount / "filler", os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        while True:
            os.write(fd, b"x" * 4096)
    except OSError as exc:
        assert exc.errno == errno.ENOSPC
    finally:
        os.close(fd)


def full_disk_manager(tmp_path):
    cfg = AppConfig()
    cfg = replace(cfg, recording=replace(cfg.recording, warn_free_mib=0.0, min_free_mib=0.0))
    return LinarmppManager(cfg, factories={"physio": counter_factory(tmp_path, "physio")})  # 1 kHz, ~25 kB/s


def test_a_really_full_disk(tmp_path, qtbot, small_tmpfs) -> None:
    m = full_disk_manager(tmp_path)
    m.start()
    try:
        qtbot.waitUntil(m.all_connected, timeout=10000)
        folder = m.start_session("DISK03", "tester", root=small_tmpfs)
        fill(small_tmpfs)
        qtbot.waitUntil(lambda: any(a.level == AlarmLevel.STOP and "Recording failed" in a.text
                                    for a in m.supervisor.alarms()), timeout=10000)
        alarm = next(a for a in m.supervisor.alarms() if "Recording failed" in a.text)
        assert str(folder) in alarm.text and "No space left" in alarm.text
        m.record_event("while_full")
        (small_tmpfs / "filler").unlink()  # the operator makes room
        m.end_session()
        manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
        assert manifest["status"] == "failed" and "No space left" in manifest["recording_failure"]["error"]
        kinds = [json.loads(ln)["kind"] for ln in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()
                 if ln.startswith("{")]
        assert {"recording_failed", "while_full", "session_stop"} <= set(kinds)
    finally:
        m.shutdown()


def test_a_disk_that_stays_full_says_failed_keeps_the_events_and_leaves_nothing_behind(
        tmp_path, qtbot, small_tmpfs) -> None:
    """Issue #25, "disk full mid-session": the manifest stayed ``recording``, 15 events were lost, an empty
    ``.manifest.json.tmp`` was left. Now the space reserve released at the failure holds the manifest
    (``failed``, with what was lost) and every event, with the disk still full at the stop."""
    from app.session.recording import RESERVE_FILE, load_session

    m = full_disk_manager(tmp_path)
    m.start()
    try:
        qtbot.waitUntil(m.all_connected, timeout=10000)
        folder = m.start_session("DISK05", "tester", root=small_tmpfs)
        fill(small_tmpfs)
        qtbot.waitUntil(lambda: bool(m.recorder.failure), timeout=10000)
        for i in range(15):
            m.record_event("while_full", i=i)
        m.end_session()  # the filler stays: the disk is full until the end
        manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
        assert manifest["status"] == "failed", manifest["status"]
        failure = manifest["recording_failure"]
        assert "No space left" in failure["error"] and failure["events_not_written"] == 0
        assert manifest["end"] and manifest["end"]["reason"]
        events = [json.loads(ln) for ln in (folder / "events.jsonl").read_text(encoding="utf-8").splitlines()]
        assert [e["data"]["i"] for e in events if e["kind"] == "while_full"] == list(range(15))
        assert {"session_start", "recording_failed", "session_stop"} <= {e["kind"] for e in events}
        assert manifest["event_count"] == len(events)
        leftovers = sorted(p.name for p in folder.rglob(".*"))
        assert leftovers == [], leftovers  # no .manifest.json.tmp, no space reserve
        assert not (folder / RESERVE_FILE).exists()
        for info in manifest["streams"].values():  # every stream's file, each ending with a whole line
            data = (folder / info["file"]).read_bytes()
            assert data.endswith(b"\n") and data.startswith(b"t_mono_s,"), info["file"]
        session = load_session(folder)
        assert session.status == "failed" and not session.complete
        assert any("recording failed" in p and "No space left" in p for p in session.problems), session.problems
        for name, n in manifest["counts"].items():  # the counts are what the files hold
            assert len(session.streams[name]) == n
    finally:
        m.shutdown()


def test_the_start_on_a_full_disk_leaves_no_half_made_session(tmp_path, qtbot, small_tmpfs) -> None:
    from app.session.recording import RecordingError

    fill(small_tmpfs)
    (small_tmpfs / "filler").write_bytes(b"")  # room for a folder and a manifest, not for the reserve
    keep = os.open(small_tmpfs / "filler2", os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        os.write(keep, b"x" * (1024 * 1024 - 128 * 1024))
    except OSError:
        pass
    finally:
        os.close(keep)
    m = full_disk_manager(tmp_path)
    m.start()
    try:
        qtbot.waitUntil(m.all_connected, timeout=10000)
        with pytest.raises(RecordingError, match="No space left"):
            m.start_session("DISK06", "tester", root=small_tmpfs)
        assert list((small_tmpfs / "DISK06").iterdir()) == []  # no session folder, no open file
        assert m.recorder is None
    finally:
        m.shutdown()


def test_when_not_even_the_manifest_fits_a_sidecar_says_failed(tmp_path, qtbot, manager, monkeypatch) -> None:
    """The disk stays full for every new block (the freed reserve taken by another program): the manifest
    cannot be replaced, so ``recording-failed.txt`` says it, the loader and the session list read it, and the
    temp file of the refused manifest is gone."""
    from app.session.recording import FAILED_FILE, load_session, summarize_session

    real_replace = os.replace

    def no_room(src, dst, *a, **kw):
        if str(src).endswith(".manifest.json.tmp"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst, *a, **kw)

    folder = manager.start_session("DISK07", "tester", root=tmp_path / "sessions")
    monkeypatch.setattr(os, "replace", no_room)
    fill_the_disk(manager.recorder)
    qtbot.waitUntil(lambda: bool(manager.recorder.failure), timeout=2000)
    manager.end_session()
    monkeypatch.undo()
    assert not (folder / ".manifest.json.tmp").exists()
    assert json.loads((folder / "manifest.json").read_text(encoding="utf-8"))["status"] == "recording"
    side = json.loads((folder / FAILED_FILE).read_text(encoding="utf-8"))
    assert "No space left" in side["error"]
    session = load_session(folder)
    assert session.status == "failed" and any("recording failed" in p for p in session.problems)
    assert summarize_session(folder).status == "failed" and not summarize_session(folder).complete


def test_events_flushed_before_the_failure_are_written_once(tmp_path, qtbot, manager) -> None:
    """The events since the last fsync are written again after a failure: exactly once each (the file is cut
    back to what the last good flush left), never twice, never glued to a half line."""
    folder = manager.start_session("DISK08", "tester", root=tmp_path / "sessions")
    rec = manager.recorder
    for i in range(10):
        manager.record_event("before_failure", i=i)
    events_file = folder / "events.jsonl"
    qtbot.waitUntil(lambda: events_file.read_text(encoding="utf-8").count("before_failure") == 10, timeout=2000)
    for out in rec._outs.values():  # the stream files fail at the next flush; the events' own file does not
        from tests.test_fault_policy import FailingFile

        out.fh = FailingFile(out.fh)
    qtbot.waitUntil(lambda: bool(rec.failure), timeout=3000)
    manager.end_session()
    lines = events_file.read_text(encoding="utf-8").splitlines()
    records = [json.loads(ln) for ln in lines]  # every line whole
    assert sorted(r["data"]["i"] for r in records if r["kind"] == "before_failure") == list(range(10))
    stamps = [(r["kind"], r["t_mono"]) for r in records]
    assert len(stamps) == len(set(stamps)), "an event was written twice"
