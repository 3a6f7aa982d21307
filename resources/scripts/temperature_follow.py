# Temperature follow (seed D2.2 §3.6, Fig. 17). Every 0.1 s, the skin-temperature callback moves the robot's
# centre to 0.10 m plus a tenth of the temperature change since the start (1 °C -> 0.1 m), and prints the
# target. The script itself sleeps 100 s (Stop ends it at once), then puts the robot in IDLE.
# Objects used: linarm and physiologicalSensors. The robot must be homed (the runner homes it first).
# The code below is Fig. 17 as printed, with Python 3's print(pos) for the figure's Python 2 "print pos".
# ruff: noqa: I001 -- kept as the seed printed it
import time
oldTime = time.time()
initialTemp = physiologicalSensors.physiologicalSensorsData.temperature

def stampaPhysio(data):
    import time
    global oldTime
    global initialTemp
    global linarm
    if time.time()-oldTime > 0.1:
        temp = data.temperature
        pos = ((temp/10)-(initialTemp/10))+0.1
        linarm.moveCentreTo(pos,0.250,0.250,0, False)
        print(pos)
        oldTime = time.time()

linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)

# linarm.setLinarmDataCallbackFun(stampaCacca)
physiologicalSensors.setPhysiologicalSensorsDataCallbackFun(stampaPhysio)
time.sleep(100)
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
