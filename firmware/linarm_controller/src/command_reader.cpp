#include "command_reader.h"

#include <math.h>
#include <string.h>

namespace wire {

int readRawField(CmdMessenger& m, uint8_t* out, int capacity) {
  const char* p = m.readStringArg();
  if (!m.isArgOk()) return -1;
  int n = 0;
  // Walk the escaped text: a '/' makes the next byte data (even NUL); an unescaped NUL ends the field.
  while (n <= capacity) {
    char c = *p;
    if (c == 0) break;
    if (c == '/') {
      ++p;
      c = *p;
    }
    if (n < capacity) out[n] = static_cast<uint8_t>(c);
    ++n;
    ++p;
  }
  return n;
}

bool parseStrictInt(const uint8_t* data, int len, int64_t* value) {
  int i = 0;
  bool negative = false;
  if (len > 0 && data[0] == '-') {
    negative = true;
    i = 1;
  }
  int digits = len - i;
  if (digits < 1 || digits > 10) return false;
  int64_t v = 0;
  for (; i < len; ++i) {
    if (data[i] < '0' || data[i] > '9') return false;
    v = v * 10 + (data[i] - '0');
  }
  *value = negative ? -v : v;
  return true;
}

static bool reject(Rejection* rej, uint16_t seq, uint8_t id, proto::ReplyError code, const char* message) {
  rej->seq = seq;
  rej->cmdId = id;
  rej->code = code;
  rej->message = message;
  return false;
}

static bool convert(const proto::ArgSpec& spec, const uint8_t* data, int len, ArgValue* v, proto::ReplyError* code,
                    const char** message) {
  *code = proto::BAD_ARGUMENT;
  v->i = 0;
  v->f = 0.0f;
  v->b = false;
  switch (spec.kind) {
    case proto::ARG_F32: {
      if (len != 4) {
        *message = "expected a float32 (4 bytes)";
        return false;
      }
      float f;
      memcpy(&f, data, 4);  // little-endian on the DUE and on x86
      if (isnan(f) || isinf(f)) {
        *message = "float is not finite";
        return false;
      }
      if ((spec.hasMin && f < spec.minF) || (spec.hasMax && f > spec.maxF)) {
        *code = proto::OUT_OF_RANGE;
        *message = "outside the table range";
        return false;
      }
      v->f = f;
      return true;
    }
    case proto::ARG_BOOL:
      if (len != 1 || (data[0] != '0' && data[0] != '1')) {
        *message = "expected 0 or 1";
        return false;
      }
      v->b = data[0] == '1';
      return true;
    case proto::ARG_INT: {
      int64_t value;
      if (!parseStrictInt(data, len, &value)) {
        *message = "not an integer";
        return false;
      }
      if ((spec.hasMin && value < spec.minI) || (spec.hasMax && value > spec.maxI)) {
        *code = proto::OUT_OF_RANGE;
        *message = "outside the table range";
        return false;
      }
      v->i = static_cast<int32_t>(value);
      return true;
    }
    default:
      *message = "unsupported argument kind";
      return false;
  }
}

bool readCommand(CmdMessenger& m, Command* out, Rejection* rej) {
  const uint8_t id = m.commandID();
  if (!m.isArgOk()) return reject(rej, 0, id, proto::UNKNOWN_COMMAND, "message without a command id");
  uint8_t seqRaw[MAX_FIELD];
  int seqLen = readRawField(m, seqRaw, MAX_FIELD);
  int64_t seqValue = -1;
  bool seqOk = seqLen > 0 && seqLen <= MAX_FIELD && parseStrictInt(seqRaw, seqLen, &seqValue) &&
               seqValue >= proto::SEQ_MIN && seqValue <= proto::SEQ_MAX;
  uint16_t seq = seqOk ? static_cast<uint16_t>(seqValue) : 0;
  const proto::CommandSpec* spec = proto::findCommand(id);
  if (spec == 0) return reject(rej, seq, id, proto::UNKNOWN_COMMAND, "no command with this id");
  if (!seqOk) return reject(rej, 0, id, proto::BAD_ARGUMENT, "missing or bad sequence number");
  uint8_t raw[MAX_ARGS][MAX_FIELD];
  int lens[MAX_ARGS];
  int n = 0;
  for (; n < spec->argCount && n < MAX_ARGS; ++n) {
    lens[n] = readRawField(m, raw[n], MAX_FIELD);
    if (lens[n] < 0) break;
  }
  bool extra = n == spec->argCount && m.available();
  if (n != spec->argCount || extra) return reject(rej, seq, id, proto::BAD_ARGUMENT, "wrong number of arguments");
  for (int k = 0; k < n; ++k) {
    proto::ReplyError code;
    const char* message = "";
    if (!convert(spec->args[k], raw[k], lens[k] > MAX_FIELD ? MAX_FIELD + 1 : lens[k], &out->args[k], &code,
                 &message))
      return reject(rej, seq, id, code, message);
  }
  out->id = id;
  out->seq = seq;
  out->spec = spec;
  return true;
}

}  // namespace wire
