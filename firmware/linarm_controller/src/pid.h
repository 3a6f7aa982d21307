// Per-motor position loop: PID on the position error with velocity feed-forward in the D term,
// output in amps for a current-controlled drive, integrator frozen while saturated (no wind-up).
#ifndef LINARM_PID_H
#define LINARM_PID_H

#include "linarm_config.h"

struct Pid {
  float kp, ki, kd;
  float integral;

  Pid() : kp(cfg::PID_KP), ki(cfg::PID_KI), kd(cfg::PID_KD), integral(0.0f) {}
  void reset() { integral = 0.0f; }
  // Returns the current command (A), clamped to +-limit.
  float update(float ref, float pos, float velRef, float vel, float limit) {
    float err = ref - pos;
    float u = kp * err + ki * integral + kd * (velRef - vel);
    float amps = u / cfg::FORCE_CONSTANT;
    if (amps < limit && amps > -limit) integral += err * cfg::DT;
    if (amps > limit) return limit;
    if (amps < -limit) return -limit;
    return amps;
  }
};

#endif  // LINARM_PID_H
