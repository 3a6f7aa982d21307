#include "sim_plant.h"

#include <math.h>

SimPlant::SimPlant(const PlantParams& params, double centre, double delta)
    : h(centre), vh(0.0), externalForce(0.0), enabled(false), p(params) {
  double half = (delta + 2.0 * p.springFreeLength) / 2.0;
  x[0] = centre - half;
  x[1] = centre + half;
  v[0] = v[1] = 0.0;
  current[0] = current[1] = 0.0;
  xPower[0] = x[0];
  xPower[1] = x[1];
  hPower = h;
}

double SimPlant::tension(double e) const { return e <= 0.0 ? 0.0 : p.springA * e + p.springB * e * e * e; }

double SimPlant::railStop(double pos, double vel) const {
  if (pos < p.railMin) return fmax(0.0, p.contactStiffness * (p.railMin - pos) - p.contactDamping * vel);
  if (pos > p.railMax) return fmin(0.0, -p.contactStiffness * (pos - p.railMax) - p.contactDamping * vel);
  return 0.0;
}

void SimPlant::step(double dt) {
  const double L = p.springFreeLength;
  double fLeft = tension(h - x[0] - L);
  double fRight = tension(x[1] - h - L);
  double cLeft = 0.0, cRight = 0.0;
  double gap = h - x[0] - p.bumper;
  if (gap < 0.0) cLeft = fmax(0.0, -p.contactStiffness * gap - p.contactDamping * (vh - v[0]));
  gap = x[1] - h - p.bumper;
  if (gap < 0.0) cRight = fmax(0.0, -p.contactStiffness * gap - p.contactDamping * (v[1] - vh));
  double fh = fRight - fLeft - p.handleDamping * vh + externalForce + cLeft - cRight + railStop(h, vh);
  double i0 = enabled ? current[0] : 0.0, i1 = enabled ? current[1] : 0.0;
  double f[2] = {p.forceConstant * i0 + fLeft - cLeft + railStop(x[0], v[0]),
                 p.forceConstant * i1 - fRight + cRight + railStop(x[1], v[1])};
  vh += fh / p.handleMass * dt;
  h += vh * dt;
  for (int i = 0; i < 2; ++i) {
    double vi = v[i];
    if (vi == 0.0 && fabs(f[i]) <= p.carriageCoulomb) continue;  // stiction
    double friction = -p.carriageViscous * vi - copysign(p.carriageCoulomb, vi != 0.0 ? vi : f[i]);
    double vNew = vi + (f[i] + friction) / p.carriageMass * dt;
    if (vi != 0.0 && vi * vNew < 0.0 && fabs(f[i]) <= p.carriageCoulomb) vNew = 0.0;  // friction never reverses
    v[i] = vNew;
    x[i] += vNew * dt;
  }
}
