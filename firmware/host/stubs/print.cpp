// Print of the Arduino core stand-in (decimal, other bases and fixed-point floats), shared by the host build
// and the bare-metal Cortex-M3 build. Written for this project; no Arduino code is copied.
#include "Arduino.h"

size_t Print::print(long n, int base) {
  if (base == DEC && n < 0) {  // no printf: the bare-metal build keeps stdio out, as the DUE's core does
    size_t sign = print('-');
    return sign + print(0ul - static_cast<unsigned long>(n), DEC);
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
