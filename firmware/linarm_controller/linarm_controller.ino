// LINarm controller firmware for the Arduino DUE (Cortex-M3).
//
// loop(): host bytes go to CmdMessenger (pinned to 4.2.0, see sketch.yaml); the control step runs at a
// fixed 1 kHz scheduled from micros(), without blocking waits. The logic (FSM, homing, trajectories, PID
// loops, VSA kinematics, limits, watchdog, protocol) lives in src/ and is also built and tested on the host
// (firmware/host). The protocol ids and enums come from src/protocol_generated.h, generated from the
// Python table (app/wire/linarm_protocol.py).
#include <Arduino.h>
#include <CmdMessenger.h>

#include "src/linarm_config.h"
#include "src/due_hal.h"
#include "src/linarm.h"
#include "src/linarm_app.h"

// The native USB port (SerialUSB) carries the 200 Hz stream with room to spare. On the programming port
// use Serial at 460800 baud at least (docs/linarm-protocol.md, link budget).
#define LINARM_SERIAL SerialUSB
static const unsigned long LINARM_BAUDRATE = 460800;  // never 1200: that erases the DUE
static const char FIRMWARE_VERSION[] = "due-1.0";

static DueHal hal;
static Linarm linarm(hal);
static CmdMessenger messenger(LINARM_SERIAL);
static LinarmApp app(messenger, LINARM_SERIAL, linarm, hal, FIRMWARE_VERSION);
static uint32_t nextTickUs = 0;

void setup() {
  LINARM_SERIAL.begin(LINARM_BAUDRATE);
  hal.begin();
  linarm.begin();
  app.begin();
  nextTickUs = micros() + cfg::LOOP_PERIOD_US;
}

void loop() {
  app.poll();
  unsigned int ticks = 0;
  while (static_cast<int32_t>(micros() - nextTickUs) >= 0) {
    if (ticks == cfg::MAX_CATCH_UP_TICKS) {  // too far behind: drop the backlog rather than burst
      nextTickUs = micros() + cfg::LOOP_PERIOD_US;
      break;
    }
    app.controlTick();
    nextTickUs += cfg::LOOP_PERIOD_US;
    ++ticks;
  }
}
