// The project's strict argument helpers on top of CmdMessenger 4.2.0 (docs/linarm-protocol.md rule 7),
// mirrored in Python by ArduinoMessage.read_raw_field() and read_host_message().
//
// For each field: the raw escaped text from readStringArg (4.2.0 does not unescape it), unescaped here
// with its true length (an escaped NUL is data). Integers must match -?[0-9]{1,10}, bools be exactly
// 0/1, floats exactly 4 bytes and finite; then the table's ranges. An argument left over after the last
// one (available()) is a BAD_ARGUMENT.
#ifndef LINARM_COMMAND_READER_H
#define LINARM_COMMAND_READER_H

#include <CmdMessenger.h>
#include <stdint.h>

#include "protocol_generated.h"

namespace wire {

const int MAX_ARGS = 6;
const int MAX_FIELD = 16;  // bytes after unescaping; longer fields are refused anyway

struct ArgValue {
  int32_t i;
  float f;
  bool b;
};

struct Command {
  uint8_t id;
  uint16_t seq;
  const proto::CommandSpec* spec;
  ArgValue args[MAX_ARGS];
};

struct Rejection {
  uint16_t seq;
  uint8_t cmdId;
  proto::ReplyError code;
  const char* message;
};

// Called from a CmdMessenger callback: reads seq and the arguments of the command being dispatched.
// Returns false (and fills *rej) when the command must be answered with ERROR.
bool readCommand(CmdMessenger& m, Command* out, Rejection* rej);

// Building blocks, exposed for the unit tests.
int readRawField(CmdMessenger& m, uint8_t* out, int capacity);  // -1: no field; > capacity: too long
bool parseStrictInt(const uint8_t* data, int len, int64_t* value);

}  // namespace wire

#endif  // LINARM_COMMAND_READER_H
