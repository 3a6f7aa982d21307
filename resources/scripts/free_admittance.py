# Free admittance exercise (example). The robot follows the patient: in POS_REF_BY_ADMITTANCE the handle
# moves at a speed proportional to the force the patient applies (Ka, m/(N s)), with a soft spring
# (stiffness set by the VSA delta). Every second the script prints the position, the force and the
# furthest positions reached; after DURATION_S it puts the robot in IDLE and prints the range of motion.
DURATION_S = 60.0
ADMITTANCE = 0.004      # m/(N s): 0.004 * 60 N = 0.24 m/s, within the velocity limit
STIFFNESS = 900.0       # N/m of the VSA around the handle

linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.setStiffness(STIFFNESS, 0.05, 0.2, 0)
linarm.setAdmittanceParameter(ADMITTANCE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_ADMITTANCE)

lowest = highest = linarm.linarmVsaState.handlePos
start = time.time()
try:
    while time.time() - start < DURATION_S:
        vsa = linarm.linarmVsaState
        lowest, highest = min(lowest, vsa.handlePos), max(highest, vsa.handlePos)
        print(f"t={time.time() - start:5.1f} s  position {vsa.handlePos:.3f} m  "
              f"force {vsa.interactionForce:+5.1f} N  range {lowest:.3f}..{highest:.3f} m")
        time.sleep(1.0)
finally:
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
    print(f"range of motion: {highest - lowest:.3f} m ({lowest:.3f} .. {highest:.3f} m)")
