# ruff: noqa: F821 -- the script API (linarm, fes, waitCondition, exerciseParams, …) is the runner's namespace
# Assisted reaching with FES (resources/scripts/assisted_reaching_fes.py as a form). The patient reaches from
# the start to the target and back; the robot assists with a virtual spring towards the current goal on top
# of the admittance, and FES follows the movement's phase (0 → 0.5 on the way out, 0.5 → 1 back). Each reach
# out is one repetition (the return is not counted); a reach not completed within the timeout is marked so.
P = exerciseParams
REPETITIONS = int(P.get("repetitions", 5))
START = float(P.get("start_m", 0.15))
TARGET = float(P.get("target_m", 0.35))
ASSIST_N_M = float(P.get("assistance_n_m", 150.0))
ADMITTANCE = float(P.get("admittance_m_ns", 0.004))
USE_FES = bool(P.get("use_fes", True))
FES_PROFILE = str(P.get("fes_profile", "frontal_reaching.yaml"))
REACHED_M = float(P.get("reached_m", 0.01))
TIMEOUT_S = float(P.get("timeout_s", 15.0))
REST_S = float(P.get("rest_s", 0.5))

going_out = True


def follow_phase(vsa):
    progress = (vsa.handlePos - START) / (TARGET - START)
    progress = min(1.0, max(0.0, progress))
    fes.setPhase(0.5 * progress if going_out else 1.0 - 0.5 * progress)


linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveCentreTo(START, 0.1, 0.2, 0, False)
waitCondition(lambda: abs(linarm.linarmVsaState.equilibriumPos - START) < 0.005, 10)

linarm.setAdmittanceParameter(ADMITTANCE)
linarm.setAssistanceParameter(ASSIST_N_M)
linarm.setAssistanceTargetPos(START)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_ASSISTANCE)

if USE_FES:
    fes.loadFile(FES_PROFILE)
    linarm.setLinarmVsaDataCallbackFun(follow_phase)
    fes.start()
try:
    for rep in range(REPETITIONS):
        linarmppManager.startRepetition(rep + 1, REPETITIONS)
        linarmppManager.prompt(rep + 1, "move")  # reach now: the reaction time runs to the handle's onset
        linarmppManager.setRunState("moving", "reaching out")
        going_out = True
        linarm.setAssistanceTargetPos(TARGET)
        reached = waitCondition(lambda: abs(linarm.linarmVsaState.handlePos - TARGET) < REACHED_M, TIMEOUT_S)
        linarmppManager.endRepetition(rep + 1, ok=reached)
        linarmppManager.reportProgress("target reached" if reached else "target not reached")
        linarmppManager.setRunState("resting")
        wait(REST_S)
        going_out = False
        linarmppManager.setRunState("moving", "back to the start")
        linarm.setAssistanceTargetPos(START)
        waitCondition(lambda: abs(linarm.linarmVsaState.handlePos - START) < REACHED_M, TIMEOUT_S)
        linarmppManager.setRunState("resting")
        wait(REST_S)
finally:
    if USE_FES:
        fes.stop()
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
