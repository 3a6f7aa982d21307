#include "trajectory.h"

#include <math.h>


static const double PI_D = 3.14159265358979323846;

Trajectory::Trajectory()
    : start_(0), target_(0), duration_(0), tAcc_(0), vPeak_(0), type_(proto::TRAPEZOIDAL), t0_(0),
      armed_(false), active_(false) {}

Trajectory::PlanResult Trajectory::plan(double start, double target, double maxVel, double maxAcc,
                                        double execTime, proto::TrajectoryType type) {
  active_ = false;
  armed_ = false;
  start_ = start;
  target_ = target;
  type_ = type;
  tAcc_ = 0;
  vPeak_ = 0;
  duration_ = 0;
  double dist = fabs(target - start);
  if (maxVel <= 0.0 || maxAcc <= 0.0) return PLAN_BAD_LIMITS;
  if (dist == 0.0) return PLAN_OK;
  if (execTime > 0.0) {
    double T = execTime;
    double vPk, aPk;
    if (type == proto::CYCLOIDAL) {
      vPk = 2 * dist / T;
      aPk = 2 * PI_D * dist / (T * T);
    } else {
      vPk = 1.5 * dist / T;
      aPk = 4.5 * dist / (T * T);
    }
    if (vPk > maxVel * (1 + 1e-6) || aPk > maxAcc * (1 + 1e-6)) return PLAN_TOO_SHORT;
    duration_ = T;
    if (type != proto::CYCLOIDAL) {
      tAcc_ = T / 3;
      vPeak_ = vPk;
    }
    return PLAN_OK;
  }
  if (type == proto::CYCLOIDAL) {
    double a = 2 * dist / maxVel;
    double b = sqrt(2 * PI_D * dist / maxAcc);
    duration_ = a > b ? a : b;
    return PLAN_OK;
  }
  if (dist >= maxVel * maxVel / maxAcc) {
    tAcc_ = maxVel / maxAcc;
    vPeak_ = maxVel;
    duration_ = 2 * tAcc_ + (dist - maxVel * tAcc_) / maxVel;
  } else {
    vPeak_ = sqrt(dist * maxAcc);
    tAcc_ = vPeak_ / maxAcc;
    duration_ = 2 * tAcc_;
  }
  return PLAN_OK;
}

double Trajectory::peakVelocity() const {
  if (type_ == proto::CYCLOIDAL) return duration_ > 0 ? 2 * fabs(target_ - start_) / duration_ : 0.0;
  return vPeak_;
}

bool Trajectory::sample(uint32_t tick, double* pos, double* vel) const {
  if (armed_) {
    *pos = start_;
    *vel = 0.0;
    return false;
  }
  double tau = static_cast<double>(static_cast<uint32_t>(tick - t0_)) * 1e-3;  // ticks are 1 ms
  double d = target_ - start_;
  if (tau >= duration_ || duration_ <= 0.0) {
    *pos = target_;
    *vel = 0.0;
    return true;
  }
  double sign = d >= 0 ? 1.0 : -1.0;
  if (type_ == proto::CYCLOIDAL) {
    double r = tau / duration_;
    *pos = start_ + d * (r - sin(2 * PI_D * r) / (2 * PI_D));
    *vel = d / duration_ * (1 - cos(2 * PI_D * r));
    return false;
  }
  double a = tAcc_ > 0 ? vPeak_ / tAcc_ : 0.0;
  double s, v;
  if (tau < tAcc_) {
    s = 0.5 * a * tau * tau;
    v = a * tau;
  } else if (tau < duration_ - tAcc_) {
    s = 0.5 * a * tAcc_ * tAcc_ + vPeak_ * (tau - tAcc_);
    v = vPeak_;
  } else {
    double rem = duration_ - tau;
    s = fabs(d) - 0.5 * a * rem * rem;
    v = a * rem;
  }
  *pos = start_ + sign * s;
  *vel = sign * v;
  return false;
}
