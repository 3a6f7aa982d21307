// The link to the LINarm++ Manager: CmdMessenger callbacks for every command of the protocol table,
// the replies (ACK / ERROR / IDENTIFY), the error events and the state stream. Runs in loop() context:
// nothing here blocks (no sendCmd with an ack request, ever).
#ifndef LINARM_APP_H
#define LINARM_APP_H

#include <CmdMessenger.h>
#include <stdint.h>

#include "linarm.h"
#include "command_reader.h"

class LinarmApp {
 public:
  LinarmApp(CmdMessenger& messenger, Stream& comms, Linarm& linarm, Hal& hal, const char* firmwareVersion);
  void begin();         // attach the callbacks, send the boot IDENTIFY (seq 0)
  void poll();          // host bytes: feed the watchdog, dispatch complete commands
  void controlTick();   // one 1 kHz period: control step, error events, stream
  bool streaming() const { return streamEnabled_; }
  uint32_t streamPeriodTicks() const { return streamTicks_; }

 private:
  static void onCommand();
  static void onUnknown();
  void handle();
  void execute(const wire::Command& cmd);
  void sendAck(const wire::Command& cmd, const wire::ArgValue* returns, int count);
  void sendError(uint16_t seq, uint8_t cmdId, uint8_t code, const char* message);
  void sendIdentify(uint16_t seq);
  void sendErrorEvent(const ErrorEventOut& e);
  void sendStateFrames(bool forceLinarmState);
  void sendLinarmState();
  void sendMotorState(uint8_t index);
  void sendVsaState();
  void sendText(const char* text);

  CmdMessenger& messenger_;
  Stream& comms_;
  Linarm& linarm_;
  Hal& hal_;
  const char* firmwareVersion_;
  bool streamEnabled_;
  uint32_t streamTicks_, streamStart_, streamCount_;
  bool lastLinarmValid_;
  uint8_t lastLinarm_[10];
  static LinarmApp* instance_;
};

#endif  // LINARM_APP_H
