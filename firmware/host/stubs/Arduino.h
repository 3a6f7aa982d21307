// Host stand-in for the parts of the Arduino core (ArduinoCore-sam) the firmware uses.
// Enough to compile the DUE-specific files on Linux (syntax and type checks) and to run the
// host-side CmdMessenger layer. Written for this project; no Arduino code is copied.
#ifndef LINARM_HOST_ARDUINO_H
#define LINARM_HOST_ARDUINO_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef uint8_t byte;
typedef bool boolean;

#define HIGH 0x1
#define LOW 0x0
#define INPUT 0x0
#define OUTPUT 0x1
#define INPUT_PULLUP 0x2
#define CHANGE 2
#define FALLING 3
#define RISING 4
#define DEC 10
#define HEX 16
#define BIN 2

// Pin names of the DUE used by the sketch (values as on the board's variant).
#define A0 54
#define A1 55
#define A2 56
#define A3 57
#define DAC0 66
#define DAC1 67

void pinMode(uint32_t pin, uint32_t mode);
void digitalWrite(uint32_t pin, uint32_t value);
int digitalRead(uint32_t pin);
void analogWrite(uint32_t pin, uint32_t value);
uint32_t analogRead(uint32_t pin);
void analogWriteResolution(int bits);
void analogReadResolution(int bits);
void attachInterrupt(uint32_t pin, void (*callback)(void), uint32_t mode);
void noInterrupts();
void interrupts();
uint32_t millis();
uint32_t micros();
void delay(uint32_t ms);
int digitalPinToInterrupt(int pin);

class Print {
 public:
  virtual ~Print() {}
  virtual size_t write(uint8_t c) = 0;
  virtual size_t write(const uint8_t* buffer, size_t size) {
    size_t n = 0;
    while (size--) n += write(*buffer++);
    return n;
  }
  size_t write(const char* str) { return str ? write(reinterpret_cast<const uint8_t*>(str), strlen(str)) : 0; }
  size_t print(const char* str) { return write(str); }
  size_t print(char c) { return write(static_cast<uint8_t>(c)); }
  size_t print(unsigned char n, int base = DEC) { return print(static_cast<unsigned long>(n), base); }
  size_t print(int n, int base = DEC) { return print(static_cast<long>(n), base); }
  size_t print(unsigned int n, int base = DEC) { return print(static_cast<unsigned long>(n), base); }
  size_t print(long n, int base = DEC);
  size_t print(unsigned long n, int base = DEC);
  size_t print(double n, int digits = 2);
  size_t println(const char* str) { return print(str) + print("\r\n"); }
};

class Stream : public Print {
 public:
  virtual int available() = 0;
  virtual int read() = 0;
  virtual int peek() = 0;
  virtual void flush() {}
  size_t readBytes(char* buffer, size_t length) {
    size_t n = 0;
    while (n < length && available() > 0) buffer[n++] = static_cast<char>(read());
    return n;
  }
};

// A serial port on the host: an in-memory stream (the tests and the SIL pump it).
class HardwareSerial : public Stream {
 public:
  void begin(unsigned long) {}
  int available() override { return 0; }
  int read() override { return -1; }
  int peek() override { return -1; }
  size_t write(uint8_t) override { return 1; }
  using Print::write;
  operator bool() { return true; }
};

extern HardwareSerial Serial;
extern HardwareSerial SerialUSB;

#endif  // LINARM_HOST_ARDUINO_H
