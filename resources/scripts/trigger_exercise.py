# -*- coding: utf-8 -*-
# Trigger exercise (seed D2.2 §4, Fig. 18; result in Fig. 19). A passive exercise: the robot moves the
# patient's arm between startPoint (0.10 m) and endPoint (0.40 m), four forward + return cycles, and each
# movement starts only when the patient's grip force exceeds 20 N (the grip is the trigger).
# Objects used: linarm and physiologicalSensors. The robot must be homed (the runner homes it first).
# The code below is Fig. 18 as printed, but for its scanning artefacts: a stray "..." in waitCondition
# and the indentation of Fig. 18's lines 27-31, which belong to the script, not to the function.
# Two additions, marked "# added": one squeeze is one trigger (the grip must fall back below the threshold
# before the next movement can be triggered: Fig. 18 as printed starts both movements of a cycle on one held
# squeeze), and each "squeeze now" is marked with linarmppManager.prompt, from which the patient's reaction
# time is measured (docs/metrics.md). Fig. 18's line N is line N + 8 here up to line 33.
# ruff: noqa: I001, F401, F811 -- kept as the seed printed it
#####
# Parameter
import time
startPoint = 0.10
endPoint = 0.40

# Velocità ciclo
maxVelTrap = 0.150
maxAccTrap = 0.150
minAccTrap = 0.50

numCicli = 4

DeltaPos1 = 0.010

forceThreshold = 30
#####

released = True  # added: re-armed once the grip has been below 20 N since the last trigger
def watchGrip(data):  # added
    global released
    if data.force < 20:
        released = True
physiologicalSensors.setPhysiologicalSensorsDataCallbackFun(watchGrip)  # added


def waitCondition(cond, loc, timeoutReaching):
    import time
    old = time.time()
    while (eval(cond, globals(), loc) == False and (time.time() - old < timeoutReaching)):
        pass


linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)

linarm.moveDeltaTo(DeltaPos1,maxVelTrap,maxAccTrap,0, False)

for i in range(0,numCicli):
    linarmppManager.prompt(2 * i + 1, "squeeze", 20)  # added
    waitCondition("released", locals(), 10)  # added: a grip held since the last trigger is released first
    waitCondition("physiologicalSensors.physiologicalSensorsData.force>20", locals(), 10)
    released = False  # added
    linarm.moveCentreTo(endPoint,maxVelTrap,maxAccTrap,0, False)
    waitCondition("abs(endPoint-linarm.linarmVsaState.equilibriumPos)<5e-3", locals(), 10)
    linarmppManager.prompt(2 * i + 2, "squeeze", 20)  # added
    waitCondition("released", locals(), 10)  # added
    waitCondition("physiologicalSensors.physiologicalSensorsData.force>20", locals(), 10)
    released = False  # added
    linarm.moveCentreTo(startPoint,maxVelTrap,maxAccTrap,0, False)
    waitCondition("abs(startPoint-linarm.linarmVsaState.equilibriumPos)<5e-3", locals(), 10)

linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
