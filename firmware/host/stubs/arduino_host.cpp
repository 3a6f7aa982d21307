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

size_t Print::print(long n, int base) {
  if (base == DEC) {
    char buf[24];
    snprintf(buf, sizeof buf, "%ld", n);
    return write(buf);
  }
  return print(static_cast<unsigned long>(static_cast<uint32_t>(n)), base);
}

size_t Print::print(unsigned long n, int base) {
  char buf[40];
  char* p = &buf[sizeof buf - 1];
  *p = 0;
  if (base < 2) base = 10;
  do {
    unsigned long d = n % static_cast<unsigned long>(base);
    *--p = static_cast<char>(d < 10 ? '0' + d : 'A' + d - 10);
    n /= static_cast<unsigned long>(base);
  } while (n);
  return write(p);
}

size_t Print::print(double number, int digits) {
  // Fixed point with round half up, as the DUE's Print does (nan / inf / ovf for the rest).
  if (isnan(number)) return print("nan");
  if (isinf(number)) return print("inf");
  if (number > 4294967040.0 || number < -4294967040.0) return print("ovf");
  size_t n = 0;
  if (number < 0.0) {
    n += print('-');
    number = -number;
  }
  double rounding = 0.5;
  for (int i = 0; i < digits; ++i) rounding /= 10.0;
  number += rounding;
  unsigned long whole = static_cast<unsigned long>(number);
  double rest = number - static_cast<double>(whole);
  n += print(whole, DEC);
  if (digits > 0) n += print('.');
  while (digits-- > 0) {
    rest *= 10.0;
    unsigned int d = static_cast<unsigned int>(rest);
    n += print(static_cast<unsigned long>(d), DEC);
    rest -= d;
  }
  return n;
}
