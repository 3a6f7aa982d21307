// A simple plant of the LINarm2 for the host build: two carriages with viscous + Coulomb friction driven
// by current-controlled motors, the handle between two cubic tension springs, bumpers, rail stops and the
// endstroke switches. Same model and constants as app/devices/sim/linarm_model.py (physics may differ in
// detail; the protocol, FSM and limits may not).
#ifndef LINARM_SIM_PLANT_H
#define LINARM_SIM_PLANT_H

#include <stdint.h>

#include "linarm_config.h"

// The constants of the generated table (app/wire/linarm_constants.py), as the Python simulator uses them.
struct PlantParams {
  double railMin = cfg::RAIL_MIN, railMax = cfg::RAIL_MAX;
  double switchMin = cfg::SWITCH_MIN_POS, switchMax = cfg::SWITCH_MAX_POS;
  double carriageMass = cfg::CARRIAGE_MASS, carriageViscous = cfg::CARRIAGE_VISCOUS,
         carriageCoulomb = cfg::CARRIAGE_COULOMB;
  double handleMass = cfg::HANDLE_MASS, handleDamping = cfg::HANDLE_DAMPING;
  double springA = cfg::SPRING_A, springB = cfg::SPRING_B, springFreeLength = cfg::SPRING_FREE_LENGTH;
  double bumper = cfg::BUMPER, contactStiffness = cfg::CONTACT_STIFFNESS, contactDamping = cfg::CONTACT_DAMPING;
  double forceConstant = cfg::FORCE_CONSTANT, currentHwLimit = cfg::CURRENT_HW_LIMIT;
  double encoderResolution = cfg::ENCODER_RESOLUTION;
};

class SimPlant {
 public:
  SimPlant(const PlantParams& p, double centre, double delta);
  void step(double dt);
  double tension(double e) const;
  double x[2], v[2], h, vh;
  double current[2];   // A, applied by the drives
  double externalForce;  // N on the handle (a patient)
  bool enabled;
  const PlantParams p;
  double xPower[2], hPower;  // where the incremental encoders counted from

 private:
  double railStop(double pos, double vel) const;
};

#endif  // LINARM_SIM_PLANT_H
