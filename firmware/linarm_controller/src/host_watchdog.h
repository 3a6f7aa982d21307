// Host-silence watchdog: armed by the first host byte; expires after WATCHDOG_TIMEOUT_MS without one.
#ifndef LINARM_HOST_WATCHDOG_H
#define LINARM_HOST_WATCHDOG_H

#include <stdint.h>

#include "protocol_generated.h"

class HostWatchdog {
 public:
  HostWatchdog() : seen_(false), last_(0) {}
  void feed(uint32_t nowTick) {
    seen_ = true;
    last_ = nowTick;
  }
  bool expired(uint32_t nowTick) const {
    return seen_ && static_cast<uint32_t>(nowTick - last_) > proto::WATCHDOG_TIMEOUT_MS;
  }
  uint32_t silenceMs(uint32_t nowTick) const { return static_cast<uint32_t>(nowTick - last_); }

 private:
  bool seen_;
  uint32_t last_;
};

#endif  // LINARM_HOST_WATCHDOG_H
