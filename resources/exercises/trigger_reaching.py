# ruff: noqa: F821, B023 -- the script API (linarm, waitCondition, exerciseParams, …) is the runner's namespace
# Trigger reaching (the seed's trigger exercise, D2.2 §4 Fig. 18, as a form). A passive exercise: the robot
# moves the patient's arm between START and END, MOVEMENTS single movements (out, back, out, ...), and each
# movement starts only when the grip force exceeds the trigger threshold (0 N: no trigger, the next movement
# starts after the rest). Each movement is one repetition; a movement whose trigger did not come within the
# timeout is skipped (marked as not completed). Parameters come from the Exercises form as exerciseParams.
import threading

P = exerciseParams
MOVEMENTS = int(P.get("movements", 8))
START = float(P.get("start_m", 0.10))
END = float(P.get("end_m", 0.40))
SPEED = float(P.get("speed_m_s", 0.15))
ACCELERATION = float(P.get("acceleration_m_s2", 0.15))
THRESHOLD = float(P.get("trigger_threshold_n", 20.0))
TRIGGER_TIMEOUT_S = float(P.get("trigger_timeout_s", 10.0))
REST_S = float(P.get("rest_s", 0.5))
ARRIVED_M = 0.005       # the seed's arrival criterion: the commanded centre within 5 mm of the target
HANDLE_REACHED_M = 0.01  # completed: the handle itself (not the centre) came within 1 cm of the target ...
COVERED = 0.9            # ... having covered at least 90 % of the movement (docs/metrics.md, "Completed")
SETTLE_TIMEOUT_S = 2.0   # how long the handle may lag the centre at the end of a movement
MOVE_TIMEOUT_S = 30.0


# The trigger is judged on the grip samples in the order they were taken, all on the callback thread. Not on the
# latest sample (the main thread's read) mixed with the callbacks' samples: the callbacks may run late (a busy
# computer) with samples older than the one the main thread already read, and an old sample from before the
# squeeze would re-arm the trigger while the grip is still held (a 1 s squeeze starting two movements).
trigger = threading.Lock()  # the callback's judgement and the main thread's wait start and end, one at a time
released = True   # re-armed: the grip has been below the threshold since the last trigger
waiting = False   # a movement waits for its squeeze
squeezed = False  # the squeeze it waited for came (set by watch_grip)


def grip():
    return physiologicalSensors.physiologicalSensorsData.force


def watch_grip(sample):  # every grip sample, in order: a release re-arms the trigger, a squeeze fires it
    global released, squeezed
    with trigger:
        if sample.force < THRESHOLD:
            released = True
        elif sample.force > THRESHOLD and released and waiting:
            released = False
            squeezed = True


def squeeze_judged():
    grip()  # paces the wait on the grip stream: each read waits for the next sample (none yet: "no data received")
    return squeezed


def wait_for_squeeze(timeout_s):
    """One squeeze = one trigger: a grip still held since the last trigger must be released first (re-armed
    only below the threshold), then squeezed through it again. A new squeeze begun before the prompt (after a
    release) triggers at once."""
    global waiting, squeezed
    with trigger:
        squeezed, waiting = False, True
    waitCondition(squeeze_judged, timeout_s)
    with trigger:  # a squeeze judged at the timeout's instant counts: the trigger is spent either way
        waiting = False
        return squeezed


if THRESHOLD > 0:
    physiologicalSensors.setPhysiologicalSensorsDataCallbackFun(watch_grip)
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveCentreTo(START, SPEED, ACCELERATION, 0, False)  # positioning: not a repetition
waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - START) < ARRIVED_M, MOVE_TIMEOUT_S)
waitCondition(lambda: abs(linarm.linarmVsaState.handlePos - START) < HANDLE_REACHED_M, SETTLE_TIMEOUT_S)
wait(REST_S)

try:
    for k in range(MOVEMENTS):
        # the target is the far end from where the handle is (after a skipped movement it has not moved)
        here = linarm.linarmVsaState.handlePos
        target = END if abs(here - START) <= abs(here - END) else START
        linarmppManager.startRepetition(k + 1, MOVEMENTS)
        if THRESHOLD > 0:
            linarmppManager.reportProgress(f"squeeze the handle ({THRESHOLD:g} N) to move")
            linarmppManager.prompt(k + 1, "squeeze", THRESHOLD)
            linarmppManager.setRunState("waiting_for_grip")
            if not wait_for_squeeze(TRIGGER_TIMEOUT_S):
                linarmppManager.endRepetition(k + 1, ok=False)
                linarmppManager.reportProgress("no grip: movement skipped")
                continue
        linarmppManager.reportProgress(f"moving to {target:.2f} m")
        linarmppManager.setRunState("moving")
        linarm.moveCentreTo(target, SPEED, ACCELERATION, 0, False)
        waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - target) < ARRIVED_M, MOVE_TIMEOUT_S)
        # the handle itself near the target, having covered the way (from where it was, not the centre's)
        reached = waitCondition(lambda: abs(linarm.linarmVsaState.handlePos - target) < HANDLE_REACHED_M
                                and abs(linarm.linarmVsaState.handlePos - here) >= COVERED * abs(target - here),
                                SETTLE_TIMEOUT_S)
        linarmppManager.setRunState("resting")
        wait(REST_S)  # the handle settles: the repetition ends at rest
        linarmppManager.endRepetition(k + 1, ok=bool(reached))
finally:
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
