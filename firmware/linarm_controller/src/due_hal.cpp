#include "due_hal.h"

#include "linarm_config.h"

namespace {

const float ADC_FULL_SCALE = 4095.0f;  // 12-bit
const uint32_t PWM_FULL_SCALE = 4095;  // analogWriteResolution(12)
const float FORCE_RANGE = 200.0f;      // N at full scale

// Encoder state: counts and the last (A, B) pair per channel; written only in the ISRs.
volatile int32_t g_counts[3] = {0, 0, 0};
volatile uint8_t g_state[3] = {0, 0, 0};
const uint8_t ENC_A[3] = {pins::ENC_MOTOR_A[0], pins::ENC_MOTOR_A[1], pins::ENC_MOBILE_A};
const uint8_t ENC_B[3] = {pins::ENC_MOTOR_B[0], pins::ENC_MOTOR_B[1], pins::ENC_MOBILE_B};
// x4 decoding: index (previous AB << 2 | new AB) -> step
const int8_t QUAD_STEP[16] = {0, 1, -1, 0, -1, 0, 0, 1, 1, 0, 0, -1, 0, -1, 1, 0};

inline void decode(int ch) {
  uint8_t ab = static_cast<uint8_t>((digitalRead(ENC_A[ch]) ? 2 : 0) | (digitalRead(ENC_B[ch]) ? 1 : 0));
  g_counts[ch] += QUAD_STEP[(g_state[ch] << 2) | ab];
  g_state[ch] = ab;
}

void isrEnc0() { decode(0); }
void isrEnc1() { decode(1); }
void isrEnc2() { decode(2); }

}  // namespace

void DueHal::begin() {
  pinMode(pins::SERVICE_JUMPER, INPUT_PULLUP);
  delay(2);  // let the pull-up charge the pin before it is read, once
  serviceJumper_ = digitalRead(pins::SERVICE_JUMPER) == LOW;
  analogWriteResolution(12);
  analogReadResolution(12);
  for (int i = 0; i < 2; ++i) {
    pinMode(pins::MOTOR_ENABLE[i], OUTPUT);
    digitalWrite(pins::MOTOR_ENABLE[i], LOW);
    pinMode(pins::MOTOR_DIR[i], OUTPUT);
    pinMode(pins::MOTOR_PWM[i], OUTPUT);
    analogWrite(pins::MOTOR_PWM[i], 0);
    pinMode(pins::ENDSTROKE[i], INPUT_PULLUP);
  }
  void (*isr[3])() = {isrEnc0, isrEnc1, isrEnc2};
  for (int ch = 0; ch < 3; ++ch) {
    pinMode(ENC_A[ch], INPUT_PULLUP);
    pinMode(ENC_B[ch], INPUT_PULLUP);
    g_state[ch] = static_cast<uint8_t>((digitalRead(ENC_A[ch]) ? 2 : 0) | (digitalRead(ENC_B[ch]) ? 1 : 0));
    attachInterrupt(digitalPinToInterrupt(ENC_A[ch]), isr[ch], CHANGE);
    attachInterrupt(digitalPinToInterrupt(ENC_B[ch]), isr[ch], CHANGE);
  }
}

uint32_t DueHal::micros() { return ::micros(); }

int32_t DueHal::motorCount(uint8_t index) { return g_counts[index & 1]; }  // 32-bit reads are atomic

int32_t DueHal::mobileCount() { return g_counts[2]; }

bool DueHal::endstroke(uint8_t index) { return digitalRead(pins::ENDSTROKE[index & 1]) == LOW; }

void DueHal::enableMotors(bool on) {
  for (int i = 0; i < 2; ++i) {
    if (!on) analogWrite(pins::MOTOR_PWM[i], 0);
    digitalWrite(pins::MOTOR_ENABLE[i], on ? HIGH : LOW);
  }
}

void DueHal::setMotorCurrent(uint8_t index, float amps) {
  index &= 1;
  float duty = fabsf(amps) / cfg::CURRENT_HW_LIMIT;
  if (duty > 1.0f) duty = 1.0f;
  digitalWrite(pins::MOTOR_DIR[index], amps >= 0.0f ? HIGH : LOW);
  analogWrite(pins::MOTOR_PWM[index], static_cast<uint32_t>(duty * PWM_FULL_SCALE + 0.5f));
}

float DueHal::motorCurrent(uint8_t index) {
  float u = static_cast<float>(analogRead(pins::MOTOR_CURRENT[index & 1])) / ADC_FULL_SCALE;
  return (2.0f * u - 1.0f) * cfg::CURRENT_HW_LIMIT;
}

float DueHal::handleForceSensor() {
  float u = static_cast<float>(analogRead(pins::FORCE_SENSOR)) / ADC_FULL_SCALE;
  return (2.0f * u - 1.0f) * FORCE_RANGE;
}
