// Limits and the 1 kHz supervision that turns a violated limit into a latched error state.
#ifndef LINARM_SAFETY_LIMITS_H
#define LINARM_SAFETY_LIMITS_H

#include <stdint.h>

#include "linarm_config.h"
#include "protocol_generated.h"

struct Limits {
  float posMin, posMax;       // m, centre references and targets stay inside
  float maxTrackingError;     // m
  float maxForce;             // N
  float maxCurrent;           // A
  float maxAcceleration;      // m/s^2
  float maxVelocity;          // m/s
  Limits()
      : posMin(cfg::POS_MIN), posMax(cfg::POS_MAX), maxTrackingError(cfg::MAX_TRACKING_ERROR),
        maxForce(cfg::MAX_FORCE), maxCurrent(cfg::MAX_CURRENT), maxAcceleration(cfg::MAX_ACCELERATION),
        maxVelocity(cfg::MAX_VELOCITY) {}
};

// One tick's worth of what the supervisor looks at.
struct SupervisionInput {
  bool on;                 // control state ON (HOME is supervised too, with fewer checks)
  bool demo;               // no robot: only force and position are checked
  bool endstrokesDisabled;
  float position[2];       // m, measured carriage positions
  float reference[2];      // m, carriage references
  float velocity[2];       // m/s
  float handlePos, handleVel, force;
  float current[2];        // A, measured
  bool endstroke[2];
};

// OVER_CURRENT needs the current above the limit for OVER_CURRENT_TICKS in a row.
class OverCurrentTimer {
 public:
  OverCurrentTimer() : running_(false), since_(0) {}
  void reset() { running_ = false; }
  bool update(bool over, uint32_t tick) {
    if (!over) {
      running_ = false;
      return false;
    }
    if (!running_) {
      running_ = true;
      since_ = tick;
      return false;
    }
    return static_cast<uint32_t>(tick - since_) >= cfg::OVER_CURRENT_TICKS;
  }

 private:
  bool running_;
  uint32_t since_;
};

// The first violated limit in the simulator's order (force, position, tracking, endstroke, velocity,
// current); NO_ERROR if none. *message gets a short static explanation.
proto::ErrorState checkLimits(const Limits& limits, const SupervisionInput& in, OverCurrentTimer& overCurrent,
                              uint32_t tick, const char** message);

// The locked envelope, checked before the limits (in ON, not in demo): the handle faster than
// ENVELOPE_VELOCITY_FACTOR x the locked maxVelocity, or more than ENVELOPE_POSITION_MARGIN outside the locked
// range: ENVELOPE_BREACH. The same rule as the host's monitor (app/safety.py), one layer below it.
proto::ErrorState checkEnvelope(const Limits& envelope, const SupervisionInput& in, const char** message);

#endif  // LINARM_SAFETY_LIMITS_H
