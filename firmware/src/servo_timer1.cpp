// Timer1 servo driver: pulses the channels one after another inside each 20 ms frame, like the classic
// Servo library (which Debian does not ship). Timer1 runs in CTC mode at 2 MHz (0.5 us per tick); each
// compare interrupt ends the running pulse and starts the next one, then waits out the rest of the frame.
#include "config.h"
#if SERVO_DRIVER == DRIVER_TIMER1
#include <Arduino.h>
#include "servo_driver.h"

static const uint8_t kPins[N_CHANNELS] = SERVO_PINS;
static volatile uint8_t* out_reg[N_CHANNELS];
static uint8_t out_mask[N_CHANNELS];
static volatile uint16_t ticks[N_CHANNELS];
static volatile int8_t active = -1;
static uint16_t frame_used;

static const uint16_t kFrameTicks = (uint16_t)(SERVO_FRAME_US * 2UL);

static inline uint16_t us_to_ticks(uint16_t us) {
  if (us < PULSE_ABS_MIN_US) us = PULSE_ABS_MIN_US;
  if (us > PULSE_ABS_MAX_US) us = PULSE_ABS_MAX_US;
  return us * 2;
}

ISR(TIMER1_COMPA_vect) {
  if (active >= 0) *out_reg[active] &= ~out_mask[active];
  active++;
  if (active < N_CHANNELS) {
    *out_reg[active] |= out_mask[active];
    uint16_t t = ticks[active];
    OCR1A = t - 1;
    frame_used += t;
  } else {
    OCR1A = kFrameTicks - frame_used - 1;
    frame_used = 0;
    active = -1;
  }
}

void servo_begin(const uint16_t* pulses_us) {
  for (uint8_t i = 0; i < N_CHANNELS; i++) {
    pinMode(kPins[i], OUTPUT);
    digitalWrite(kPins[i], LOW);
    out_reg[i] = portOutputRegister(digitalPinToPort(kPins[i]));
    out_mask[i] = digitalPinToBitMask(kPins[i]);
    ticks[i] = us_to_ticks(pulses_us[i]);
  }
  uint8_t sreg = SREG;
  cli();
  TCCR1A = 0;
  TCCR1B = _BV(WGM12) | _BV(CS11);  // CTC on OCR1A, clk/8
  TCNT1 = 0;
  OCR1A = 2000;  // first frame starts 1 ms from now
  frame_used = 0;
  active = -1;
  TIFR1 = _BV(OCF1A);
  TIMSK1 = _BV(OCIE1A);
  SREG = sreg;
}

void servo_write(uint8_t channel, uint16_t pulse_us) {
  if (channel >= N_CHANNELS) return;
  uint16_t t = us_to_ticks(pulse_us);
  uint8_t sreg = SREG;
  cli();
  ticks[channel] = t;
  SREG = sreg;
}
#endif
