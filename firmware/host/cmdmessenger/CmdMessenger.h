// Host-side stand-in for the Arduino CmdMessenger library (the firmware pins 4.2.0 on the DUE).
//
// Only the part of the interface the firmware calls, written for this project from the behaviour
// measured in /work/shared/reference/cmdmessenger.md (no library code is copied):
//  * receive: bytes kept with their escapes in a 64-byte buffer; an unescaped ';' ends a message;
//    after 63 stored bytes the buffer is emptied and reading goes on (the tail of an overlong message
//    becomes a new message, usually command 0);
//  * the command id is atoi() of the first field cast to int16 then uint8, with the DUE's atoi (32-bit long,
//    saturating: "4294967299" is id 255, whatever the PC's long); ids < 50 with an attached callback
//    reach it, everything else the default callback;
//  * arguments: leading separators are skipped (empty fields vanish); readStringArg returns the raw,
//    still escaped text; available() advances the cursor like next();
//  * send: sendCmdStart prints the id, sendCmdArg prints text, sendCmdBinArg / sendCmdEscArg escape
//    ',' ';' '/' and NUL, sendCmdEnd prints ';'. There is no length limit when sending.
// sendCmdEnd(reqAc = true) aborts the host program: the firmware must never block waiting for an ack.
// As in 4.2.0, the constructor does not set startCommand: build an instance on zeroed memory (README).
#ifndef LINARM_HOST_CMDMESSENGER_H
#define LINARM_HOST_CMDMESSENGER_H

#include <Arduino.h>

#define MAXCALLBACKS 50
#define MESSENGERBUFFERSIZE 64
#define MAXSTREAMBUFFERSIZE 512
#define DEFAULT_TIMEOUT 5000

typedef void (*messengerCallbackFunction)(void);

class CmdMessenger {
 public:
  explicit CmdMessenger(Stream& comms, const char fld_separator = ',', const char cmd_separator = ';',
                        const char esc_character = '/');

  void printLfCr(bool addNewLine = true) { printNewlines_ = addNewLine; }
  void attach(messengerCallbackFunction newFunction) { defaultCallback_ = newFunction; }
  void attach(byte msgId, messengerCallbackFunction newFunction) {
    if (msgId < MAXCALLBACKS) callbacks_[msgId] = newFunction;
  }
  void feedinSerialData();

  uint8_t commandID() const { return lastCommandId_; }
  bool isArgOk() const { return argOk_; }
  bool available() { return next() != 0; }
  int16_t readInt16Arg();
  int32_t readInt32Arg();
  bool readBoolArg() { return readInt16Arg() != 0; }
  char* readStringArg();
  void unescape(char* fromChar);

  void sendCmdStart(byte cmdId);
  template <class T>
  void sendCmdArg(T arg) {
    if (!startCommand_) return;
    comms_->print(fieldSeparator_);
    comms_->print(arg);
  }
  void sendCmdEscArg(char* arg);
  template <class T>
  void sendCmdBinArg(T arg) {
    if (!startCommand_) return;
    comms_->print(fieldSeparator_);
    const uint8_t* bytes = reinterpret_cast<const uint8_t*>(&arg);
    for (unsigned int i = 0; i < sizeof(T); ++i) printEsc(static_cast<char>(bytes[i]));
  }
  bool sendCmdEnd(bool reqAc = false, byte ackCmdId = 1, unsigned int timeout = DEFAULT_TIMEOUT);

  // Host-only instrumentation (the tests read it).
  unsigned long overflows() const { return overflows_; }

 private:
  void processByte(char c);
  void handleMessage();
  char* next();
  size_t findNext(const char* str) const;
  void printEsc(char c);

  Stream* comms_;
  char fieldSeparator_;
  char commandSeparator_;
  char escapeCharacter_;
  bool printNewlines_;
  bool startCommand_;
  messengerCallbackFunction defaultCallback_;
  messengerCallbackFunction callbacks_[MAXCALLBACKS];
  char buffer_[MESSENGERBUFFERSIZE];
  uint8_t bufferIndex_;
  char lastChar_;
  char* cursor_;   // where the next argument search starts (NULL: not started)
  char* current_;  // the argument last returned
  bool argOk_;
  uint8_t lastCommandId_;
  unsigned long overflows_;
};

#endif  // LINARM_HOST_CMDMESSENGER_H
