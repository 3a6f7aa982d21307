// The parts of the Arduino core (ArduinoCore-sam) the sketch calls, as do-nothing bodies for the Cortex-M3
// size build: enough to link and to count the firmware's own code and data. Never flashed. Written for this
// project; no Arduino code is copied.
#include <Arduino.h>

HardwareSerial Serial;
HardwareSerial SerialUSB;

static volatile uint32_t g_pins[128];
static volatile uint32_t g_micros;

extern "C" void SysTick_Handler(void) { g_micros += 1000; }

void pinMode(uint32_t, uint32_t) {}
void digitalWrite(uint32_t pin, uint32_t value) { g_pins[pin & 127] = value; }
int digitalRead(uint32_t pin) { return static_cast<int>(g_pins[pin & 127]); }
void analogWrite(uint32_t pin, uint32_t value) { g_pins[pin & 127] = value; }
uint32_t analogRead(uint32_t pin) { return g_pins[pin & 127]; }
void analogWriteResolution(int) {}
void analogReadResolution(int) {}
void attachInterrupt(uint32_t, void (*)(void), uint32_t) {}
void noInterrupts() {}
void interrupts() {}
int digitalPinToInterrupt(int pin) { return pin; }
uint32_t micros() { return g_micros; }
uint32_t millis() { return g_micros / 1000u; }
void delay(uint32_t ms) {
  uint32_t t0 = millis();
  while (millis() - t0 < ms) {
  }
}

// C++ runtime pieces the core provides (abi.cpp / new.cpp there): no libstdc++ on the target.
void* operator new(size_t size) { return malloc(size); }
void operator delete(void* p) noexcept { free(p); }
void operator delete(void* p, size_t) noexcept { free(p); }
extern "C" void __cxa_pure_virtual(void) {
  for (;;) {
  }
}
