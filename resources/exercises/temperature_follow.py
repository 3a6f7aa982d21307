# ruff: noqa: F821 -- the script API (linarm, physiologicalSensors, exerciseParams, …) is the runner's namespace
# Temperature follow (seed D2.2 §3.6, Fig. 17, as a form). Every update period the robot's centre moves to
# the base position plus gain × the skin-temperature change since the start. No repetitions are marked.
P = exerciseParams
DURATION_S = float(P.get("duration_s", 100.0))
BASE_M = float(P.get("base_m", 0.10))
GAIN_M_PER_C = float(P.get("gain_m_per_c", 0.1))
PERIOD_S = float(P.get("update_period_s", 0.1))
SPEED = float(P.get("speed_m_s", 0.25))

initial = physiologicalSensors.physiologicalSensorsData.temperature
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveCentreTo(BASE_M, SPEED, SPEED, 0, False)  # positioning at the base: not one of the movements
waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - BASE_M) < 0.005, 10)
linarmppManager.prompt(None, "start")  # the exercise proper starts here (the metrics: what moved before is positioning)
elapsed = 0.0
try:
    while elapsed < DURATION_S:
        change = physiologicalSensors.physiologicalSensorsData.temperature - initial
        pos = BASE_M + GAIN_M_PER_C * change
        linarm.moveCentreTo(pos, SPEED, SPEED, 0, False)
        linarmppManager.reportProgress(f"ΔT {change:+.2f} °C → {pos:.3f} m")
        wait(PERIOD_S)
        elapsed += PERIOD_S
finally:
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
