// VSA kinematics: centre/delta <-> motor (carriage) positions, stiffness <-> delta, spring forces.
// delta is the springs' pretension displacement: carriage distance - 2 x free length.
#ifndef LINARM_VSA_H
#define LINARM_VSA_H

namespace vsa {

float springTension(float elongation);                 // N, 0 when slack
float stiffness(float delta);                          // N/m, k(delta) around the centre
float deltaForStiffness(float k);                      // m
float span(float delta);                               // carriage distance x1 - x0
float centreOf(float x0, float x1);
float deltaOf(float x0, float x1);
void motorPositions(float centre, float delta, float* x0, float* x1);
void motorVelocities(float centreVel, float deltaVel, float* v0, float* v1);
// Interaction force on the handle from the two spring elongations (+ pushes towards +x).
float interactionForce(float x0, float x1, float handle);

}  // namespace vsa

#endif  // LINARM_VSA_H
