// Definitions for the host stand-in of the Arduino core (see Arduino.h).
#include "Arduino.h"

#include <stdio.h>

#include <chrono>

HardwareSerial Serial;
HardwareSerial SerialUSB;

static uint32_t g_pins[128];

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

static std::chrono::steady_clock::time_point start_time() {
  static const std::chrono::steady_clock::time_point t0 = std::chrono::steady_clock::now();
  return t0;
}

uint32_t micros() {
  return static_cast<uint32_t>(
      std::chrono::duration_cast<std::chrono::microseconds>(std::chrono::steady_clock::now() - start_time()).count());
}
uint32_t millis() { return micros() / 1000u; }
void delay(uint32_t ms) {
  uint32_t t0 = millis();
  while (millis() - t0 < ms) {
  }
}
