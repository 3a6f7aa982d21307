"""Issue #17 point 1: spoofed, replayed and stale α / VR datagrams are refused and counted; a process
that takes over a helper's port is never "reconnected"; non-loopback bind hosts need allow_remote."""

from __future__ import annotations

import os
import signal
import socket
import time
from dataclasses import replace

import pytest
from hypothesis import given
from hypothesis import strategies as st

from app.core.config import AppConfig, ConfigError, load_config
from app.devices import patient_model, vr
from app.devices.patient_model import PatientModelDriver, free_udp_port
from app.devices.transport import UdpTransport
from app.manager import LinarmppManager
from app.safety.supervisor import AlarmLevel
from app.wire.udp_frames import (
    MAC_SIZE,
    FrameError,
    PatientModelFrame,
    PatientModelReply,
    SequenceGuard,
    VrEvent,
    VrEventFrame,
    decode_patient_model_frame,
    encode_patient_model_reply,
    encode_vr_event,
    seal,
    unseal,
)

HOST = "127.0.0.1"
KEY = bytes(range(32))


# ── pure codec ───────────────────────────────────────────────────────────────────────────────────────

@given(st.binary(min_size=1, max_size=64), st.binary(min_size=16, max_size=32))
def test_seal_unseal_round_trip(frame: bytes, key: bytes) -> None:
    assert unseal(key, seal(key, frame)) == frame
    assert len(seal(key, frame)) == len(frame) + MAC_SIZE


@given(st.binary(min_size=1, max_size=64), st.data())
def test_any_changed_byte_is_refused(frame: bytes, data) -> None:
    sealed = bytearray(seal(KEY, frame))
    i = data.draw(st.integers(0, len(sealed) - 1))
    sealed[i] ^= data.draw(st.integers(1, 255))
    with pytest.raises(FrameError):
        unseal(KEY, bytes(sealed))


@given(st.binary(max_size=80))
def test_unseal_raises_only_frame_error(data: bytes) -> None:
    try:
        unseal(KEY, data)
    except FrameError:
        pass


@given(st.integers(0, 0xFFFF), st.integers(1, 0x7FFF))
def test_sequence_guard_accepts_newer_refuses_replays(start: int, step: int) -> None:
    g = SequenceGuard()
    assert g.accept(start)
    assert not g.accept(start)  # the same frame again
    assert g.accept((start + step) & 0xFFFF)  # newer, across the wrap too
    assert not g.accept(start)  # an old one
    assert g.rejected == 2


# ── the manager's end ───────────────────────────────────────────────────────────────────────────────

def reply(seq: int, ack: int, alpha: float = 0.5) -> bytes:
    return encode_patient_model_reply(PatientModelReply(seq, ack, alpha, 0.5, 0.5, 0.5, -1.0, 1.0))


@pytest.fixture
def external_model(qtbot):
    """A PatientModelDriver with a shared key, and a socket playing the model at the pinned address."""
    model = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    model.bind((HOST, 0))
    model.settimeout(2.0)
    listen = free_udp_port(HOST)
    driver = PatientModelDriver(UdpTransport((HOST, listen), model.getsockname()), 100.0, key=KEY)
    driver.frame_source = lambda seq: PatientModelFrame(seq, 70, 5, 33, 2, 0, 0, 0.1, 0.4)
    driver.start()
    try:
        model.recvfrom(256)  # the driver is up
        yield driver, model, (HOST, listen)
    finally:
        driver.stop()
        model.close()


def latest_frame_seq(model: socket.socket) -> int:
    data, _ = model.recvfrom(256)
    return decode_patient_model_frame(unseal(KEY, data)).seq  # the manager seals its frames too


def test_spoofed_replayed_and_stale_replies_are_refused_and_counted(qtbot, external_model) -> None:
    driver, model, manager_addr = external_model
    ack = latest_frame_seq(model)
    good = seal(KEY, reply(7, ack))
    model.sendto(good, manager_addr)
    qtbot.waitUntil(lambda: driver.datagrams_received == 1, timeout=2000)
    # the replayed seq=7 (the 276 of 576 α samples), unauthenticated, and acknowledging an old frame
    model.sendto(good, manager_addr)
    model.sendto(reply(8, ack, alpha=-1.0), manager_addr)
    time.sleep(0.6)
    model.sendto(seal(KEY, reply(9, ack, alpha=-1.0)), manager_addr)
    qtbot.waitUntil(lambda: sum(driver.invalid_datagrams.values()) == 3, timeout=3000)
    assert driver.invalid_datagrams == {"replay": 1, "mac": 1, "stale ack": 1}
    assert driver.datagrams_received == 1
    assert driver.latest("patient_model.main").alpha == 0.5  # no spoofed α got through


def test_spoofed_vr_events_are_refused(qtbot) -> None:
    game = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    game.bind((HOST, 0))
    listen = free_udp_port(HOST)
    driver = vr.VrDriver(UdpTransport((HOST, listen), game.getsockname()), 50.0, key=KEY)
    driver.start()
    try:
        game.settimeout(2.0)
        game.recvfrom(256)  # the driver is up: it sends frames
        subtask = driver.task.subTask
        reached = encode_vr_event(VrEventFrame(3, VrEvent.TARGET_REACHED, subtask, 100, 1.0))
        game.sendto(reached, (HOST, listen))  # plain: no MAC
        game.sendto(seal(KEY, encode_vr_event(VrEventFrame(5, VrEvent.SCORE, subtask, 0))), (HOST, listen))
        game.sendto(seal(KEY, reached), (HOST, listen))  # seq 3 after 5: a replay
        qtbot.waitUntil(lambda: sum(driver.invalid_datagrams.values()) == 2, timeout=3000)
        assert driver.invalid_datagrams == {"mac": 1, "replay": 1}
        assert driver.task.targetsReached == 0  # the target did not move
    finally:
        driver.stop()
        game.close()


def test_a_process_holding_the_models_port_is_never_reconnected(qtbot) -> None:
    manager = LinarmppManager(AppConfig(), factories={"patient_model": patient_model.create})
    manager.start()
    thief = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        driver = manager.driver("patient_model")
        assert driver.authenticated
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        proc = driver.process
        port = driver.udp.peer[1]
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        thief.bind((HOST, port))  # takes the model's port before the restart
        thief.settimeout(0.05)
        deadline = time.monotonic() + 4.0
        while time.monotonic() < deadline and not [a for a in manager.supervisor.alarms()
                                                   if a.level == AlarmLevel.STOP and "cannot bind" in a.text]:
            try:
                data, sender = thief.recvfrom(256)
                thief.sendto(reply(1 + int(time.monotonic() * 100) % 60000, int.from_bytes(data[32:34], "little")),
                             sender)
            except OSError:
                pass
            qtbot.wait(5)
        assert [a for a in manager.supervisor.alarms() if a.level == AlarmLevel.STOP and "cannot bind" in a.text]
        assert not driver.connected  # the thief's replies never counted
        assert not [a for a in manager.supervisor.alarms() if "reconnected" in a.text]
        assert driver.invalid_datagrams["mac"] > 0
        # The next start listens on a fresh port of ours, with a new key: the real model is back.
        qtbot.waitUntil(lambda: driver.connected, timeout=10000)
        assert driver.udp.peer[1] != port and proc.starts >= 3
    finally:
        thief.close()
        manager.shutdown()


@pytest.mark.parametrize(("yaml_text", "words"), [
    ("devices:\n  patient_model:\n    bind_host: 0.0.0.0\n", "not a loopback address"),
    ("devices:\n  vr:\n    bind_host: 256.1.1.1\n", "not an IP address"),
])
def test_non_loopback_or_invalid_bind_hosts_are_refused(tmp_path, yaml_text: str, words: str) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(yaml_text, encoding="utf-8")
    with pytest.raises(ConfigError, match=words) as info:
        load_config(path)
    assert f"{path}:" in str(info.value)
    path.write_text(yaml_text.replace("0.0.0.0\n", "0.0.0.0\n    allow_remote: true\n"), encoding="utf-8")
    if "0.0.0.0" in yaml_text:
        assert load_config(path).devices.patient_model.allow_remote


def test_external_peers_are_plain_by_default_and_say_so(qtbot) -> None:
    cfg = AppConfig()
    ext = replace(cfg.devices.patient_model, mode="external", peer_port=free_udp_port(HOST))
    cfg = replace(cfg, devices=replace(cfg.devices, patient_model=ext))
    manager = LinarmppManager(cfg, factories={"patient_model": patient_model.create})
    manager.start()
    try:
        assert not manager.driver("patient_model").authenticated
        assert [a for a in manager.supervisor.alarms()
                if a.level == AlarmLevel.WARNING and "not authenticated" in a.text]
    finally:
        manager.shutdown()
