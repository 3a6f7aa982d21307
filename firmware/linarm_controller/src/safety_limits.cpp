#include "safety_limits.h"

#include <math.h>

proto::ErrorState checkLimits(const Limits& lim, const SupervisionInput& in, OverCurrentTimer& overCurrent,
                              uint32_t tick, const char** message) {
  if (in.on && fabsf(in.force) > lim.maxForce) {
    *message = "interaction force above maxForce";
    return proto::OVER_FORCE;
  }
  if (in.on && (in.handlePos < lim.posMin - cfg::POSITION_LIMIT_MARGIN ||
                in.handlePos > lim.posMax + cfg::POSITION_LIMIT_MARGIN)) {
    *message = "handle outside the position limits";
    return proto::POSITION_LIMIT;
  }
  if (in.demo) return proto::NO_ERROR;
  for (int i = 0; i < 2; ++i) {
    if (fabsf(in.reference[i] - in.position[i]) > lim.maxTrackingError) {
      *message = i == 0 ? "motor 0 tracking error" : "motor 1 tracking error";
      return proto::TRACKING_ERROR;
    }
  }
  if (in.on && !in.endstrokesDisabled && (in.endstroke[0] || in.endstroke[1])) {
    *message = "endstroke switch closed";
    return proto::ENDSTROKE_HIT;
  }
  float vmax = cfg::OVER_VELOCITY_FACTOR * lim.maxVelocity;
  if (in.on && (fabsf(in.handleVel) > vmax || fabsf(in.velocity[0]) > vmax || fabsf(in.velocity[1]) > vmax)) {
    *message = "velocity above 1.5 x maxVelocity";
    return proto::OVER_VELOCITY;
  }
  float i0 = fabsf(in.current[0]), i1 = fabsf(in.current[1]);
  if (overCurrent.update((i0 > i1 ? i0 : i1) > lim.maxCurrent, tick)) {
    *message = "motor current above maxCurrent for 50 ms";
    return proto::OVER_CURRENT;
  }
  return proto::NO_ERROR;
}

proto::ErrorState checkEnvelope(const Limits& env, const SupervisionInput& in, const char** message) {
  if (!in.on || in.demo) return proto::NO_ERROR;
  if (fabsf(in.handleVel) > cfg::ENVELOPE_VELOCITY_FACTOR * env.maxVelocity) {
    *message = "handle speed above 1.2 x the locked maxVelocity";
    return proto::ENVELOPE_BREACH;
  }
  if (in.handlePos < env.posMin - cfg::ENVELOPE_POSITION_MARGIN ||
      in.handlePos > env.posMax + cfg::ENVELOPE_POSITION_MARGIN) {
    *message = "handle outside the locked position range";
    return proto::ENVELOPE_BREACH;
  }
  return proto::NO_ERROR;
}
