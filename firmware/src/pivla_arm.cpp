// pivla arm firmware: receives framed commands over USB serial, checks them against per-channel limits,
// and moves the servos with rate- and acceleration-limited motion. Safety lives here as well as on the
// host: out-of-limit or corrupt commands are rejected without moving anything, and a watchdog holds the
// arm still when the host stops talking. Protocol: protocol.h and docs/robot.md.
#include <Arduino.h>
#include <avr/eeprom.h>
#include <avr/wdt.h>
#include <math.h>

#include "config.h"
#include "protocol.h"
#include "servo_driver.h"

struct Limits {
  uint16_t min_us, max_us, home_us;
};

struct Settings {
  uint16_t magic;
  uint16_t watchdog_ms;
  uint16_t default_speed;
  uint16_t max_speed;
  uint16_t accel;
  Limits limits[N_CHANNELS];
  uint16_t crc;
};

static const uint16_t kSettingsMagic = 0x5056 + PROTOCOL_VERSION;
static Settings settings;
static bool settings_are_defaults;

static float pos[N_CHANNELS];  // commanded pulse now (us)
static float vel[N_CHANNELS];  // us/s
static uint16_t target[N_CHANNELS];
static float move_speed;
static uint8_t flags;
static uint16_t error_count;
static uint32_t last_valid_ms;
static uint32_t last_motion_ms;
static FrameParser parser;

// Keep the hardware watchdog off after a watchdog reset until setup() re-arms it.
void disable_wdt_early(void) __attribute__((naked, used, section(".init3")));
void disable_wdt_early(void) {
  MCUSR = 0;
  wdt_disable();
}

static uint16_t settings_crc(const Settings& s) {
  uint16_t crc = 0xFFFF;
  const uint8_t* p = (const uint8_t*)&s;
  for (size_t i = 0; i < offsetof(Settings, crc); i++) crc = crc16_ccitt(crc, p[i]);
  return crc;
}

static void load_settings() {
  eeprom_read_block(&settings, (const void*)0, sizeof(settings));
  if (settings.magic == kSettingsMagic && settings.crc == settings_crc(settings)) {
    settings_are_defaults = false;
    return;
  }
  settings.magic = kSettingsMagic;
  settings.watchdog_ms = WATCHDOG_DEFAULT_MS;
  settings.default_speed = SPEED_DEFAULT_US_S;
  settings.max_speed = SPEED_MAX_US_S;
  settings.accel = ACCEL_DEFAULT_US_S2;
  for (uint8_t i = 0; i < N_CHANNELS; i++)
    settings.limits[i] = {PULSE_DEFAULT_MIN_US, PULSE_DEFAULT_MAX_US, PULSE_DEFAULT_HOME_US};
  settings.crc = settings_crc(settings);
  settings_are_defaults = true;
}

static void save_settings() {
  settings.crc = settings_crc(settings);
  eeprom_update_block(&settings, (void*)0, sizeof(settings));
  settings_are_defaults = false;
}

static void put_byte(uint8_t b) { Serial.write(b); }

static inline uint16_t get_u16(const uint8_t* p) { return (uint16_t)p[0] | ((uint16_t)p[1] << 8); }
static inline uint8_t* put_u16(uint8_t* p, uint16_t v) {
  p[0] = (uint8_t)(v & 0xFF);
  p[1] = (uint8_t)(v >> 8);
  return p + 2;
}

static void reply_error(uint8_t seq, uint8_t code, uint8_t cmd) {
  error_count++;
  uint8_t payload[2] = {code, cmd};
  write_frame(put_byte, seq, CMD_ERROR, payload, 2);
}

static uint16_t round_pulse(float us) { return (uint16_t)(us + 0.5f); }

static void hold_position() {
  for (uint8_t i = 0; i < N_CHANNELS; i++) {
    target[i] = round_pulse(pos[i]);
    pos[i] = target[i];
    vel[i] = 0;
  }
}

static void reply_state(uint8_t seq, uint8_t cmd) {
  uint8_t payload[1 + 4 * N_CHANNELS + 6];
  uint8_t* p = payload;
  bool moving = false;
  for (uint8_t i = 0; i < N_CHANNELS; i++) moving |= round_pulse(pos[i]) != target[i];
  *p++ = flags | (moving ? FLAG_MOVING : 0) | (settings_are_defaults ? FLAG_EEPROM_DEFAULTS : 0);
  for (uint8_t i = 0; i < N_CHANNELS; i++) p = put_u16(p, round_pulse(pos[i]));
  for (uint8_t i = 0; i < N_CHANNELS; i++) p = put_u16(p, target[i]);
  uint32_t now = millis();
  p = put_u16(p, (uint16_t)(now & 0xFFFF));
  p = put_u16(p, (uint16_t)(now >> 16));
  p = put_u16(p, error_count);
  write_frame(put_byte, seq, cmd | REPLY_FLAG, payload, (uint8_t)(p - payload));
}

static void reply_config(uint8_t seq, uint8_t cmd) {
  uint8_t payload[8];
  uint8_t* p = payload;
  p = put_u16(p, settings.watchdog_ms);
  p = put_u16(p, settings.default_speed);
  p = put_u16(p, settings.max_speed);
  put_u16(p, settings.accel);
  write_frame(put_byte, seq, cmd | REPLY_FLAG, payload, sizeof(payload));
}

static void reply_limits(uint8_t seq, uint8_t cmd, uint8_t ch) {
  uint8_t payload[7];
  payload[0] = ch;
  uint8_t* p = payload + 1;
  p = put_u16(p, settings.limits[ch].min_us);
  p = put_u16(p, settings.limits[ch].max_us);
  put_u16(p, settings.limits[ch].home_us);
  write_frame(put_byte, seq, cmd | REPLY_FLAG, payload, sizeof(payload));
}

static float clamp_speed(uint16_t requested) {
  uint16_t s = requested ? requested : settings.default_speed;
  return (float)(s > settings.max_speed ? settings.max_speed : s);
}

// Executes one verified frame. Returns true if it was a valid command (resets the host watchdog).
static bool dispatch(const Frame& f) {
  const uint8_t* in = f.payload;
  switch (f.cmd) {
    case CMD_PING: {
      if (f.len != 0) break;
      uint8_t payload[8] = {PROTOCOL_VERSION, FW_VERSION_MAJOR, FW_VERSION_MINOR, FW_VERSION_PATCH,
                            N_CHANNELS, SERVO_DRIVER, SERIAL_RX_BUFFER_SIZE, MAX_PAYLOAD};
      write_frame(put_byte, f.seq, CMD_PING | REPLY_FLAG, payload, sizeof(payload));
      return true;
    }
    case CMD_SET_TARGETS: {
      if (f.len != 2 + 2 * N_CHANNELS) break;
      if (flags & FLAG_ESTOP) {
        reply_error(f.seq, ERR_ESTOP, f.cmd);
        return false;
      }
      uint16_t wanted[N_CHANNELS];
      for (uint8_t i = 0; i < N_CHANNELS; i++) {
        wanted[i] = get_u16(in + 2 + 2 * i);
        if (wanted[i] < settings.limits[i].min_us || wanted[i] > settings.limits[i].max_us) {
          reply_error(f.seq, ERR_LIMIT, f.cmd);
          return false;
        }
      }
      move_speed = clamp_speed(get_u16(in));
      for (uint8_t i = 0; i < N_CHANNELS; i++) target[i] = wanted[i];
      flags &= ~FLAG_WATCHDOG;
      reply_state(f.seq, f.cmd);
      return true;
    }
    case CMD_GET_STATE:
      if (f.len != 0) break;
      reply_state(f.seq, f.cmd);
      return true;
    case CMD_HOME:
      if (f.len != 2) break;
      if (flags & FLAG_ESTOP) {
        reply_error(f.seq, ERR_ESTOP, f.cmd);
        return false;
      }
      move_speed = clamp_speed(get_u16(in));
      for (uint8_t i = 0; i < N_CHANNELS; i++) target[i] = settings.limits[i].home_us;
      flags &= ~FLAG_WATCHDOG;
      reply_state(f.seq, f.cmd);
      return true;
    case CMD_ESTOP:
      if (f.len != 0) break;
      hold_position();
      flags |= FLAG_ESTOP;
      reply_state(f.seq, f.cmd);
      return true;
    case CMD_CLEAR_ESTOP:
      if (f.len != 0) break;
      hold_position();
      flags &= ~(FLAG_ESTOP | FLAG_WATCHDOG);
      reply_state(f.seq, f.cmd);
      return true;
    case CMD_SET_CONFIG: {
      if (f.len != 8) break;
      uint16_t wd = get_u16(in), def = get_u16(in + 2), mx = get_u16(in + 4), acc = get_u16(in + 6);
      if (wd < WATCHDOG_MIN_MS || wd > WATCHDOG_MAX_MS || def == 0 || def > mx || mx > SPEED_CEILING_US_S ||
          acc < 100) {
        reply_error(f.seq, ERR_PAYLOAD, f.cmd);
        return false;
      }
      settings.watchdog_ms = wd;
      settings.default_speed = def;
      settings.max_speed = mx;
      settings.accel = acc;
      save_settings();
      reply_config(f.seq, f.cmd);
      return true;
    }
    case CMD_GET_CONFIG:
      if (f.len != 0) break;
      reply_config(f.seq, f.cmd);
      return true;
    case CMD_SET_LIMITS: {
      if (f.len != 7) break;
      uint8_t ch = in[0];
      uint16_t lo = get_u16(in + 1), hi = get_u16(in + 3), home = get_u16(in + 5);
      if (ch >= N_CHANNELS || lo < PULSE_ABS_MIN_US || hi > PULSE_ABS_MAX_US || lo + 20 > hi || home < lo ||
          home > hi) {
        reply_error(f.seq, ERR_PAYLOAD, f.cmd);
        return false;
      }
      // Never let new limits strand the servo outside them (that would force a move).
      uint16_t now_us = round_pulse(pos[ch]);
      if (now_us < lo || now_us > hi || target[ch] < lo || target[ch] > hi) {
        reply_error(f.seq, ERR_STATE, f.cmd);
        return false;
      }
      settings.limits[ch] = {lo, hi, home};
      save_settings();
      reply_limits(f.seq, f.cmd, ch);
      return true;
    }
    case CMD_GET_LIMITS:
      if (f.len != 1) break;
      if (in[0] >= N_CHANNELS) {
        reply_error(f.seq, ERR_PAYLOAD, f.cmd);
        return false;
      }
      reply_limits(f.seq, f.cmd, in[0]);
      return true;
    default:
      reply_error(f.seq, ERR_UNKNOWN_CMD, f.cmd);
      return false;
  }
  reply_error(f.seq, ERR_LENGTH, f.cmd);
  return false;
}

// Trapezoidal profile per channel: accelerate up to move_speed, brake so as to stop on the target.
static void update_motion(float dt) {
  float accel = settings.accel;
  for (uint8_t i = 0; i < N_CHANNELS; i++) {
    float err = (float)target[i] - pos[i];
    float dist = fabsf(err);
    if (dist < 0.5f && fabsf(vel[i]) < accel * dt) {
      pos[i] = target[i];
      vel[i] = 0;
    } else {
      float vmax = sqrtf(2.0f * accel * dist);
      if (vmax > move_speed) vmax = move_speed;
      float desired = err > 0 ? vmax : -vmax;
      float dv = desired - vel[i];
      float max_dv = accel * dt;
      if (dv > max_dv) dv = max_dv;
      if (dv < -max_dv) dv = -max_dv;
      vel[i] += dv;
      float step = vel[i] * dt;
      if ((err > 0 && step > err) || (err < 0 && step < err)) {
        pos[i] = target[i];
        vel[i] = 0;
      } else {
        pos[i] += step;
      }
    }
    // Motion is bounded by the channel's limits whatever happened before (e.g. a limit change).
    if (pos[i] < settings.limits[i].min_us) pos[i] = settings.limits[i].min_us;
    if (pos[i] > settings.limits[i].max_us) pos[i] = settings.limits[i].max_us;
    servo_write(i, round_pulse(pos[i]));
  }
}

void setup() {
  load_settings();
  uint16_t start[N_CHANNELS];
  for (uint8_t i = 0; i < N_CHANNELS; i++) {
    start[i] = target[i] = settings.limits[i].home_us;
    pos[i] = start[i];
    vel[i] = 0;
  }
  move_speed = settings.default_speed;
  servo_begin(start);
  Serial.begin(SERIAL_BAUD);
  last_valid_ms = last_motion_ms = millis();
  wdt_enable(WDTO_250MS);
}

void loop() {
  wdt_reset();
  uint32_t now = millis();
  // Bounded work per pass so motion updates keep their rate under a flood of bytes.
  for (uint8_t n = 0; n < 48 && Serial.available() > 0; n++) {
    uint8_t r = parser.feed((uint8_t)Serial.read(), now);
    if (r == FrameParser::RESULT_FRAME) {
      if (dispatch(parser.frame)) last_valid_ms = now;
    } else if (r == FrameParser::RESULT_ERROR) {
      reply_error(parser.error_seq, parser.error_code, parser.error_cmd);
    }
  }
  if (parser.expire(now, FRAME_TIMEOUT_MS)) reply_error(parser.error_seq, parser.error_code, parser.error_cmd);

  if (!(flags & (FLAG_ESTOP | FLAG_WATCHDOG)) && (uint32_t)(now - last_valid_ms) > settings.watchdog_ms) {
    hold_position();
    flags |= FLAG_WATCHDOG;
  }
  uint32_t elapsed = now - last_motion_ms;
  if (elapsed >= MOTION_PERIOD_MS) {
    last_motion_ms = now;
    update_motion((elapsed > 50 ? 50 : elapsed) * 0.001f);
  }
}
