// A simple plant of the LINarm2 for the host build: two carriages with viscous + Coulomb friction driven
// by current-controlled motors, the handle between two cubic tension springs, bumpers, rail stops and the
// endstroke switches. Same model and constants as app/devices/sim/linarm_model.py (physics may differ in
// detail; the protocol, FSM and limits may not).
#ifndef LINARM_SIM_PLANT_H
#define LINARM_SIM_PLANT_H

#include <stdint.h>

struct PlantParams {
  double railMin = 0.0, railMax = 0.50;
  double switchMin = 0.005, switchMax = 0.495;
  double carriageMass = 1.0, carriageViscous = 30.0, carriageCoulomb = 8.0;
  double handleMass = 0.5, handleDamping = 20.0;
  double springA = 150.0, springB = 1.0e6, springFreeLength = 0.04;
  double bumper = 0.015, contactStiffness = 5.0e4, contactDamping = 200.0;
  double forceConstant = 20.0, currentHwLimit = 6.0;
  double encoderResolution = 1.0e-5;
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
