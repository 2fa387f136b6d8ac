// Build-time configuration of the pivla arm firmware (ATmega328P / Arduino Uno, 16 MHz).
// Values a maker may change at run time (watchdog, speeds, per-channel limits) live in EEPROM and are
// set over the serial protocol; the constants here are the compiled-in defaults and hard ceilings.
#pragma once
#include <stdint.h>

#define FW_VERSION_MAJOR 1
#define FW_VERSION_MINOR 0
#define FW_VERSION_PATCH 0
#define PROTOCOL_VERSION 1

// Six joints + gripper.
#define N_CHANNELS 7

// Servo driver: 0 = Timer1-driven pulses on Uno pins (SERVO_PINS), 1 = PCA9685 over I2C (Wire).
#define DRIVER_TIMER1 0
#define DRIVER_PCA9685 1
#ifndef SERVO_DRIVER
#define SERVO_DRIVER DRIVER_TIMER1
#endif

// Uno digital pins for channels 0..6 with the Timer1 driver (D2..D8).
#define SERVO_PINS {2, 3, 4, 5, 6, 7, 8}
// PCA9685: I2C address and the output channels used for channels 0..6.
#define PCA9685_ADDRESS 0x40
#define PCA9685_OUTPUTS {0, 1, 2, 3, 4, 5, 6}

// Servo frame period (hobby servos expect ~50 Hz).
#define SERVO_FRAME_US 20000
// Absolute pulse bounds no configuration can exceed.
#define PULSE_ABS_MIN_US 500
#define PULSE_ABS_MAX_US 2500
// Defaults for an uncalibrated board: a narrow band around the servo centre.
#define PULSE_DEFAULT_MIN_US 1000
#define PULSE_DEFAULT_MAX_US 2000
#define PULSE_DEFAULT_HOME_US 1500

// Motion: speeds in pulse-microseconds per second, acceleration in us/s^2.
#define SPEED_DEFAULT_US_S 600
#define SPEED_MAX_US_S 1500
#define SPEED_CEILING_US_S 6000
#define ACCEL_DEFAULT_US_S2 4000
#define MOTION_PERIOD_MS 10

// Host watchdog: hold position when no valid frame arrives for this long.
#define WATCHDOG_DEFAULT_MS 500
#define WATCHDOG_MIN_MS 50
#define WATCHDOG_MAX_MS 10000

// A frame that stays incomplete this long is dropped (answered with ERR_TIMEOUT).
#define FRAME_TIMEOUT_MS 50

#define SERIAL_BAUD 115200
