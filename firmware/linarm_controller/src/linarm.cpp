#include "linarm.h"

#include <math.h>

#include "controllers.h"
#include "vsa.h"

namespace {

// Values arrive as float32: accept them within a relative 1e-6 of the bounds (as the simulator does).
bool inRange(float value, float lo, float hi) {
  float m = fabsf(lo) > fabsf(hi) ? fabsf(lo) : fabsf(hi);
  float tol = 1e-6f * (m > 1.0f ? m : 1.0f);
  return value >= lo - tol && value <= hi + tol;
}

float clampf(float v, float lo, float hi) { return v < lo ? lo : (v > hi ? hi : v); }

const Result OUT_OF_RANGE_R = {proto::OUT_OF_RANGE, "value out of range"};
const Result SERVICE_ONLY_R = {proto::LOCKED, "envelope locked: service mode only (jumper at boot)"};

}  // namespace

Linarm::Linarm(Hal& hal)
    : hal_(hal), ticks_(0), ctrlState_(proto::IDLE_CTRL_STATE), ctrlMode_(proto::POS_REF_BY_VEL),
      homeState_(proto::HOME_NOT_DONE), errorState_(proto::NO_ERROR), triggerMode_(proto::NO_TRIGGER),
      trajectoryType_(proto::TRAPEZOIDAL), triggerParam_(0.0f), initialized_(false), demo_(false),
      virtualVsa_(false), endstrokesDisabled_(false), virtualDisp_(0.0f), locked_(false), serviceMode_(false),
      homeCentre_(cfg::HOME_CENTRE),
      homeDelta_(cfg::HOME_DELTA), homingVelocity_(cfg::HOMING_VELOCITY), ka_(cfg::ADMITTANCE_KA),
      kt_(cfg::ASSISTANCE_KT), assistTarget_(cfg::ASSISTANCE_TARGET), mobileRatio_(cfg::ENCODER_RESOLUTION),
      mobileOffset_(0.0f), centreRef_(0.0f), deltaRef_(0.0f), centreVelRef_(0.0f), deltaVelRef_(0.0f),
      centreVelCmd_(0.0f), deltaVelCmd_(0.0f), homeDeadline_(0), settleUntil_(0), settling_(false),
      histIndex_(0), histFill_(0), demoH_(0.0f), demoVh_(0.0f), eventPending_(false) {
  for (int i = 0; i < 2; ++i) {
    motorRatio_[i] = cfg::ENCODER_RESOLUTION;
    motorOffset_[i] = 0.0f;
    motorRef_[i] = motorVelRef_[i] = cmdCurrent_[i] = 0.0f;
    demoX_[i] = demoV_[i] = 0.0f;
  }
  for (unsigned int k = 0; k < 3; ++k)
    for (unsigned int j = 0; j <= cfg::VELOCITY_WINDOW; ++j) countHist_[k][j] = 0;
  event_.tUs = 0;
  event_.error = proto::NO_ERROR;
  event_.state = proto::IDLE_CTRL_STATE;
  event_.message = "";
}

void Linarm::begin() {
  serviceMode_ = hal_.serviceJumper();  // only here: service mode is entered at boot or not at all
  hal_.enableMotors(false);
  histFill_ = 0;
  measure();
  setMotorRefs(vsa::centreOf(meas_.x[0], meas_.x[1]), vsa::deltaOf(meas_.x[0], meas_.x[1]), 0.0f, 0.0f);
}

void Linarm::presetHomed(float x0, float x1, float handle) {
  float x[2], h;
  readPositions(x, &h);
  motorOffset_[0] += x0 - x[0];
  motorOffset_[1] += x1 - x[1];
  mobileOffset_ += handle - h;
  initialized_ = true;
  homeState_ = proto::HOME_DONE;
  measure();
  setMotorRefs(vsa::centreOf(meas_.x[0], meas_.x[1]), vsa::deltaOf(meas_.x[0], meas_.x[1]), 0.0f, 0.0f);
}

bool Linarm::takeErrorEvent(ErrorEventOut* out) {
  if (!eventPending_) return false;
  *out = event_;
  eventPending_ = false;
  return true;
}

// ------------------------------------------------------------------------------------------ sensors
void Linarm::readPositions(float x[2], float* h) const {
  for (int i = 0; i < 2; ++i) x[i] = static_cast<float>(hal_.motorCount(i)) * motorRatio_[i] + motorOffset_[i];
  *h = static_cast<float>(hal_.mobileCount()) * mobileRatio_ + mobileOffset_;
}

void Linarm::measure() {
  Measurement& m = meas_;
  int32_t counts[3] = {hal_.motorCount(0), hal_.motorCount(1), hal_.mobileCount()};
  // Velocity: counts over a short window (immune to the offset jumps of homing).
  const unsigned int W = cfg::VELOCITY_WINDOW;
  unsigned int oldest = (histIndex_ + 1) % (W + 1);
  for (int k = 0; k < 3; ++k) countHist_[k][histIndex_] = counts[k];
  float vel[3] = {0.0f, 0.0f, 0.0f};
  if (histFill_ >= W) {
    const float ratios[3] = {motorRatio_[0], motorRatio_[1], mobileRatio_};
    for (int k = 0; k < 3; ++k)
      vel[k] = static_cast<float>(counts[k] - countHist_[k][oldest]) * ratios[k] / (W * cfg::DT);
  } else {
    ++histFill_;
  }
  histIndex_ = oldest;
  if (demo_) {
    m.x[0] = demoX_[0];
    m.x[1] = demoX_[1];
    m.v[0] = demoV_[0];
    m.v[1] = demoV_[1];
    m.h = demoH_;
    m.vh = demoVh_;
    m.force = virtualVsa_ ? vsa::stiffness(vsa::deltaOf(m.x[0], m.x[1])) * virtualDisp_ : 0.0f;
  } else {
    readPositions(m.x, &m.h);
    m.v[0] = vel[0];
    m.v[1] = vel[1];
    m.vh = vel[2];
    m.force = vsa::interactionForce(m.x[0], m.x[1], m.h);
  }
  for (int i = 0; i < 2; ++i) {
    m.current[i] = hal_.motorCurrent(i);
    m.endstroke[i] = hal_.endstroke(i);
  }
}

// ------------------------------------------------------------------------------------------ the loop
void Linarm::tick() {
  measure();
  supervise();
  if (motorsOn()) {
    references();
    motorLoops();
  } else {
    for (int i = 0; i < 2; ++i) {
      cmdCurrent_[i] = 0.0f;
      hal_.setMotorCurrent(i, 0.0f);
      pid_[i].reset();
    }
  }
  if (demo_) kinematicDemo();
  ++ticks_;
}

void Linarm::motorLoops() {
  for (int i = 0; i < 2; ++i) {
    cmdCurrent_[i] = pid_[i].update(motorRef_[i], meas_.x[i], motorVelRef_[i], meas_.v[i], cfg::CURRENT_HW_LIMIT);
    hal_.setMotorCurrent(i, demo_ ? 0.0f : cmdCurrent_[i]);
  }
}

void Linarm::kinematicDemo() {
  // Demo: no robot. The carriages follow their references; the handle sits at the centre, or at the
  // virtual VSA displacement.
  if (motorsOn()) {
    for (int i = 0; i < 2; ++i) {
      demoX_[i] = motorRef_[i];
      demoV_[i] = motorVelRef_[i];
    }
  } else {
    demoV_[0] = demoV_[1] = 0.0f;
  }
  float old = demoH_;
  demoH_ = vsa::centreOf(demoX_[0], demoX_[1]) + (virtualVsa_ ? virtualDisp_ : 0.0f);
  demoVh_ = (demoH_ - old) / cfg::DT;
}

// ------------------------------------------------------------------------------------------ references
void Linarm::setMotorRefs(float centre, float delta, float centreVel, float deltaVel) {
  centreRef_ = centre;
  deltaRef_ = delta;
  centreVelRef_ = centreVel;
  deltaVelRef_ = deltaVel;
  vsa::motorPositions(centre, delta, &motorRef_[0], &motorRef_[1]);
  vsa::motorVelocities(centreVel, deltaVel, &motorVelRef_[0], &motorVelRef_[1]);
}

void Linarm::references() {
  if (ctrlState_ == proto::HOME_CTRL_STATE) {
    homing();
    return;
  }
  checkTriggers();
  float centre = centreRef_, delta = deltaRef_, cv = 0.0f, dv = 0.0f;
  const float vmax = limits_.maxVelocity, amax = limits_.maxAcceleration;
  if (ctrlMode_ == proto::POS_REF_BY_VEL) {
    cv = ctrl::ramp(centreVelRef_, centreVelCmd_, vmax, amax);
    dv = ctrl::ramp(deltaVelRef_, deltaVelCmd_, vmax, amax);
    ctrl::integrateClamped(&centre, &cv, limits_.posMin, limits_.posMax);
    ctrl::integrateClamped(&delta, &dv, cfg::DELTA_MIN, cfg::DELTA_MAX);
  } else {
    if (ctrlMode_ == proto::POS_REF_BY_TARGET_POS || ctrlMode_ == proto::POS_REF_BY_IMPEDANCE) {
      if (centreTraj_.active()) {
        double p, v;
        if (centreTraj_.sample(ticks_, &p, &v)) centreTraj_.clear();
        centre = static_cast<float>(p);
        cv = static_cast<float>(v);
      }
    } else {
      float wanted = ctrlMode_ == proto::POS_REF_BY_ASSISTANCE
                         ? ctrl::assistanceVelocity(ka_, kt_, meas_.force, assistTarget_, meas_.h)
                         : ctrl::admittanceVelocity(ka_, meas_.force);
      cv = ctrl::ramp(centreVelRef_, wanted, vmax, amax);
      ctrl::integrateClamped(&centre, &cv, limits_.posMin, limits_.posMax);
    }
    if (deltaTraj_.active()) {
      double p, v;
      if (deltaTraj_.sample(ticks_, &p, &v)) deltaTraj_.clear();
      delta = static_cast<float>(p);
      dv = static_cast<float>(v);
    }
  }
  setMotorRefs(centre, delta, cv, dv);
}

void Linarm::checkTriggers() {
  Trajectory* trajs[2] = {&centreTraj_, &deltaTraj_};
  for (int k = 0; k < 2; ++k) {
    Trajectory* t = trajs[k];
    if (!t->armed()) continue;
    bool fire = triggerMode_ == proto::TRIGGER_ON_FORCE
                    ? fabsf(meas_.force) >= triggerParam_
                    : fabs(meas_.h - t->target()) <= triggerParam_;
    if (fire) t->startAt(ticks_);
  }
}

// ------------------------------------------------------------------------------------------ homing
float Linarm::seekVelocity() const {
  // The locked envelope holds during homing too (a patient's narrower limits do not slow homing down).
  return locked_ && homingVelocity_ > envelope_.maxVelocity ? envelope_.maxVelocity : homingVelocity_;
}

uint32_t Linarm::seekTimeoutTicks() const {
  return static_cast<uint32_t>((1.5f * (cfg::RAIL_MAX - cfg::RAIL_MIN) / seekVelocity() + 1.0f) * 1000.0f);
}

bool Linarm::homingBusy() const {
  return ctrlState_ == proto::HOME_CTRL_STATE && homeState_ != proto::HOME_DONE;
}

void Linarm::startHoming() {
  motorsOnFromMeasurement();
  ctrlState_ = proto::HOME_CTRL_STATE;
  hal_.enableMotors(!demo_);
  if (initialized_) {
    startMoveHome();
    return;
  }
  if (demo_) {  // no switches to find: the demo positions are the reference
    initialized_ = true;
    startMoveHome();
    return;
  }
  homeState_ = proto::HOME_SEEK_MIN;
  homeDeadline_ = ticks_ + seekTimeoutTicks();
}

void Linarm::startMoveHome() {
  homeState_ = proto::HOME_MOVE_TO_HOME;
  float centre = vsa::centreOf(meas_.x[0], meas_.x[1]);
  float delta = vsa::deltaOf(meas_.x[0], meas_.x[1]);
  setMotorRefs(centre, delta, 0.0f, 0.0f);
  float vel = homingVelocity_ > cfg::HOME_MOVE_MIN_VELOCITY ? homingVelocity_ : cfg::HOME_MOVE_MIN_VELOCITY;
  if (locked_ && vel > envelope_.maxVelocity) vel = envelope_.maxVelocity;  // homing stays in the envelope
  centreTraj_.plan(centre, homeCentre_, vel, limits_.maxAcceleration, 0.0, trajectoryType_);
  deltaTraj_.plan(delta, homeDelta_, vel, limits_.maxAcceleration, 0.0, trajectoryType_);
  centreTraj_.startAt(ticks_);
  deltaTraj_.startAt(ticks_);
  settling_ = false;
}

void Linarm::referenceMotor(int i, float position) {
  // An endstroke switch closed: from now on this is the motor's position.
  float shift = position - meas_.x[i];
  motorOffset_[i] += shift;
  motorRef_[i] += shift;
  meas_.x[i] += shift;
  meas_.force = vsa::interactionForce(meas_.x[0], meas_.x[1], meas_.h);
}

void Linarm::homing() {
  const proto::HomeState hs = homeState_;
  if (hs == proto::HOME_SEEK_MIN || hs == proto::HOME_SEEK_MAX) {
    if (static_cast<int32_t>(ticks_ - homeDeadline_) > 0) {
      latch(proto::HOMING_FAILED, "endstroke not found before the seek timeout");
      return;
    }
    float vel = (hs == proto::HOME_SEEK_MIN ? -1.0f : 1.0f) * seekVelocity();
    for (int i = 0; i < 2; ++i) {
      motorVelRef_[i] = vel;
      // the reference leads by SEEK_LEAD at most: a stalled carriage runs into the timeout instead
      motorRef_[i] = clampf(motorRef_[i] + vel * cfg::DT, meas_.x[i] - cfg::SEEK_LEAD, meas_.x[i] + cfg::SEEK_LEAD);
    }
    if (hs == proto::HOME_SEEK_MIN && meas_.endstroke[0]) {
      referenceMotor(0, cfg::SWITCH_MIN_POS);
      homeState_ = proto::HOME_SEEK_MAX;
      homeDeadline_ = ticks_ + seekTimeoutTicks();
    } else if (hs == proto::HOME_SEEK_MAX && meas_.endstroke[1]) {
      referenceMotor(1, cfg::SWITCH_MAX_POS);
      startMoveHome();
    }
    return;
  }
  if (hs == proto::HOME_MOVE_TO_HOME) {
    double c = centreRef_, d = deltaRef_, cv = 0.0, dv = 0.0;
    bool doneC = true, doneD = true;
    if (centreTraj_.active()) doneC = centreTraj_.sample(ticks_, &c, &cv);
    if (deltaTraj_.active()) doneD = deltaTraj_.sample(ticks_, &d, &dv);
    setMotorRefs(static_cast<float>(c), static_cast<float>(d), static_cast<float>(cv), static_cast<float>(dv));
    if (doneC && doneD) {
      centreTraj_.clear();
      deltaTraj_.clear();
      if (!settling_) {
        settling_ = true;
        settleUntil_ = ticks_ + cfg::HOME_SETTLE_TICKS;
      } else if (static_cast<int32_t>(ticks_ - settleUntil_) >= 0) {
        // at rest and without load the handle sits at the centre: that references its encoder
        if (!demo_) {
          const float shift = vsa::centreOf(meas_.x[0], meas_.x[1]) - meas_.h;
          mobileOffset_ += shift;
          // The state sent with `initialized` must already use the new handle reference.
          meas_.h += shift;
          meas_.force = vsa::interactionForce(meas_.x[0], meas_.x[1], meas_.h);
        }
        initialized_ = true;
        homeState_ = proto::HOME_DONE;
      }
    }
    return;
  }
  setMotorRefs(centreRef_, deltaRef_, 0.0f, 0.0f);  // HOME_DONE: hold
}

// ------------------------------------------------------------------------------------------ supervision
void Linarm::supervise() {
  if (!motorsOn()) return;
  if (watchdog_.expired(ticks_)) {
    latch(proto::WATCHDOG, "no host bytes for 250 ms");
    return;
  }
  SupervisionInput in;
  in.on = ctrlState_ == proto::ON_CTRL_STATE;
  in.demo = demo_;
  in.endstrokesDisabled = endstrokesDisabled_;
  for (int i = 0; i < 2; ++i) {
    in.position[i] = meas_.x[i];
    in.reference[i] = motorRef_[i];
    in.velocity[i] = meas_.v[i];
    in.current[i] = meas_.current[i];
    in.endstroke[i] = meas_.endstroke[i];
  }
  in.handlePos = meas_.h;
  in.handleVel = meas_.vh;
  in.force = meas_.force;
  const char* message = "";
  proto::ErrorState e = locked_ ? checkEnvelope(envelope_, in, &message) : proto::NO_ERROR;
  if (e == proto::NO_ERROR) e = checkLimits(limits_, in, overCurrent_, ticks_, &message);
  if (e != proto::NO_ERROR) latch(e, message);
}

void Linarm::latch(proto::ErrorState error, const char* message) {
  if (errorState_ != proto::NO_ERROR) return;
  errorState_ = error;
  motorsOff();
  event_.tUs = hal_.micros();
  event_.error = error;
  event_.state = ctrlState_;
  event_.message = message;
  eventPending_ = true;
}

void Linarm::motorsOff() {
  ctrlState_ = proto::IDLE_CTRL_STATE;
  if (homeState_ != proto::HOME_DONE) homeState_ = initialized_ ? proto::HOME_DONE : proto::HOME_NOT_DONE;
  for (int i = 0; i < 2; ++i) {
    cmdCurrent_[i] = 0.0f;
    hal_.setMotorCurrent(i, 0.0f);
  }
  hal_.enableMotors(false);
  clearMotion();
}

void Linarm::clearMotion() {
  centreTraj_.clear();
  deltaTraj_.clear();
  centreVelCmd_ = deltaVelCmd_ = 0.0f;
  centreVelRef_ = deltaVelRef_ = 0.0f;
  motorVelRef_[0] = motorVelRef_[1] = 0.0f;
}

void Linarm::motorsOnFromMeasurement() {
  // Bumpless: references at the measured positions, integrators cleared.
  clearMotion();
  setMotorRefs(vsa::centreOf(meas_.x[0], meas_.x[1]), vsa::deltaOf(meas_.x[0], meas_.x[1]), 0.0f, 0.0f);
  pid_[0].reset();
  pid_[1].reset();
  overCurrent_.reset();
}

// ------------------------------------------------------------------------------------------ commands
Result Linarm::setDemo(bool demo) {
  if (ctrlState_ != proto::IDLE_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "IDLE only");
  if (demo != demo_) {
    if (demo) {  // the virtual robot starts at home
      vsa::motorPositions(homeCentre_, homeDelta_, &demoX_[0], &demoX_[1]);
      demoV_[0] = demoV_[1] = 0.0f;
      demoH_ = homeCentre_;
      demoVh_ = 0.0f;
    }
    demo_ = demo;
    initialized_ = false;  // a different "robot": home again
    homeState_ = proto::HOME_NOT_DONE;
  }
  return Result::ok();
}

Result Linarm::resetError() {
  errorState_ = proto::NO_ERROR;
  overCurrent_.reset();
  return Result::ok();
}

Result Linarm::setCtrlState(uint8_t state) {
  if (state == proto::IDLE_CTRL_STATE) {
    motorsOff();
    return Result::ok();
  }
  if (errorState_ != proto::NO_ERROR) return Result::refuse(proto::IN_ERROR, "error latched: resetError first");
  if (homingBusy()) return Result::refuse(proto::BUSY, "homing in progress");
  if (state == proto::HOME_CTRL_STATE) {
    startHoming();
    return Result::ok();
  }
  if (!initialized_) return Result::refuse(proto::NOT_HOMED, "home the robot first");
  if (ctrlState_ != proto::ON_CTRL_STATE) {
    motorsOnFromMeasurement();
    ctrlState_ = proto::ON_CTRL_STATE;
    hal_.enableMotors(!demo_);
  }
  return Result::ok();
}

Result Linarm::setCtrlMode(uint8_t mode) {
  if (homingBusy()) return Result::refuse(proto::BUSY, "homing in progress");
  ctrlMode_ = static_cast<proto::ControlMode>(mode);
  clearMotion();
  return Result::ok();
}

Result Linarm::setCentreVelocity(float v) {
  if (ctrlState_ != proto::ON_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "ON only");
  if (ctrlMode_ != proto::POS_REF_BY_VEL) return Result::refuse(proto::WRONG_MODE, "POS_REF_BY_VEL only");
  if (!inRange(v, -limits_.maxVelocity, limits_.maxVelocity)) return OUT_OF_RANGE_R;
  centreVelCmd_ = v;
  return Result::ok();
}

Result Linarm::setDeltaVelocity(float v) {
  if (ctrlState_ != proto::ON_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "ON only");
  if (ctrlMode_ != proto::POS_REF_BY_VEL) return Result::refuse(proto::WRONG_MODE, "POS_REF_BY_VEL only");
  if (!inRange(v, -limits_.maxVelocity, limits_.maxVelocity)) return OUT_OF_RANGE_R;
  deltaVelCmd_ = v;
  return Result::ok();
}

Result Linarm::plan(Trajectory* out, float start, float target, float maxVel, float maxAcc, float execTime,
                    bool trigger) {
  if (execTime == 0.0f) {
    if (!inRange(maxVel, 1e-6f, limits_.maxVelocity)) return Result::refuse(proto::OUT_OF_RANGE, "maxVel");
    if (!inRange(maxAcc, 1e-6f, limits_.maxAcceleration)) return Result::refuse(proto::OUT_OF_RANGE, "maxAcc");
  }
  float vel = maxVel > 0.0f ? maxVel : limits_.maxVelocity;
  float acc = maxAcc > 0.0f ? maxAcc : limits_.maxAcceleration;
  if (vel > limits_.maxVelocity) vel = limits_.maxVelocity;
  if (acc > limits_.maxAcceleration) acc = limits_.maxAcceleration;
  Trajectory t;
  if (t.plan(start, target, vel, acc, execTime, trajectoryType_) != Trajectory::PLAN_OK)
    return Result::refuse(proto::OUT_OF_RANGE, "trajectory not feasible within maxVel/maxAcc");
  if (trigger) {
    if (triggerMode_ == proto::NO_TRIGGER)
      return Result::refuse(proto::NOT_SUPPORTED, "trigger requested but TRIGGER_MODE is NO_TRIGGER");
    t.arm();
  } else {
    t.startAt(ticks_);
  }
  *out = t;
  return Result::ok();
}

Result Linarm::moveCentreTo(float target, float maxVel, float maxAcc, float execTime, bool trigger) {
  if (ctrlState_ != proto::ON_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "ON only");
  if (ctrlMode_ != proto::POS_REF_BY_TARGET_POS && ctrlMode_ != proto::POS_REF_BY_IMPEDANCE)
    return Result::refuse(proto::WRONG_MODE, "POS_REF_BY_TARGET_POS or POS_REF_BY_IMPEDANCE only");
  if (!inRange(target, limits_.posMin, limits_.posMax)) return Result::refuse(proto::OUT_OF_RANGE, "targetPos");
  return plan(&centreTraj_, centreRef_, target, maxVel, maxAcc, execTime, trigger);
}

Result Linarm::moveDelta(float target, float maxVel, float maxAcc, float execTime, bool trigger) {
  if (ctrlState_ != proto::ON_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "ON only");
  if (ctrlMode_ == proto::POS_REF_BY_VEL) return Result::refuse(proto::WRONG_MODE, "use setDeltaVelocity");
  if (!inRange(target, cfg::DELTA_MIN, cfg::DELTA_MAX)) return Result::refuse(proto::OUT_OF_RANGE, "delta");
  return plan(&deltaTraj_, deltaRef_, target, maxVel, maxAcc, execTime, trigger);
}

Result Linarm::moveDeltaTo(float target, float maxVel, float maxAcc, float execTime, bool trigger) {
  return moveDelta(target, maxVel, maxAcc, execTime, trigger);
}

Result Linarm::setStiffness(float k, float maxVel, float maxAcc, float execTime) {
  if (!inRange(k, vsa::stiffness(cfg::DELTA_MIN), vsa::stiffness(cfg::DELTA_MAX)))
    return Result::refuse(proto::OUT_OF_RANGE, "stiffness");
  return moveDelta(vsa::deltaForStiffness(k), maxVel, maxAcc, execTime, false);
}

Result Linarm::goToHome() {
  if (errorState_ != proto::NO_ERROR) return Result::refuse(proto::IN_ERROR, "error latched: resetError first");
  if (homingBusy()) return Result::refuse(proto::BUSY, "homing in progress");
  startHoming();
  return Result::ok();
}

Result Linarm::setTrajectoryType(uint8_t type) {
  trajectoryType_ = static_cast<proto::TrajectoryType>(type);
  return Result::ok();
}

Result Linarm::setAdmittanceParameter(float ka) {
  if (!inRange(ka, 0.0f, cfg::KA_MAX)) return OUT_OF_RANGE_R;
  ka_ = ka;
  return Result::ok();
}

Result Linarm::setAssistanceParameter(float kt) {
  if (!inRange(kt, 0.0f, cfg::KT_MAX)) return OUT_OF_RANGE_R;
  kt_ = kt;
  return Result::ok();
}

Result Linarm::setAssistanceTargetPos(float pos) {
  if (!inRange(pos, limits_.posMin, limits_.posMax)) return OUT_OF_RANGE_R;
  assistTarget_ = pos;
  return Result::ok();
}

Result Linarm::enableVirtualVsa(bool on) {
  virtualVsa_ = on;
  return Result::ok();
}

Result Linarm::setVirtualVsaSpringDisplacement(float disp) {
  if (!inRange(disp, -cfg::VIRTUAL_DISP_MAX, cfg::VIRTUAL_DISP_MAX)) return OUT_OF_RANGE_R;
  virtualDisp_ = disp;
  return Result::ok();
}

Result Linarm::disableEndstrokes(bool disable) {
  if (disable && serviceLocked()) return SERVICE_ONLY_R;  // enabling them again is always allowed
  endstrokesDisabled_ = disable;
  return Result::ok();
}

Result Linarm::setTriggerMode(uint8_t mode) {
  triggerMode_ = static_cast<proto::TriggerMode>(mode);
  return Result::ok();
}

Result Linarm::setTriggerParameter(float param) {
  triggerParam_ = param;
  return Result::ok();
}

Result Linarm::setMotorOffset(uint8_t index, float offset) {
  if (serviceLocked()) return SERVICE_ONLY_R;  // calibration moves every limit's reference
  if (ctrlState_ != proto::IDLE_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "IDLE only");
  motorOffset_[index & 1] = offset;
  return Result::ok();
}

Result Linarm::setMobileOffset(float offset) {
  if (serviceLocked()) return SERVICE_ONLY_R;  // calibration moves every limit's reference
  if (ctrlState_ != proto::IDLE_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "IDLE only");
  mobileOffset_ = offset;
  return Result::ok();
}

Result Linarm::setMotorRatio(uint8_t index, float ratio) {
  if (serviceLocked()) return SERVICE_ONLY_R;  // calibration moves every limit's reference
  if (ctrlState_ != proto::IDLE_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "IDLE only");
  if (!inRange(ratio, cfg::RATIO_MIN, cfg::RATIO_MAX)) return OUT_OF_RANGE_R;
  motorRatio_[index & 1] = ratio;
  return Result::ok();
}

Result Linarm::setMobileRatio(float ratio) {
  if (serviceLocked()) return SERVICE_ONLY_R;  // calibration moves every limit's reference
  if (ctrlState_ != proto::IDLE_CTRL_STATE) return Result::refuse(proto::WRONG_STATE, "IDLE only");
  if (!inRange(ratio, cfg::RATIO_MIN, cfg::RATIO_MAX)) return OUT_OF_RANGE_R;
  mobileRatio_ = ratio;
  return Result::ok();
}

Result Linarm::setMaxTrackingError(float v) {
  if (!inRange(v, cfg::MAX_TRACKING_ERROR_MIN, cfg::MAX_TRACKING_ERROR_MAX)) return OUT_OF_RANGE_R;
  if (locked_ && v > envelope_.maxTrackingError)
    return Result::refuse(proto::LOCKED, "maxTrackingError beyond the locked envelope (restart to change it)");
  limits_.maxTrackingError = v;
  return Result::ok();
}

Result Linarm::setMaxForce(float v) {
  if (!inRange(v, cfg::MAX_FORCE_MIN, cfg::MAX_FORCE_MAX)) return OUT_OF_RANGE_R;
  if (locked_ && v > envelope_.maxForce)
    return Result::refuse(proto::LOCKED, "maxForce beyond the locked envelope (restart to change it)");
  limits_.maxForce = v;
  return Result::ok();
}

Result Linarm::setMaxCurrent(float v) {
  if (!inRange(v, cfg::MAX_CURRENT_MIN, cfg::CURRENT_HW_LIMIT)) return OUT_OF_RANGE_R;
  if (locked_ && v > envelope_.maxCurrent)
    return Result::refuse(proto::LOCKED, "maxCurrent beyond the locked envelope (restart to change it)");
  limits_.maxCurrent = v;
  return Result::ok();
}

Result Linarm::setMaxAcceleration(float v) {
  if (!inRange(v, cfg::MAX_ACC_MIN, cfg::MAX_ACC_MAX)) return OUT_OF_RANGE_R;
  if (locked_ && v > envelope_.maxAcceleration)
    return Result::refuse(proto::LOCKED, "maxAcceleration beyond the locked envelope (restart to change it)");
  limits_.maxAcceleration = v;
  return Result::ok();
}

Result Linarm::setMaxVelocity(float v) {
  if (!inRange(v, cfg::MAX_VEL_MIN, cfg::MAX_VEL_MAX)) return OUT_OF_RANGE_R;
  if (locked_ && v > envelope_.maxVelocity)
    return Result::refuse(proto::LOCKED, "maxVelocity beyond the locked envelope (restart to change it)");
  limits_.maxVelocity = v;
  return Result::ok();
}

Result Linarm::setHomeParameter(float centre, float delta, float velocity) {
  if (homingBusy()) return Result::refuse(proto::BUSY, "homing in progress");
  if (!inRange(centre, limits_.posMin, limits_.posMax)) return Result::refuse(proto::OUT_OF_RANGE, "homeCentre");
  if (!inRange(delta, cfg::DELTA_MIN, cfg::DELTA_MAX)) return Result::refuse(proto::OUT_OF_RANGE, "homeDelta");
  if (!inRange(velocity, cfg::HOMING_VELOCITY_MIN, limits_.maxVelocity))
    return Result::refuse(proto::OUT_OF_RANGE, "homingVelocity");
  homeCentre_ = centre;
  homeDelta_ = delta;
  homingVelocity_ = velocity;
  return Result::ok();
}

Result Linarm::setPosLimit(float minPos, float maxPos) {
  if (!inRange(minPos, cfg::RAIL_MIN, cfg::RAIL_MAX)) return Result::refuse(proto::OUT_OF_RANGE, "minPos");
  if (!inRange(maxPos, minPos + cfg::POS_LIMIT_MIN_SPAN, cfg::RAIL_MAX))
    return Result::refuse(proto::OUT_OF_RANGE, "maxPos");
  if (locked_ && (minPos < envelope_.posMin || maxPos > envelope_.posMax))
    return Result::refuse(proto::LOCKED, "position limits beyond the locked envelope (restart to change them)");
  limits_.posMin = minPos;
  limits_.posMax = maxPos;
  return Result::ok();
}

Result Linarm::setPidTunings(uint8_t index, float kp, float ki, float kd) {
  if (!inRange(kp, 0.0f, cfg::KP_MAX) || !inRange(ki, 0.0f, cfg::KI_MAX) || !inRange(kd, 0.0f, cfg::KD_MAX))
    return OUT_OF_RANGE_R;
  if (serviceLocked()) return SERVICE_ONLY_R;  // the loop gains are part of what was validated
  Pid& p = pid_[index & 1];
  p.kp = kp;
  p.ki = ki;
  p.kd = kd;
  return Result::ok();
}

Result Linarm::lockEnvelope() {
  // Locking again can only narrow: the limits are inside the envelope already.
  envelope_ = limits_;
  locked_ = true;
  return Result::ok();
}
