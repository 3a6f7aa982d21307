#include "linarm_app.h"

#include <math.h>

#include "vsa.h"

// Frame layouts are written here by hand; these fail the build if the table grows or shrinks.
static_assert(proto::MSG_LINARM_STATE_FIELD_COUNT == 11, "LINARM_STATE layout changed in the protocol table");
static_assert(proto::MSG_MOTOR_STATE_FIELD_COUNT == 6, "MOTOR_STATE layout changed in the protocol table");
static_assert(proto::MSG_VSA_STATE_FIELD_COUNT == 7, "VSA_STATE layout changed in the protocol table");
static_assert(proto::MSG_ERROR_EVENT_FIELD_COUNT == 4, "ERROR_EVENT layout changed in the protocol table");
static_assert(proto::MSG_IDENTIFY_FIELD_COUNT == 4, "IDENTIFY layout changed in the protocol table");
static_assert(proto::MSG_ERROR_FIELD_COUNT == 4, "ERROR layout changed in the protocol table");
static_assert(proto::COMMAND_ID_MAX < proto::MAX_CALLBACKS, "command ids must stay below MAXCALLBACKS");

LinarmApp* LinarmApp::instance_ = 0;

LinarmApp::LinarmApp(CmdMessenger& messenger, Stream& comms, Linarm& linarm, Hal& hal, const char* firmwareVersion)
    : messenger_(messenger), comms_(comms), linarm_(linarm), hal_(hal), firmwareVersion_(firmwareVersion),
      streamEnabled_(false), streamTicks_(proto::DEFAULT_STREAM_PERIOD_MS), streamStart_(0), streamCount_(0),
      lastLinarmValid_(false) {
  for (int i = 0; i < 10; ++i) lastLinarm_[i] = 0;
}

void LinarmApp::begin() {
  instance_ = this;
  messenger_.printLfCr(false);  // no "\r\n" after ';' (the host does not need it)
  messenger_.attach(onUnknown);
  for (uint8_t id = 0; id < proto::COMMAND_COUNT; ++id) messenger_.attach(id, onCommand);
  sendIdentify(0);  // the boot message
}

void LinarmApp::poll() {
  if (comms_.available() > 0) linarm_.hostActivity();  // any host byte feeds the watchdog
  messenger_.feedinSerialData();
}

void LinarmApp::controlTick() {
  linarm_.tick();
  ErrorEventOut e;
  if (linarm_.takeErrorEvent(&e)) sendErrorEvent(e);
  // whole-millisecond schedule: the first frames go out on the tick after startDataStream
  if (streamEnabled_ && (linarm_.ticks() - streamStart_) % streamTicks_ == 0) {
    sendStateFrames(streamCount_ % proto::LINARM_STATE_DIVIDER == 0);
    ++streamCount_;
  }
}

// ------------------------------------------------------------------------------------------ dispatch
void LinarmApp::onCommand() {
  if (instance_) instance_->handle();
}

void LinarmApp::onUnknown() {
  if (instance_) instance_->handle();  // readCommand answers UNKNOWN_COMMAND (with the seq if it parses)
}

void LinarmApp::handle() {
  wire::Command cmd;
  wire::Rejection rej;
  if (!wire::readCommand(messenger_, &cmd, &rej)) {
    sendError(rej.seq, rej.cmdId, rej.code, rej.message);
    return;
  }
  execute(cmd);
}

void LinarmApp::execute(const wire::Command& cmd) {
  const wire::ArgValue* a = cmd.args;
  wire::ArgValue ret[7] = {};
  int nret = 0;
  Result r = Result::ok();
  switch (cmd.id) {
    case proto::CMD_IDENTIFY:
      sendIdentify(cmd.seq);
      return;
    case proto::CMD_HEARTBEAT:
      return;  // no reply: its bytes already fed the watchdog
    case proto::CMD_SET_DEMO: r = linarm_.setDemo(a[0].b); break;
    case proto::CMD_RESET_ERROR: r = linarm_.resetError(); break;
    case proto::CMD_SET_CTRL_STATE: r = linarm_.setCtrlState(static_cast<uint8_t>(a[0].i)); break;
    case proto::CMD_SET_CTRL_MODE: r = linarm_.setCtrlMode(static_cast<uint8_t>(a[0].i)); break;
    case proto::CMD_SET_CENTRE_VELOCITY: r = linarm_.setCentreVelocity(a[0].f); break;
    case proto::CMD_SET_DELTA_VELOCITY: r = linarm_.setDeltaVelocity(a[0].f); break;
    case proto::CMD_GET_PID_TUNINGS: {
      const Pid& p = linarm_.pid(a[0].i);
      ret[0].i = a[0].i;
      ret[1].f = p.kp;
      ret[2].f = p.ki;
      ret[3].f = p.kd;
      nret = 4;
      break;
    }
    case proto::CMD_MOVE_CENTRE_TO: r = linarm_.moveCentreTo(a[0].f, a[1].f, a[2].f, a[3].f, a[4].b); break;
    case proto::CMD_MOVE_DELTA_TO: r = linarm_.moveDeltaTo(a[0].f, a[1].f, a[2].f, a[3].f, a[4].b); break;
    case proto::CMD_SET_STIFFNESS: r = linarm_.setStiffness(a[0].f, a[1].f, a[2].f, a[3].f); break;
    case proto::CMD_GO_TO_HOME: r = linarm_.goToHome(); break;
    case proto::CMD_SET_TRAJECTORY_TYPE: r = linarm_.setTrajectoryType(static_cast<uint8_t>(a[0].i)); break;
    case proto::CMD_SET_ADMITTANCE_PARAMETER: r = linarm_.setAdmittanceParameter(a[0].f); break;
    case proto::CMD_GET_ADMITTANCE_PARAMETER: ret[0].f = linarm_.admittance(); nret = 1; break;
    case proto::CMD_SET_ASSISTANCE_PARAMETER: r = linarm_.setAssistanceParameter(a[0].f); break;
    case proto::CMD_GET_ASSISTANCE_PARAMETER: ret[0].f = linarm_.assistance(); nret = 1; break;
    case proto::CMD_SET_ASSISTANCE_TARGET_POS: r = linarm_.setAssistanceTargetPos(a[0].f); break;
    case proto::CMD_GET_ASSISTANCE_TARGET_POS: ret[0].f = linarm_.assistanceTarget(); nret = 1; break;
    case proto::CMD_ENABLE_VIRTUAL_VSA: r = linarm_.enableVirtualVsa(a[0].b); break;
    case proto::CMD_SET_VIRTUAL_VSA_SPRING_DISPLACEMENT: r = linarm_.setVirtualVsaSpringDisplacement(a[0].f); break;
    case proto::CMD_GET_IS_INITIALIZED: ret[0].b = linarm_.initialized(); nret = 1; break;
    case proto::CMD_DISABLE_ENDSTROKES: r = linarm_.disableEndstrokes(a[0].b); break;
    case proto::CMD_SET_TRIGGER_MODE: r = linarm_.setTriggerMode(static_cast<uint8_t>(a[0].i)); break;
    case proto::CMD_SET_TRIGGER_PARAMETER: r = linarm_.setTriggerParameter(a[0].f); break;
    case proto::CMD_START_DATA_STREAM: {
      long ticks = lroundf(a[0].f / cfg::DT);  // the firmware counts whole milliseconds
      streamTicks_ = ticks < 1 ? 1 : static_cast<uint32_t>(ticks);
      streamEnabled_ = true;
      streamStart_ = linarm_.ticks() + 1;
      break;
    }
    case proto::CMD_STOP_DATA_STREAM: streamEnabled_ = false; break;
    case proto::CMD_SET_MOTOR_OFFSET: r = linarm_.setMotorOffset(static_cast<uint8_t>(a[0].i), a[1].f); break;
    case proto::CMD_SET_MOBILE_OFFSET: r = linarm_.setMobileOffset(a[0].f); break;
    case proto::CMD_SET_MOTOR_RATIO: r = linarm_.setMotorRatio(static_cast<uint8_t>(a[0].i), a[1].f); break;
    case proto::CMD_SET_MOBILE_RATIO: r = linarm_.setMobileRatio(a[0].f); break;
    case proto::CMD_SET_MAX_TRACKING_ERROR: r = linarm_.setMaxTrackingError(a[0].f); break;
    case proto::CMD_SET_MAX_FORCE: r = linarm_.setMaxForce(a[0].f); break;
    case proto::CMD_SET_MAX_CURRENT: r = linarm_.setMaxCurrent(a[0].f); break;
    case proto::CMD_SET_MAX_ACCELERATION: r = linarm_.setMaxAcceleration(a[0].f); break;
    case proto::CMD_SET_MAX_VELOCITY: r = linarm_.setMaxVelocity(a[0].f); break;
    case proto::CMD_SET_HOME_PARAMETER: r = linarm_.setHomeParameter(a[0].f, a[1].f, a[2].f); break;
    case proto::CMD_SET_POS_LIMIT: r = linarm_.setPosLimit(a[0].f, a[1].f); break;
    case proto::CMD_SET_PID_TUNINGS:
      r = linarm_.setPidTunings(static_cast<uint8_t>(a[0].i), a[1].f, a[2].f, a[3].f);
      break;
    case proto::CMD_LOCK_ENVELOPE: {
      r = linarm_.lockEnvelope();
      const Limits& e = linarm_.envelope();
      const float values[7] = {e.maxVelocity, e.maxAcceleration, e.maxForce, e.maxCurrent, e.maxTrackingError,
                               e.posMin, e.posMax};
      for (int k = 0; k < 7; ++k) ret[k].f = values[k];
      nret = 7;  // sendAck stops at the table's returnCount
      break;
    }
    case proto::CMD_GET_STATE:
      sendAck(cmd, ret, 0);
      sendStateFrames(true);
      return;
    default:
      sendError(cmd.seq, cmd.id, proto::UNKNOWN_COMMAND, "no handler");
      return;
  }
  if (!r.accepted()) {
    sendError(cmd.seq, cmd.id, r.code, r.message);
    return;
  }
  sendAck(cmd, ret, nret);
}

// ------------------------------------------------------------------------------------------ replies
void LinarmApp::sendText(const char* text) {
  // sendCmdEscArg takes a char*; copy so that string literals stay const. ASCII only, never empty.
  char buf[80];
  size_t n = 0;
  for (; text[n] != 0 && n < sizeof buf - 1; ++n) {
    unsigned char c = static_cast<unsigned char>(text[n]);
    buf[n] = c < 0x80 ? static_cast<char>(c) : '?';
  }
  buf[n] = 0;
  if (n > 0) messenger_.sendCmdEscArg(buf);
}

void LinarmApp::sendAck(const wire::Command& cmd, const wire::ArgValue* returns, int count) {
  messenger_.sendCmdStart(proto::MSG_ACK);
  messenger_.sendCmdArg(static_cast<unsigned long>(cmd.seq));
  messenger_.sendCmdArg(static_cast<unsigned int>(cmd.id));
  for (int k = 0; k < count && k < cmd.spec->returnCount; ++k) {
    switch (cmd.spec->returns[k].kind) {
      case proto::ARG_F32: messenger_.sendCmdBinArg(returns[k].f); break;
      case proto::ARG_BOOL: messenger_.sendCmdArg(returns[k].b ? 1 : 0); break;
      default: messenger_.sendCmdArg(static_cast<long>(returns[k].i)); break;
    }
  }
  messenger_.sendCmdEnd();
}

void LinarmApp::sendError(uint16_t seq, uint8_t cmdId, uint8_t code, const char* message) {
  messenger_.sendCmdStart(proto::MSG_ERROR);
  messenger_.sendCmdArg(static_cast<unsigned long>(seq));
  messenger_.sendCmdArg(static_cast<unsigned int>(cmdId));
  messenger_.sendCmdArg(static_cast<unsigned int>(code));
  sendText(message);
  messenger_.sendCmdEnd();
}

void LinarmApp::sendIdentify(uint16_t seq) {
  messenger_.sendCmdStart(proto::MSG_IDENTIFY);
  messenger_.sendCmdArg(static_cast<unsigned long>(seq));
  messenger_.sendCmdArg(static_cast<unsigned int>(proto::PROTOCOL_VERSION));
  sendText(proto::DEVICE_NAME);
  // "+service" tells the host (and the operator) that calibration stays possible after the lock.
  char version[48];
  size_t n = 0;
  for (; firmwareVersion_[n] != 0 && n < sizeof version - 9; ++n) version[n] = firmwareVersion_[n];
  const char* suffix = linarm_.serviceMode() ? "+service" : "";
  for (size_t k = 0; suffix[k] != 0; ++k) version[n++] = suffix[k];
  version[n] = 0;
  sendText(version);
  messenger_.sendCmdEnd();
}

void LinarmApp::sendErrorEvent(const ErrorEventOut& e) {
  messenger_.sendCmdStart(proto::MSG_ERROR_EVENT);
  messenger_.sendCmdBinArg(static_cast<uint32_t>(e.tUs));
  messenger_.sendCmdArg(static_cast<unsigned int>(e.error));
  messenger_.sendCmdArg(static_cast<unsigned int>(e.state));
  sendText(e.message);
  messenger_.sendCmdEnd();
}

void LinarmApp::sendStateFrames(bool forceLinarmState) {
  uint8_t now[10] = {
      static_cast<uint8_t>(linarm_.controlState()), static_cast<uint8_t>(linarm_.controlMode()),
      static_cast<uint8_t>(linarm_.homeState()),    static_cast<uint8_t>(linarm_.errorState()),
      static_cast<uint8_t>(linarm_.triggerMode()),  static_cast<uint8_t>(linarm_.initialized()),
      static_cast<uint8_t>(linarm_.trajectoryType()), static_cast<uint8_t>(linarm_.demo()),
      static_cast<uint8_t>(linarm_.virtualVsa()),   static_cast<uint8_t>(linarm_.endstrokesDisabled())};
  bool changed = !lastLinarmValid_;
  for (int i = 0; i < 10; ++i) changed = changed || now[i] != lastLinarm_[i];
  if (forceLinarmState || changed) {
    sendLinarmState();
    for (int i = 0; i < 10; ++i) lastLinarm_[i] = now[i];
    lastLinarmValid_ = true;
  }
  sendMotorState(0);
  sendMotorState(1);
  sendVsaState();
}

void LinarmApp::sendLinarmState() {
  messenger_.sendCmdStart(proto::MSG_LINARM_STATE);
  messenger_.sendCmdBinArg(static_cast<uint32_t>(hal_.micros()));
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.controlState()));
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.controlMode()));
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.homeState()));
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.errorState()));
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.triggerMode()));
  messenger_.sendCmdArg(linarm_.initialized() ? 1 : 0);
  messenger_.sendCmdArg(static_cast<unsigned int>(linarm_.trajectoryType()));
  messenger_.sendCmdArg(linarm_.demo() ? 1 : 0);
  messenger_.sendCmdArg(linarm_.virtualVsa() ? 1 : 0);
  messenger_.sendCmdArg(linarm_.endstrokesDisabled() ? 1 : 0);
  messenger_.sendCmdEnd();
}

void LinarmApp::sendMotorState(uint8_t index) {
  const Measurement& m = linarm_.measurement();
  messenger_.sendCmdStart(proto::MSG_MOTOR_STATE);
  messenger_.sendCmdBinArg(static_cast<uint32_t>(hal_.micros()));
  messenger_.sendCmdArg(static_cast<unsigned int>(index));
  messenger_.sendCmdBinArg(static_cast<float>(m.x[index]));
  messenger_.sendCmdBinArg(static_cast<float>(m.v[index]));
  messenger_.sendCmdBinArg(static_cast<float>(linarm_.commandedCurrent(index)));
  messenger_.sendCmdBinArg(static_cast<float>(linarm_.motorReference(index)));
  messenger_.sendCmdEnd();
}

void LinarmApp::sendVsaState() {
  const Measurement& m = linarm_.measurement();
  float delta = vsa::deltaOf(m.x[0], m.x[1]);
  messenger_.sendCmdStart(proto::MSG_VSA_STATE);
  messenger_.sendCmdBinArg(static_cast<uint32_t>(hal_.micros()));
  messenger_.sendCmdBinArg(static_cast<float>(vsa::centreOf(m.x[0], m.x[1])));
  messenger_.sendCmdBinArg(delta);
  messenger_.sendCmdBinArg(static_cast<float>(vsa::stiffness(delta)));
  messenger_.sendCmdBinArg(static_cast<float>(m.h));
  messenger_.sendCmdBinArg(static_cast<float>(m.vh));
  messenger_.sendCmdBinArg(static_cast<float>(m.force));
  messenger_.sendCmdEnd();
}
