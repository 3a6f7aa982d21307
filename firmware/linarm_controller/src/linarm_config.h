// LINarm2 constants and the controller's defaults (SI units).
// Everything the simulator, the panel and the firmware share (defaults, ranges, supervision rules,
// mechanics, the simulated plant) is generated from app/wire/linarm_constants.py into
// linarm_constants_generated.h (namespace cfg); the build fails when that copy drifts. Only what is
// particular to this firmware's implementation stays here.
#ifndef LINARM_LINARM_CONFIG_H
#define LINARM_LINARM_CONFIG_H

#include "linarm_constants_generated.h"

namespace cfg {

// Control loop
const unsigned long LOOP_PERIOD_US = 1000;  // = DT
const unsigned int MAX_CATCH_UP_TICKS = 5;  // after a stall, run at most this many ticks back to back

// Velocity estimate from encoder counts: difference over a short window
const unsigned int VELOCITY_WINDOW = 4;  // ticks

}  // namespace cfg

#endif  // LINARM_LINARM_CONFIG_H
