# Assisted reaching with FES (example; not a clinical prescription).
# The patient reaches from START to TARGET and back, REPETITIONS times. The robot assists: in
# POS_REF_BY_ASSISTANCE a virtual spring (gain ASSIST_N_M) pulls the handle towards the current goal, on top
# of the admittance (the patient's own force moves the handle). FES follows the movement: the example
# profile "frontal_reaching.yaml" is on a phase axis (0 = start of the reach, 0.5 = target, 1 = back at the
# start) and a LINarm callback feeds the phase from the handle position (fes.setPhase, an extension of the
# seed's FESUser). Every value passes the safety limits; Stop stops the FES and the robot at once.
START = 0.15            # m
TARGET = 0.35           # m
REPETITIONS = 3
ASSIST_N_M = 150.0      # assistance spring, N/m
ADMITTANCE = 0.004      # m/(N s)
REACHED_M = 0.01        # the goal counts as reached within 1 cm
TIMEOUT_S = 15.0        # per movement

goal = START
going_out = True


def follow_phase(vsa):
    # 0 -> 0.5 on the way out, 0.5 -> 1 on the way back
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

fes.loadFile("frontal_reaching.yaml")
linarm.setLinarmVsaDataCallbackFun(follow_phase)
fes.start()
try:
    for rep in range(REPETITIONS):
        for goal, going_out in ((TARGET, True), (START, False)):
            linarm.setAssistanceTargetPos(goal)
            reached = waitCondition(lambda: abs(linarm.linarmVsaState.handlePos - goal) < REACHED_M, TIMEOUT_S)
            print(f"repetition {rep + 1}: {'reached' if reached else 'did not reach'} {goal:.2f} m")
            wait(0.5)
finally:
    fes.stop()
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
