// Hal of the host build: encoders, switches and drives of a SimPlant; time in whole control ticks.
#ifndef LINARM_SIM_HAL_H
#define LINARM_SIM_HAL_H

#include <math.h>

#include "linarm_hal.h"
#include "sim_plant.h"

class SimHal : public Hal {
 public:
  explicit SimHal(SimPlant& plant, bool serviceJumper = false)
      : plant_(plant), us_(0), serviceJumper_(serviceJumper) {}
  void begin() override {}
  uint32_t micros() override { return us_; }
  void advanceMicros(uint32_t us) { us_ += us; }
  int32_t motorCount(uint8_t i) override {
    return static_cast<int32_t>(lround((plant_.x[i & 1] - plant_.xPower[i & 1]) / plant_.p.encoderResolution));
  }
  int32_t mobileCount() override {
    return static_cast<int32_t>(lround((plant_.h - plant_.hPower) / plant_.p.encoderResolution));
  }
  bool endstroke(uint8_t i) override {
    return (i & 1) == 0 ? plant_.x[0] <= plant_.p.switchMin : plant_.x[1] >= plant_.p.switchMax;
  }
  void enableMotors(bool on) override { plant_.enabled = on; }
  void setMotorCurrent(uint8_t i, float amps) override {
    double limit = plant_.p.currentHwLimit;
    plant_.current[i & 1] = amps > limit ? limit : (amps < -limit ? -limit : amps);
  }
  float motorCurrent(uint8_t i) override {
    return plant_.enabled ? static_cast<float>(plant_.current[i & 1]) : 0.0f;
  }
  float handleForceSensor() override { return static_cast<float>(plant_.externalForce); }
  bool serviceJumper() override { return serviceJumper_; }

 private:
  SimPlant& plant_;
  uint32_t us_;
  bool serviceJumper_;
};

#endif  // LINARM_SIM_HAL_H
