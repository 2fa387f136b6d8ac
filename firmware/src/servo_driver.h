// Servo output back ends. Exactly one is compiled in, chosen by SERVO_DRIVER in config.h.
#pragma once
#include <stdint.h>

// Starts producing pulses; `pulses_us` holds the initial width of each channel.
void servo_begin(const uint16_t* pulses_us);
// Sets the pulse width of one channel from the next servo frame on (interrupt-safe).
void servo_write(uint8_t channel, uint16_t pulse_us);
