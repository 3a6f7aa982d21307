// Reference generators of the interaction modes, and the velocity helpers shared by the jog mode.
#ifndef LINARM_CONTROLLERS_H
#define LINARM_CONTROLLERS_H

#include "linarm_config.h"

namespace ctrl {

// POS_REF_BY_ADMITTANCE: v = Ka F
inline float admittanceVelocity(float ka, float force) { return ka * force; }

// POS_REF_BY_ASSISTANCE: v = Ka (F + Kt (Apos - handle)), a virtual spring towards the target
inline float assistanceVelocity(float ka, float kt, float force, float target, float handle) {
  return ka * (force + kt * (target - handle));
}

// Velocity towards `wanted` within +-maxVel and a step of maxAcc dt.
inline float ramp(float current, float wanted, float maxVel, float maxAcc) {
  if (wanted > maxVel) wanted = maxVel;
  if (wanted < -maxVel) wanted = -maxVel;
  float step = maxAcc * cfg::DT;
  float d = wanted - current;
  if (d > step) d = step;
  if (d < -step) d = -step;
  return current + d;
}

// Integrate a velocity into a position clamped to [lo, hi]; at a bound the velocity is cut.
inline void integrateClamped(float* pos, float* vel, float lo, float hi) {
  float p = *pos + *vel * cfg::DT;
  if (p <= lo) {
    if (p < lo && *vel < 0.0f) *vel = 0.0f;
    *pos = lo;
  } else if (p >= hi) {
    if (p > hi && *vel > 0.0f) *vel = 0.0f;
    *pos = hi;
  } else {
    *pos = p;
  }
}

}  // namespace ctrl

#endif  // LINARM_CONTROLLERS_H
