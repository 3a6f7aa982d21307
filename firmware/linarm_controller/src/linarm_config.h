// LINarm2 constants and the controller's defaults (SI units).
// The controller semantics (defaults, limits, homing) mirror app/devices/sim/linarm_model.py; the shared
// protocol scenarios (tests/protocol_scenarios) fail when the two disagree.
#ifndef LINARM_LINARM_CONFIG_H
#define LINARM_LINARM_CONFIG_H

namespace cfg {

// Control loop
const float DT = 0.001f;                // s, 1 kHz
const unsigned long LOOP_PERIOD_US = 1000;
const unsigned int MAX_CATCH_UP_TICKS = 5;  // after a stall, run at most this many ticks back to back

// Mechanics
const float RAIL_MIN = 0.0f;            // m
const float RAIL_MAX = 0.50f;           // m
const float SWITCH_MIN_POS = 0.005f;    // m, motor 0's endstroke closes at or below this
const float SWITCH_MAX_POS = 0.495f;    // m, motor 1's endstroke closes at or above this
const float FORCE_CONSTANT = 20.0f;     // N/A of the current-controlled drives
const float CURRENT_HW_LIMIT = 6.0f;    // A, what the drives can deliver
const float ENCODER_RESOLUTION = 1.0e-5f;  // m/count (motors and handle), until setMotorRatio/setMobileRatio

// VSA springs: tension f(e) = a e + b e^3 for an elongation e > 0; free length L.
const float SPRING_A = 150.0f;          // N/m
const float SPRING_B = 1.0e6f;          // N/m^3
const float SPRING_FREE_LENGTH = 0.04f; // m
const float DELTA_MIN = 0.01f;          // m, pretension (carriage distance 0.09 m)
const float DELTA_MAX = 0.06f;          // m, pretension (carriage distance 0.14 m)

// Controller defaults (setters in the protocol)
const float POS_MIN = 0.08f;
const float POS_MAX = 0.42f;
const float MAX_TRACKING_ERROR = 0.02f;
const float MAX_FORCE = 60.0f;
const float MAX_CURRENT = 5.0f;
const float MAX_ACCELERATION = 2.0f;
const float MAX_VELOCITY = 0.5f;
const float HOME_CENTRE = 0.25f;
const float HOME_DELTA = 0.02f;
const float HOMING_VELOCITY = 0.2f;     // m/s: a full homing takes ~4 s
const float HOME_MOVE_MIN_VELOCITY = 0.05f;
const unsigned long HOME_SETTLE_TICKS = 300;  // 0.3 s at rest before the handle encoder is referenced
const float SEEK_LEAD = 0.005f;         // m, how far a seek reference may lead its carriage
const float ADMITTANCE_KA = 0.005f;     // m/(N s)
const float ASSISTANCE_KT = 100.0f;     // N/m
const float ASSISTANCE_TARGET = 0.25f;  // m
const float PID_KP = 20000.0f;          // N/m
const float PID_KI = 100000.0f;         // N/(m s)
const float PID_KD = 200.0f;            // N s/m

// Supervision
const float POSITION_LIMIT_MARGIN = 0.02f;    // m outside [minPos, maxPos] before POSITION_LIMIT
const float OVER_VELOCITY_FACTOR = 1.5f;      // x maxVelocity
const unsigned long OVER_CURRENT_TICKS = 50;  // ms above maxCurrent before OVER_CURRENT

// Command argument ranges checked by the controller (beyond the protocol table's)
const float KA_MAX = 1.0f;
const float KT_MAX = 5000.0f;
const float VIRTUAL_DISP_MAX = 0.05f;
const float RATIO_MIN = 1e-9f;
const float RATIO_MAX = 1.0f;
const float MAX_TRACKING_ERROR_MIN = 1e-6f, MAX_TRACKING_ERROR_MAX = 0.1f;
const float MAX_FORCE_MIN = 0.1f, MAX_FORCE_MAX = 200.0f;
const float MAX_CURRENT_MIN = 0.01f;
const float MAX_ACC_MIN = 1e-3f, MAX_ACC_MAX = 10.0f;
const float MAX_VEL_MIN = 1e-3f, MAX_VEL_MAX = 1.0f;
const float HOMING_VELOCITY_MIN = 1e-3f;
const float POS_LIMIT_MIN_SPAN = 1e-3f;
const float KP_MAX = 1e6f, KI_MAX = 1e7f, KD_MAX = 1e4f;

// Velocity estimate from encoder counts: difference over a short window
const unsigned int VELOCITY_WINDOW = 4;  // ticks

}  // namespace cfg

#endif  // LINARM_LINARM_CONFIG_H
