// Point-to-point trajectories: trapezoidal or cycloidal, planned from (maxVel, maxAcc) or for a fixed
// execution time. Time is counted in control ticks so that long sessions keep millisecond precision.
#ifndef LINARM_TRAJECTORY_H
#define LINARM_TRAJECTORY_H

#include <stdint.h>

#include "protocol_generated.h"

class Trajectory {
 public:
  enum PlanResult { PLAN_OK = 0, PLAN_BAD_LIMITS, PLAN_TOO_SHORT };

  Trajectory();
  // execTime > 0: trapezoid in thirds (v = 1.5 D/T, a = 4.5 D/T^2), cycloid with v = 2 D/T,
  // a = 2 pi D/T^2; both must stay within maxVel / maxAcc. Otherwise the profile comes from them.
  PlanResult plan(double start, double target, double maxVel, double maxAcc, double execTime,
                  proto::TrajectoryType type);
  void startAt(uint32_t tick) { t0_ = tick; armed_ = false; active_ = true; }
  void arm() { armed_ = true; active_ = true; }  // waits for a trigger
  void clear() { active_ = false; armed_ = false; }
  bool active() const { return active_; }
  bool armed() const { return active_ && armed_; }
  // Position/velocity at a controller tick; returns true once finished (at the target).
  bool sample(uint32_t tick, double* pos, double* vel) const;
  double start() const { return start_; }
  double target() const { return target_; }
  double duration() const { return duration_; }
  double peakVelocity() const;

 private:
  double start_, target_, duration_, tAcc_, vPeak_;
  proto::TrajectoryType type_;
  uint32_t t0_;
  bool armed_, active_;
};

#endif  // LINARM_TRAJECTORY_H
