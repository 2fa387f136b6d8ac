// Wire protocol shared with the host (pivla.robot.protocol mirrors every constant; docs/robot.md).
//
// Frame: 0xA5 0x5A LEN SEQ CMD PAYLOAD[LEN] CRC16_LO CRC16_HI
// CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF) over LEN SEQ CMD PAYLOAD. Little-endian integers.
// A reply echoes SEQ and carries CMD | 0x80, or CMD_ERROR with payload {code, offending cmd}.
#pragma once
#include <stdint.h>

#define SOF0 0xA5
#define SOF1 0x5A
#define MAX_PAYLOAD 40
#define FRAME_OVERHEAD 7

enum Command : uint8_t {
  CMD_PING = 0x01,
  CMD_SET_TARGETS = 0x02,
  CMD_GET_STATE = 0x03,
  CMD_HOME = 0x04,
  CMD_ESTOP = 0x05,
  CMD_CLEAR_ESTOP = 0x06,
  CMD_SET_CONFIG = 0x07,
  CMD_GET_CONFIG = 0x08,
  CMD_SET_LIMITS = 0x09,
  CMD_GET_LIMITS = 0x0A,
  CMD_ERROR = 0x7F,
  REPLY_FLAG = 0x80,
};

enum ErrorCode : uint8_t {
  ERR_CRC = 1,
  ERR_LENGTH = 2,
  ERR_UNKNOWN_CMD = 3,
  ERR_PAYLOAD = 4,
  ERR_LIMIT = 5,
  ERR_ESTOP = 6,
  ERR_TIMEOUT = 7,
  ERR_STATE = 8,
};

// State flags reported in every state reply.
enum StateFlag : uint8_t {
  FLAG_ESTOP = 0x01,
  FLAG_WATCHDOG = 0x02,
  FLAG_MOVING = 0x04,
  FLAG_EEPROM_DEFAULTS = 0x08,
};

uint16_t crc16_ccitt(uint16_t crc, uint8_t byte);

struct Frame {
  uint8_t len;
  uint8_t seq;
  uint8_t cmd;
  uint8_t payload[MAX_PAYLOAD];
};

// Incremental frame parser: feed() bytes; it returns RESULT_FRAME when `frame` holds a verified frame,
// RESULT_ERROR with error_code/error_seq set for a corrupt one, RESULT_NONE otherwise.
class FrameParser {
 public:
  enum Result : uint8_t { RESULT_NONE, RESULT_FRAME, RESULT_ERROR };
  FrameParser() : state_(WAIT_SOF0) {}
  Result feed(uint8_t byte, uint32_t now_ms);
  // Drops a frame left incomplete for longer than timeout_ms; returns true if one was dropped.
  bool expire(uint32_t now_ms, uint32_t timeout_ms);
  Frame frame;
  uint8_t error_code;
  uint8_t error_seq;
  uint8_t error_cmd;

 private:
  enum State : uint8_t { WAIT_SOF0, WAIT_SOF1, READ_LEN, READ_SEQ, READ_CMD, READ_PAYLOAD, READ_CRC0, READ_CRC1 };
  State state_;
  uint8_t index_;
  uint16_t crc_;
  uint8_t crc_lo_;
  uint32_t started_ms_;
};

// Writes one frame through `put` (one byte at a time).
void write_frame(void (*put)(uint8_t), uint8_t seq, uint8_t cmd, const uint8_t* payload, uint8_t len);
