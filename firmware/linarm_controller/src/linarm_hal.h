// Hardware abstraction: what the controller needs from the robot. DueHal (due_hal.h) drives the real
// LINarm2 from an Arduino DUE; the host build has SimHal (a simple plant) behind the same interface.
#ifndef LINARM_LINARM_HAL_H
#define LINARM_LINARM_HAL_H

#include <stdint.h>

class Hal {
 public:
  virtual ~Hal() {}
  virtual void begin() = 0;
  // Time: microseconds since boot (wraps every 2^32 us, as Arduino's micros()).
  virtual uint32_t micros() = 0;
  // Quadrature encoders, counts since power-up: the motors' (0, 1) and the handle's (mobile).
  virtual int32_t motorCount(uint8_t index) = 0;
  virtual int32_t mobileCount() = 0;
  // Endstroke switches: 0 = the min switch (touched by motor 0), 1 = the max switch (motor 1).
  virtual bool endstroke(uint8_t index) = 0;
  // Current-controlled drives: PWM duty and direction for `amps`; 0 with enable off.
  virtual void enableMotors(bool on) = 0;
  virtual void setMotorCurrent(uint8_t index, float amps) = 0;
  virtual float motorCurrent(uint8_t index) = 0;  // measured (A)
  // Handle force sensor (N, + pushes towards +x). The controller estimates the interaction force from the
  // spring elongations (as the simulator does); the sensor value is kept for diagnostics.
  virtual float handleForceSensor() = 0;
  // The service jumper, read once at boot: calibration, endstroke and PID work stay possible after the
  // envelope lock only when the controller booted with it fitted (docs/linarm-protocol.md, "Safety envelope").
  virtual bool serviceJumper() = 0;
};

#endif  // LINARM_LINARM_HAL_H
