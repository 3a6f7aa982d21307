// Host-side stand-in for CmdMessenger 4.2.0 (see CmdMessenger.h for what it models).
#include "CmdMessenger.h"

#include <limits.h>
#include <stdio.h>

namespace {

// atol/atoi as on the DUE (newlib, ILP32): long is 32 bits and strtol saturates at LONG_MIN/LONG_MAX, so
// "4294967299" reads as 2147483647 (id 255 after the library's casts), not as 3 as an LP64 atol would.
// The host build must give the DUE's answer, whatever the PC's long is.
int32_t dueAtol(const char* s) {
  while (*s == ' ' || (*s >= '\t' && *s <= '\r')) ++s;
  bool negative = false;
  if (*s == '+' || *s == '-') negative = *s++ == '-';
  const int64_t limit = negative ? -static_cast<int64_t>(INT32_MIN) : static_cast<int64_t>(INT32_MAX);
  int64_t value = 0;
  for (; *s >= '0' && *s <= '9'; ++s) {
    value = value * 10 + (*s - '0');
    if (value > limit) {
      value = limit;  // saturated; the remaining digits change nothing
      while (*s >= '0' && *s <= '9') ++s;
      break;
    }
  }
  return static_cast<int32_t>(negative ? -value : value);
}

int dueAtoi(const char* s) { return static_cast<int>(dueAtol(s)); }  // int is 32 bits on the DUE too

}  // namespace

CmdMessenger::CmdMessenger(Stream& comms, const char fld_separator, const char cmd_separator,
                           const char esc_character)
    : comms_(&comms),
      fieldSeparator_(fld_separator),
      commandSeparator_(cmd_separator),
      escapeCharacter_(esc_character),
      printNewlines_(false),
      // startCommand_ is left alone, as 4.2.0's init() does: a static instance starts zeroed, any other
      // must be built on zeroed memory (host/sim/rig.h, ZeroedMessenger).
      defaultCallback_(0),
      bufferIndex_(0),
      lastChar_(0),
      cursor_(0),
      current_(0),
      argOk_(false),
      lastCommandId_(0),
      overflows_(0) {
  for (int i = 0; i < MAXCALLBACKS; ++i) callbacks_[i] = 0;
  memset(buffer_, 0, sizeof buffer_);
}

void CmdMessenger::feedinSerialData() {
  while (comms_->available() > 0) {
    int c = comms_->read();
    if (c < 0) break;
    processByte(static_cast<char>(c));
  }
}

void CmdMessenger::processByte(char c) {
  bool escaped = lastChar_ == escapeCharacter_;
  lastChar_ = c;
  if (c == escapeCharacter_ && escaped) lastChar_ = 0;  // "//" is a literal '/', it escapes nothing
  if (c == commandSeparator_ && !escaped) {
    buffer_[bufferIndex_] = 0;
    if (bufferIndex_ > 0) {
      handleMessage();
      lastChar_ = 0;
    }
    bufferIndex_ = 0;
    return;
  }
  buffer_[bufferIndex_++] = c;
  if (bufferIndex_ >= MESSENGERBUFFERSIZE - 1) {  // overflow: empty the buffer and go on reading
    ++overflows_;
    bufferIndex_ = 0;
  }
}

void CmdMessenger::handleMessage() {
  cursor_ = 0;
  current_ = 0;
  lastCommandId_ = static_cast<uint8_t>(readInt16Arg());
  if (argOk_ && lastCommandId_ < MAXCALLBACKS && callbacks_[lastCommandId_] != 0) {
    callbacks_[lastCommandId_]();
  } else if (defaultCallback_ != 0) {
    defaultCallback_();
  }
}

size_t CmdMessenger::findNext(const char* str) const {
  // Offset of the next unescaped field separator or unescaped NUL, within the buffer.
  const char* end = buffer_ + MESSENGERBUFFERSIZE;
  char last = 0;
  size_t n = 0;
  while (str + n < end) {
    char c = str[n];
    bool escaped = last == escapeCharacter_;
    last = c;
    if (c == escapeCharacter_ && escaped) last = 0;
    if (!escaped && (c == 0 || c == fieldSeparator_)) return n;
    ++n;
  }
  return n;
}

char* CmdMessenger::next() {
  char* pos = cursor_ ? cursor_ : buffer_;
  char* end = buffer_ + MESSENGERBUFFERSIZE;
  while (pos < end && *pos != 0 && findNext(pos) == 0) ++pos;  // skip leading separators
  if (pos >= end || *pos == 0) {
    cursor_ = pos;
    current_ = 0;
    return 0;
  }
  char* start = pos;
  pos += findNext(pos);
  if (pos < end && *pos != 0) {
    *pos = 0;
    ++pos;
  }
  cursor_ = pos;
  current_ = start;
  return start;
}

int16_t CmdMessenger::readInt16Arg() {
  if (next()) {
    argOk_ = true;
    return static_cast<int16_t>(dueAtoi(current_));
  }
  argOk_ = false;
  return 0;
}

int32_t CmdMessenger::readInt32Arg() {
  if (next()) {
    argOk_ = true;
    return static_cast<int32_t>(dueAtol(current_));
  }
  argOk_ = false;
  return 0;
}

char* CmdMessenger::readStringArg() {
  if (next()) {
    argOk_ = true;
    return current_;  // 4.2.0: still escaped
  }
  argOk_ = false;
  return const_cast<char*>("");
}

void CmdMessenger::unescape(char* fromChar) {
  char* dst = fromChar;
  const char* src = fromChar;
  while (*src != 0) {
    if (*src == escapeCharacter_) {
      ++src;
      if (*src == 0) break;
    }
    *dst++ = *src++;
  }
  *dst = 0;
}

void CmdMessenger::sendCmdStart(byte cmdId) {
  if (startCommand_) return;
  startCommand_ = true;
  comms_->print(static_cast<unsigned int>(cmdId));
}

void CmdMessenger::printEsc(char c) {
  if (c == fieldSeparator_ || c == commandSeparator_ || c == escapeCharacter_ || c == 0)
    comms_->write(static_cast<uint8_t>(escapeCharacter_));
  comms_->write(static_cast<uint8_t>(c));
}

void CmdMessenger::sendCmdEscArg(char* arg) {
  if (!startCommand_) return;
  comms_->print(fieldSeparator_);
  while (*arg) printEsc(*arg++);
}

bool CmdMessenger::sendCmdEnd(bool reqAc, byte, unsigned int) {
  if (reqAc) {
#ifndef LINARM_BARE_METAL  // the Cortex-M3 size build keeps stdio out
    fprintf(stderr, "CmdMessenger (host): sendCmdEnd with reqAc would block the control loop\n");
#endif
    abort();
  }
  if (startCommand_) {
    comms_->print(commandSeparator_);
    if (printNewlines_) comms_->print("\r\n");
  }
  startCommand_ = false;
  return false;
}
