// The few Arduino core and C++ runtime pieces the firmware's logic links against on the MPS2 board. Written
// for this project; no Arduino code is copied.
#include <Arduino.h>

#include "mps2_board.h"

uint32_t millis() { return mps2::millis(); }
uint32_t micros() { return mps2::millis() * 1000u; }
void noInterrupts() { mps2::disableIrq(); }
void interrupts() { mps2::enableIrq(); }

void* operator new(size_t size) { return malloc(size); }
void operator delete(void* p) noexcept { free(p); }
void operator delete(void* p, size_t) noexcept { free(p); }
extern "C" void __cxa_pure_virtual(void) {
  for (;;) {
  }
}
