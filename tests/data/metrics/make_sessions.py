"""Make the small recorded sessions of known truth that tests/test_metrics_truth.py reads (issue #28).

Each case is a real headless run (app.scripting.headless.run_headless, the code path of ``main.py --headless
--script FILE --record DIR``) on the simulated devices, with the simulated patient driven through the
simulator's control channel (``manager.sim_patient()``), then trimmed to what the metrics read and stored as
``<case>.json.gz``: the manifest's times, the events the metrics use, and the streams ``linarm.vsa``
(handlePos, equilibriumPos), ``linarm.state`` (controlState, at its changes) and ``physio.main`` (force, for
the trigger cases), times and positions as delta-coded integers (µs, µm).

The truth of each case is what was commanded: how many movements (the script's own list of targets, or the
patient's pushes), the reaction delay the patient was given, and where the movements turn. The kinematic
truth is read off the commanded centre (``equilibriumPos``, noise-free) by tests/test_metrics_truth.py.

    PYTHONPATH=. .venv/bin/python tests/data/metrics/make_sessions.py [CASE ...]
"""

from __future__ import annotations

import gzip
import json
import sys
import tempfile
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
KEEP_EVENTS = {"prompt", "repetition_start", "repetition_end", "script_start", "script_stop", "exercise_start",
               "run_start", "run_state", "run_end", "emergency_stop", "alarm"}

PASSIVE = """
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveCentreTo(TARGETS[0], 0.1, 0.3, 0, False)  # positioning at the first point
waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - TARGETS[0]) < 0.005, 15)
wait(1.0)
linarmppManager.prompt(None, "start")
for target in TARGETS[1:]:  # no pause: turn as soon as the centre is within 5 mm
    linarm.moveCentreTo(target, SPEED, ACC, 0, False)
    waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - target) < 0.005, 15)
wait(1.0)
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
"""

SWAY = """
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.setStiffness(900.0, 0.05, 0.2, 0)
linarm.setAdmittanceParameter(ADMITTANCE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_ADMITTANCE)
wait(1.0)
linarmppManager.prompt(None, "start")
wait(SWAYS * HALF_PERIOD + 1.5)
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
"""


def passive_case(targets: list[float], speed: float, acc: float) -> dict[str, Any]:
    head = f"TARGETS = {targets!r}\nSPEED = {speed!r}\nACC = {acc!r}\n"
    return {"script": head + PASSIVE, "truth": {"kind": "passive", "count": len(targets) - 1, "targets": targets,
                                                 "speed_m_s": speed, "acceleration_m_s2": acc}}


def sway_case(sways: int, half_period: float, low: float, high: float, force: float) -> dict[str, Any]:
    head = f"LOW = {low!r}\nSWAYS = {sways}\nHALF_PERIOD = {half_period!r}\nADMITTANCE = 0.005\n"
    return {"script": head + SWAY, "truth": {"kind": "sway", "count": sways, "half_period_s": half_period,
                                               "targets": [low, high], "push_n": force}}


def trigger_case(delay: float, movements: int = 4) -> dict[str, Any]:
    params = {"movements": movements, "start_m": 0.12, "end_m": 0.36, "speed_m_s": 0.15, "acceleration_m_s2": 0.3,
              "trigger_threshold_n": 20.0, "trigger_timeout_s": 10.0, "rest_s": 0.5}
    text = (ROOT / "resources" / "exercises" / "trigger_reaching.py").read_text(encoding="utf-8")
    script = f"exerciseParams = {params!r}\n" + text
    return {"script": script, "truth": {"kind": "trigger", "count": movements, "reaction_s": delay,
                                        "params": params, "squeeze_s": 0.6}}


CASES: dict[str, dict[str, Any]] = {
    "reaches6_v015": passive_case([0.10, 0.40] * 3 + [0.10], 0.15, 0.5),
    "reaches6_v030": passive_case([0.10, 0.40] * 3 + [0.10], 0.30, 1.0),
    "reaches12_v015": passive_case([0.10, 0.40] * 6 + [0.10], 0.15, 0.5),
    "mixed_v015": passive_case([0.10, 0.15, 0.10, 0.25, 0.10, 0.40, 0.10], 0.15, 0.5),
    "mixed_v030": passive_case([0.10, 0.15, 0.10, 0.25, 0.10, 0.40, 0.10], 0.30, 1.0),
    "sway_3s": sway_case(8, 1.5, 0.12, 0.38, 20.0),
    "trigger_rt04": trigger_case(0.4),
    "trigger_rt16": trigger_case(1.6),
}


def config() -> Any:
    from app.core.config import AppConfig, UdpEndpoint

    cfg = AppConfig()
    return replace(cfg, devices=replace(cfg.devices, patient_model=UdpEndpoint(mode="off"),
                                        vr=UdpEndpoint(mode="off")))


def make(name: str, case: dict[str, Any]) -> Path:
    from app.scripting.headless import EXIT_OK, run_headless
    from app.session.recording import load_session

    truth = dict(case["truth"])
    commands: list[tuple[float, str, Any]] = []  # what the simulated patient was told, and when (monotonic)
    timers: list[threading.Timer] = []
    stop = threading.Event()

    def prepare(manager: Any) -> None:
        patient = manager.sim_patient()
        patient.passive()
        patient.idle()

        def on_event(kind: str, data: dict[str, Any]) -> None:
            if kind != "prompt":
                return
            if truth["kind"] == "trigger":
                def squeeze() -> None:
                    commands.append((time.monotonic(), "squeeze", truth["squeeze_s"]))
                    patient.squeeze(truth["squeeze_s"])
                timer = threading.Timer(truth["reaction_s"], squeeze)
                timers.append(timer)
                timer.start()
            elif truth["kind"] == "sway":
                def sway() -> None:
                    # the push ramps up and down over 0.2 s (a step of force on the handle's spring would
                    # shake it faster than the robot's speed envelope allows); the targets lie beyond where
                    # the patient gets in 1.5 s, so the sway turns without a rest
                    low, high = truth["targets"]
                    for k in range(truth["count"]):
                        target = high if k % 2 == 0 else low
                        commands.append((time.monotonic(), "push_to", target))
                        for f in np.linspace(0.0, truth["push_n"], 6)[1:]:
                            patient.push_to(target, float(f))
                            if stop.wait(0.04):
                                return
                        if stop.wait(truth["half_period_s"] - 0.4):
                            return
                        for f in np.linspace(truth["push_n"], 0.0, 6)[1:]:
                            patient.push_to(target, float(f))
                            if stop.wait(0.04):
                                return
                    commands.append((time.monotonic(), "passive", None))
                    patient.passive()
                thread = threading.Thread(target=sway, daemon=True)
                timers.append(thread)  # type: ignore[arg-type]
                thread.start()

        manager.bus.listen("make_sessions", lambda r: on_event(r.kind, r.data))

    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / f"{name}.py"
        script.write_text("# ruff: noqa\n" + case["script"], encoding="utf-8")
        out: list[str] = []
        code = run_headless(config(), str(script), record_dir=str(Path(tmp) / "rec"), prepare=prepare,
                            output=lambda stream, text: out.append(text))
        stop.set()
        for timer in timers:
            timer.join(5.0)
        if code != EXIT_OK:
            raise RuntimeError(f"{name}: exit {code}\n{''.join(out)}")
        folder = next(p for p in (Path(tmp) / "rec").rglob("manifest.json")).parent
        session = load_session(folder)
        data = trim(session)
        t0 = session.start_mono
        data["truth"] = {**truth, "patient_commands": [(round(t - t0, 4), what, arg) for t, what, arg in commands]}
        data["case"] = name
    path = HERE / f"{name}.json.gz"
    with gzip.open(path, "wt", encoding="utf-8", compresslevel=9) as fh:
        json.dump(data, fh, separators=(",", ":"))
    return path


def _delta(values: np.ndarray, scale: float) -> list[int]:
    ints = np.round(np.asarray(values, dtype=float) * scale).astype(np.int64)
    return [int(ints[0]), *np.diff(ints).tolist()] if len(ints) else []


def trim(session: Any) -> dict[str, Any]:
    t0 = session.start_mono
    streams: dict[str, Any] = {}
    keep = {"linarm.vsa": ("handlePos", "equilibriumPos"), "linarm.state": ("controlState",),
            "physio.main": ("force",)}
    for name, channels in keep.items():
        s = session.streams.get(name)
        if s is None or not len(s.t):
            continue
        t = s.t - t0
        sel = np.ones(len(t), dtype=bool)
        if name == "linarm.state":  # at its changes only (and the last sample)
            v = s.data["controlState"]
            sel = np.concatenate([[True], v[1:] != v[:-1]])
            sel[-1] = True
        if name == "physio.main" and not any(e.get("kind") == "prompt" and (e.get("data") or {}).get("cue") == "squeeze"
                                             for e in session.events):
            continue
        entry: dict[str, Any] = {"rate_hz": s.nominal_rate_hz, "t_us": _delta(t[sel], 1e6)}
        for ch in channels:
            scale = 1e6 if name == "linarm.vsa" else (1e3 if name == "physio.main" else 1.0)
            entry[ch] = {"scale": scale, "d": _delta(s.data[ch][sel], scale)}
        streams[name] = entry
    events = []
    for e in session.events:
        if e.get("kind") not in KEEP_EVENTS:
            continue
        data = {k: v for k, v in (e.get("data") or {}).items() if k != "text"}
        events.append({"kind": e["kind"], "t_s": round(float(e["t_mono"]) - t0, 6), "data": data})
    return {"duration_s": session.duration_s, "streams": streams, "events": events}


def main(argv: list[str]) -> int:
    names = argv or list(CASES)
    for name in names:
        started = time.monotonic()
        path = make(name, CASES[name])
        print(f"{name}: {path.stat().st_size / 1024:.1f} KiB in {time.monotonic() - started:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
