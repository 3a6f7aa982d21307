// Hal on the Arduino DUE (SAM3X8E, 3.3 V I/O). Pin map: see pins below and firmware/README.md.
#ifndef LINARM_DUE_HAL_H
#define LINARM_DUE_HAL_H

#include <Arduino.h>

#include "linarm_hal.h"

namespace pins {
// Current-controlled drives (e.g. ESCON 50/5 in current mode): enable, direction, PWM set value.
const uint8_t MOTOR_PWM[2] = {6, 7};        // PWM, 12-bit duty = |I| / CURRENT_HW_LIMIT
const uint8_t MOTOR_DIR[2] = {22, 23};      // HIGH = +x
const uint8_t MOTOR_ENABLE[2] = {24, 25};   // HIGH = enabled
const uint8_t MOTOR_CURRENT[2] = {A0, A1};  // drive's current monitor, 0..3.3 V = -I..+I
// Quadrature encoders (A, B), decoded x4 in pin-change interrupts.
const uint8_t ENC_MOTOR_A[2] = {30, 32};
const uint8_t ENC_MOTOR_B[2] = {31, 33};
const uint8_t ENC_MOBILE_A = 34;
const uint8_t ENC_MOBILE_B = 35;
// Endstroke switches, normally open to GND (INPUT_PULLUP: LOW = closed).
const uint8_t ENDSTROKE[2] = {40, 41};  // 0: min (motor 0), 1: max (motor 1)
// Handle force sensor amplifier, 0..3.3 V = -FORCE_RANGE..+FORCE_RANGE.
const uint8_t FORCE_SENSOR = A2;
// Service jumper to GND (INPUT_PULLUP: LOW = fitted), read once in begin(): fitted at boot = service mode.
const uint8_t SERVICE_JUMPER = 52;
}  // namespace pins

class DueHal : public Hal {
 public:
  DueHal() : serviceJumper_(false) {}
  void begin() override;
  uint32_t micros() override;
  int32_t motorCount(uint8_t index) override;
  int32_t mobileCount() override;
  bool endstroke(uint8_t index) override;
  void enableMotors(bool on) override;
  void setMotorCurrent(uint8_t index, float amps) override;
  float motorCurrent(uint8_t index) override;
  float handleForceSensor() override;
  bool serviceJumper() override { return serviceJumper_; }

 private:
  bool serviceJumper_;  // as read at boot: pulling or fitting the jumper later changes nothing
};

#endif  // LINARM_DUE_HAL_H
