# ruff: noqa: F821, B023 -- the script API (linarm, waitCondition, exerciseParams, …) is the runner's namespace
# Trigger reaching (the seed's trigger exercise, D2.2 §4 Fig. 18, as a form). A passive exercise: the robot
# moves the patient's arm between START and END, MOVEMENTS single movements (out, back, out, ...), and each
# movement starts only when the grip force exceeds the trigger threshold (0 N: no trigger, the next movement
# starts after the rest). Each movement is one repetition; a movement whose trigger did not come within the
# timeout is skipped (marked as not completed). Parameters come from the Exercises form as exerciseParams.
P = exerciseParams
MOVEMENTS = int(P.get("movements", 8))
START = float(P.get("start_m", 0.10))
END = float(P.get("end_m", 0.40))
SPEED = float(P.get("speed_m_s", 0.15))
ACCELERATION = float(P.get("acceleration_m_s2", 0.15))
THRESHOLD = float(P.get("trigger_threshold_n", 20.0))
TRIGGER_TIMEOUT_S = float(P.get("trigger_timeout_s", 10.0))
REST_S = float(P.get("rest_s", 0.5))
ARRIVED_M = 0.005       # the seed's arrival criterion: within 5 mm of the target
MOVE_TIMEOUT_S = 30.0

linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveCentreTo(START, SPEED, ACCELERATION, 0, False)
waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - START) < ARRIVED_M, MOVE_TIMEOUT_S)
wait(REST_S)

try:
    for k in range(MOVEMENTS):
        target = END if k % 2 == 0 else START
        linarmppManager.startRepetition(k + 1, MOVEMENTS)
        if THRESHOLD > 0:
            linarmppManager.reportProgress(f"squeeze the handle ({THRESHOLD:g} N) to move")
            gripped = waitCondition(lambda: physiologicalSensors.physiologicalSensorsData.force > THRESHOLD,
                                    TRIGGER_TIMEOUT_S)
            if not gripped:
                linarmppManager.endRepetition(k + 1, ok=False)
                linarmppManager.reportProgress("no grip: movement skipped")
                continue
        linarmppManager.reportProgress(f"moving to {target:.2f} m")
        linarm.moveCentreTo(target, SPEED, ACCELERATION, 0, False)
        arrived = waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - target) < ARRIVED_M,
                                MOVE_TIMEOUT_S)
        wait(REST_S)  # the handle settles: the repetition ends at rest
        linarmppManager.endRepetition(k + 1, ok=arrived)
finally:
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
