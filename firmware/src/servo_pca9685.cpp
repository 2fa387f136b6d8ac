// PCA9685 servo driver: a 16-channel PWM board on I2C (address PCA9685_ADDRESS) generates the pulses, so
// the Uno only sends a register write when a channel's pulse changes by at least one PWM count.
#include "config.h"
#if SERVO_DRIVER == DRIVER_PCA9685
#include <Arduino.h>
#include <Wire.h>
#include "servo_driver.h"

static const uint8_t kOutputs[N_CHANNELS] = PCA9685_OUTPUTS;
static uint16_t last_counts[N_CHANNELS];

// 25 MHz oscillator / (4096 * 50 Hz) - 1 = 121 -> period 122 * 4096 / 25 us.
static const uint8_t kPrescale = 121;
static const uint32_t kPeriodUs = (uint32_t)(kPrescale + 1) * 4096UL / 25UL;

static void write_reg(uint8_t reg, uint8_t value) {
  Wire.beginTransmission(PCA9685_ADDRESS);
  Wire.write(reg);
  Wire.write(value);
  Wire.endTransmission();
}

static void write_counts(uint8_t channel, uint16_t counts) {
  Wire.beginTransmission(PCA9685_ADDRESS);
  Wire.write((uint8_t)(0x06 + 4 * kOutputs[channel]));  // LEDn_ON_L, auto-increment
  Wire.write(0);
  Wire.write(0);
  Wire.write((uint8_t)(counts & 0xFF));
  Wire.write((uint8_t)(counts >> 8));
  Wire.endTransmission();
}

static uint16_t us_to_counts(uint16_t us) {
  if (us < PULSE_ABS_MIN_US) us = PULSE_ABS_MIN_US;
  if (us > PULSE_ABS_MAX_US) us = PULSE_ABS_MAX_US;
  return (uint16_t)(((uint32_t)us * 4096UL + kPeriodUs / 2) / kPeriodUs);
}

void servo_begin(const uint16_t* pulses_us) {
  Wire.begin();
  Wire.setClock(400000);
  Wire.setWireTimeout(3000, true);  // a missing board must not hang the firmware
  write_reg(0x00, 0x10);            // MODE1: sleep, to set the prescaler
  write_reg(0xFE, kPrescale);
  write_reg(0x00, 0x20);            // MODE1: wake, register auto-increment
  delayMicroseconds(500);
  write_reg(0x01, 0x04);            // MODE2: totem-pole outputs
  for (uint8_t i = 0; i < N_CHANNELS; i++) {
    last_counts[i] = us_to_counts(pulses_us[i]);
    write_counts(i, last_counts[i]);
  }
}

void servo_write(uint8_t channel, uint16_t pulse_us) {
  if (channel >= N_CHANNELS) return;
  uint16_t counts = us_to_counts(pulse_us);
  if (counts == last_counts[channel]) return;
  last_counts[channel] = counts;
  write_counts(channel, counts);
}
#endif
