#include "vsa.h"

#include <math.h>

#include "linarm_config.h"

namespace vsa {

float springTension(float e) {
  if (e <= 0.0f) return 0.0f;
  return cfg::SPRING_A * e + cfg::SPRING_B * e * e * e;
}

float stiffness(float delta) {
  float e0 = delta / 2.0f;
  if (e0 <= 0.0f) return 0.0f;
  return 2.0f * (cfg::SPRING_A + 3.0f * cfg::SPRING_B * e0 * e0);
}

float deltaForStiffness(float k) {
  float q = (k / 2.0f - cfg::SPRING_A) / (3.0f * cfg::SPRING_B);
  return 2.0f * sqrtf(q > 0.0f ? q : 0.0f);
}

float span(float delta) { return delta + 2.0f * cfg::SPRING_FREE_LENGTH; }
float centreOf(float x0, float x1) { return (x0 + x1) / 2.0f; }
float deltaOf(float x0, float x1) { return (x1 - x0) - 2.0f * cfg::SPRING_FREE_LENGTH; }

void motorPositions(float centre, float delta, float* x0, float* x1) {
  float half = span(delta) / 2.0f;
  *x0 = centre - half;
  *x1 = centre + half;
}

void motorVelocities(float centreVel, float deltaVel, float* v0, float* v1) {
  *v0 = centreVel - deltaVel / 2.0f;
  *v1 = centreVel + deltaVel / 2.0f;
}

float interactionForce(float x0, float x1, float h) {
  return springTension(h - x0 - cfg::SPRING_FREE_LENGTH) - springTension(x1 - h - cfg::SPRING_FREE_LENGTH);
}

}  // namespace vsa
