# Reach exercise used by bench/bench_load.py (issue #16): 6 cycles 0.10 m <-> 0.40 m in target-position
# mode, ~30 s of motion. Each move must arrive (within 5 mm) or the script raises, so "every move done"
# is the script finishing without an error.
# ruff: noqa: F821, N816 -- a script for the runner: `linarm` is its global, names as the seed's
import time

startPoint = 0.10
endPoint = 0.40
maxVel = 0.20
maxAcc = 0.40
cycles = 6


def arrive(target, timeout_s=8.0):
    t0 = time.time()
    while abs(target - linarm.linarmVsaState.equilibriumPos) >= 5e-3:
        if time.time() - t0 > timeout_s:
            raise RuntimeError(f"move to {target} m not done within {timeout_s} s")
        time.sleep(0.01)


linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
linarm.setCtrlMode(linarm.CONTROL_MODES.POS_REF_BY_TARGET_POS)
linarm.setCtrlState(linarm.CONTROL_STATES.ON_CTRL_STATE)
linarm.moveDeltaTo(0.010, maxVel, maxAcc, 0, False)
linarm.moveCentreTo(startPoint, maxVel, maxAcc, 0, False)
arrive(startPoint)
moves = 0
for _cycle in range(cycles):
    linarm.moveCentreTo(endPoint, maxVel, maxAcc, 0, False)
    arrive(endPoint)
    moves += 1
    linarm.moveCentreTo(startPoint, maxVel, maxAcc, 0, False)
    arrive(startPoint)
    moves += 1
print(f"MOVES_DONE {moves}")
linarm.setCtrlState(linarm.CONTROL_STATES.IDLE_CTRL_STATE)
