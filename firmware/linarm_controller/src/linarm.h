// The Linarm object: FSM (IDLE / HOME / ON), homing on the endstroke switches, the five control modes,
// trajectories, the per-motor position loops at 1 kHz, supervision with latching error states and the
// host-silence watchdog. No I/O besides the Hal; the protocol lives in LinarmApp.
//
// Mirrors the controller part of app/devices/sim/linarm_model.py (LinarmSimCore): same states, same
// replies, same limits. Command methods return the protocol's reply code (0 = accepted).
#ifndef LINARM_LINARM_H
#define LINARM_LINARM_H

#include <stdint.h>

#include "linarm_config.h"
#include "linarm_hal.h"
#include "safety_limits.h"
#include "pid.h"
#include "protocol_generated.h"
#include "trajectory.h"
#include "host_watchdog.h"

struct Result {
  uint8_t code;  // 0 = accepted, else proto::ReplyError
  const char* message;
  static Result ok() { Result r = {0, ""}; return r; }
  static Result refuse(proto::ReplyError code, const char* message) {
    Result r = {static_cast<uint8_t>(code), message};
    return r;
  }
  bool accepted() const { return code == 0; }
};

struct Measurement {
  float x[2];      // m, carriage positions
  float v[2];      // m/s
  float h;         // m, handle
  float vh;        // m/s
  float force;     // N, + pushes the handle towards +x
  float current[2];  // A, measured
  bool endstroke[2];
};

struct ErrorEventOut {
  uint32_t tUs;
  proto::ErrorState error;
  proto::ControlState state;
  const char* message;
};

class Linarm {
 public:
  explicit Linarm(Hal& hal);
  void begin();
  void tick();                 // one control period (call at 1 kHz)
  void hostActivity() { watchdog_.feed(ticks_); }  // any host byte
  bool takeErrorEvent(ErrorEventOut* out);
  // Host build only: encoders referenced as if homed, carriages and handle at the given positions.
  void presetHomed(float x0, float x1, float handle);

  // Commands (names and arguments as in the protocol table)
  Result setDemo(bool demo);
  Result resetError();
  Result setCtrlState(uint8_t state);
  Result setCtrlMode(uint8_t mode);
  Result setCentreVelocity(float v);
  Result setDeltaVelocity(float v);
  Result moveCentreTo(float target, float maxVel, float maxAcc, float execTime, bool trigger);
  Result moveDeltaTo(float target, float maxVel, float maxAcc, float execTime, bool trigger);
  Result setStiffness(float k, float maxVel, float maxAcc, float execTime);
  Result goToHome();
  Result setTrajectoryType(uint8_t type);
  Result setAdmittanceParameter(float ka);
  Result setAssistanceParameter(float kt);
  Result setAssistanceTargetPos(float pos);
  Result enableVirtualVsa(bool on);
  Result setVirtualVsaSpringDisplacement(float disp);
  Result disableEndstrokes(bool disable);
  Result setTriggerMode(uint8_t mode);
  Result setTriggerParameter(float param);
  Result setMotorOffset(uint8_t index, float offset);
  Result setMobileOffset(float offset);
  Result setMotorRatio(uint8_t index, float ratio);
  Result setMobileRatio(float ratio);
  Result setMaxTrackingError(float v);
  Result setMaxForce(float v);
  Result setMaxCurrent(float v);
  Result setMaxAcceleration(float v);
  Result setMaxVelocity(float v);
  Result setHomeParameter(float centre, float delta, float velocity);
  Result setPosLimit(float minPos, float maxPos);
  Result setPidTunings(uint8_t index, float kp, float ki, float kd);
  Result lockEnvelope();  // the current limits become the envelope until restart

  // State
  uint32_t ticks() const { return ticks_; }
  proto::ControlState controlState() const { return ctrlState_; }
  proto::ControlMode controlMode() const { return ctrlMode_; }
  proto::HomeState homeState() const { return homeState_; }
  proto::ErrorState errorState() const { return errorState_; }
  proto::TriggerMode triggerMode() const { return triggerMode_; }
  proto::TrajectoryType trajectoryType() const { return trajectoryType_; }
  bool initialized() const { return initialized_; }
  bool demo() const { return demo_; }
  bool virtualVsa() const { return virtualVsa_; }
  bool endstrokesDisabled() const { return endstrokesDisabled_; }
  bool motorsOn() const { return ctrlState_ != proto::IDLE_CTRL_STATE; }
  const Measurement& measurement() const { return meas_; }
  float commandedCurrent(int i) const { return cmdCurrent_[i]; }
  float motorReference(int i) const { return motorRef_[i]; }
  float centreReference() const { return centreRef_; }
  float deltaReference() const { return deltaRef_; }
  const Limits& limits() const { return limits_; }
  bool envelopeLocked() const { return locked_; }
  const Limits& envelope() const { return envelope_; }
  bool serviceMode() const { return serviceMode_; }
  const Pid& pid(int i) const { return pid_[i]; }
  float admittance() const { return ka_; }
  float assistance() const { return kt_; }
  float assistanceTarget() const { return assistTarget_; }

 private:
  void measure();
  void readPositions(float x[2], float* h) const;
  void supervise();
  void latch(proto::ErrorState error, const char* message);
  void motorsOff();
  void clearMotion();
  void motorsOnFromMeasurement();
  void setMotorRefs(float centre, float delta, float centreVel, float deltaVel);
  void references();
  void checkTriggers();
  void motorLoops();
  void kinematicDemo();
  void startHoming();
  void startMoveHome();
  void homing();
  void referenceMotor(int i, float position);
  uint32_t seekTimeoutTicks() const;
  float seekVelocity() const;  // homingVelocity, never above the locked maxVelocity
  bool homingBusy() const;
  Result plan(Trajectory* out, float start, float target, float maxVel, float maxAcc, float execTime,
              bool trigger);
  Result moveDelta(float target, float maxVel, float maxAcc, float execTime, bool trigger);
  bool serviceLocked() const { return locked_ && !serviceMode_; }

  Hal& hal_;
  uint32_t ticks_;
  proto::ControlState ctrlState_;
  proto::ControlMode ctrlMode_;
  proto::HomeState homeState_;
  proto::ErrorState errorState_;
  proto::TriggerMode triggerMode_;
  proto::TrajectoryType trajectoryType_;
  float triggerParam_;
  bool initialized_, demo_, virtualVsa_, endstrokesDisabled_;
  float virtualDisp_;
  Limits limits_;
  Limits envelope_;   // what lockEnvelope() froze; limits_ stays inside it
  bool locked_;       // until restart: nothing clears it
  bool serviceMode_;  // the service jumper, read at boot (begin)
  float homeCentre_, homeDelta_, homingVelocity_;
  float ka_, kt_, assistTarget_;
  Pid pid_[2];
  float motorRatio_[2], motorOffset_[2], mobileRatio_, mobileOffset_;
  float centreRef_, deltaRef_, centreVelRef_, deltaVelRef_, centreVelCmd_, deltaVelCmd_;
  Trajectory centreTraj_, deltaTraj_;
  float motorRef_[2], motorVelRef_[2];
  float cmdCurrent_[2];
  uint32_t homeDeadline_, settleUntil_;
  bool settling_;
  OverCurrentTimer overCurrent_;
  HostWatchdog watchdog_;
  Measurement meas_;
  int32_t countHist_[3][cfg::VELOCITY_WINDOW + 1];
  unsigned int histIndex_, histFill_;
  float demoX_[2], demoV_[2], demoH_, demoVh_;
  bool eventPending_;
  ErrorEventOut event_;
};

#endif  // LINARM_LINARM_H
