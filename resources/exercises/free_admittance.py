# ruff: noqa: F821 -- the script API (linarm, exerciseParams, …) is the runner's namespace
# Free admittance (resources/scripts/free_admittance.py as a form). The robot follows the patient: the handle
# moves at a speed proportional to the patient's force, with a soft spring around it. No repetitions are
# marked: the metrics segment the movements from the handle's speed. Progress shows the range reached.
P = exerciseParams
DURATION_S = float(P.get("duration_s", 60.0))
ADMITTANCE = float(P.get("admittance_m_ns", 0.004))
STIFFNESS = float(P.get("stiffness_n_m", 900.0))

linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.setStiffness(STIFFNESS, 0.05, 0.2, 0)
linarm.setAdmittanceParameter(ADMITTANCE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_ADMITTANCE)

lowest = highest = linarm.linarmVsaState.handlePos
elapsed = 0.0
try:
    while elapsed < DURATION_S:
        pos = linarm.linarmVsaState.handlePos
        lowest, highest = min(lowest, pos), max(highest, pos)
        linarmppManager.reportProgress(f"{elapsed:.0f} of {DURATION_S:.0f} s, range {highest - lowest:.3f} m")
        wait(1.0)
        elapsed += 1.0
finally:
    linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
    print(f"range of motion: {highest - lowest:.3f} m ({lowest:.3f} .. {highest:.3f} m)")
