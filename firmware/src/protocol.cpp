#include "protocol.h"

uint16_t crc16_ccitt(uint16_t crc, uint8_t byte) {
  crc ^= (uint16_t)byte << 8;
  for (uint8_t i = 0; i < 8; i++) crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
  return crc;
}

FrameParser::Result FrameParser::feed(uint8_t byte, uint32_t now_ms) {
  switch (state_) {
    case WAIT_SOF0:
      if (byte == SOF0) {
        state_ = WAIT_SOF1;
        started_ms_ = now_ms;
      }
      return RESULT_NONE;
    case WAIT_SOF1:
      // A repeated SOF0 keeps us waiting for SOF1; anything else resynchronises silently.
      state_ = byte == SOF1 ? READ_LEN : (byte == SOF0 ? WAIT_SOF1 : WAIT_SOF0);
      return RESULT_NONE;
    case READ_LEN:
      if (byte > MAX_PAYLOAD) {
        state_ = WAIT_SOF0;
        error_code = ERR_LENGTH;
        error_seq = 0;
        error_cmd = 0;
        return RESULT_ERROR;
      }
      frame.len = byte;
      crc_ = crc16_ccitt(0xFFFF, byte);
      state_ = READ_SEQ;
      return RESULT_NONE;
    case READ_SEQ:
      frame.seq = byte;
      crc_ = crc16_ccitt(crc_, byte);
      state_ = READ_CMD;
      return RESULT_NONE;
    case READ_CMD:
      frame.cmd = byte;
      crc_ = crc16_ccitt(crc_, byte);
      index_ = 0;
      state_ = frame.len ? READ_PAYLOAD : READ_CRC0;
      return RESULT_NONE;
    case READ_PAYLOAD:
      frame.payload[index_++] = byte;
      crc_ = crc16_ccitt(crc_, byte);
      if (index_ >= frame.len) state_ = READ_CRC0;
      return RESULT_NONE;
    case READ_CRC0:
      crc_lo_ = byte;
      state_ = READ_CRC1;
      return RESULT_NONE;
    case READ_CRC1:
      state_ = WAIT_SOF0;
      if ((uint16_t)(crc_lo_ | ((uint16_t)byte << 8)) != crc_) {
        error_code = ERR_CRC;
        error_seq = frame.seq;
        error_cmd = frame.cmd;
        return RESULT_ERROR;
      }
      return RESULT_FRAME;
  }
  state_ = WAIT_SOF0;
  return RESULT_NONE;
}

bool FrameParser::expire(uint32_t now_ms, uint32_t timeout_ms) {
  if (state_ == WAIT_SOF0 || (uint32_t)(now_ms - started_ms_) < timeout_ms) return false;
  error_code = ERR_TIMEOUT;
  error_seq = state_ > READ_SEQ ? frame.seq : 0;
  error_cmd = state_ > READ_CMD ? frame.cmd : 0;
  state_ = WAIT_SOF0;
  return true;
}

void write_frame(void (*put)(uint8_t), uint8_t seq, uint8_t cmd, const uint8_t* payload, uint8_t len) {
  uint16_t crc = 0xFFFF;
  put(SOF0);
  put(SOF1);
  put(len);
  crc = crc16_ccitt(crc, len);
  put(seq);
  crc = crc16_ccitt(crc, seq);
  put(cmd);
  crc = crc16_ccitt(crc, cmd);
  for (uint8_t i = 0; i < len; i++) {
    put(payload[i]);
    crc = crc16_ccitt(crc, payload[i]);
  }
  put((uint8_t)(crc & 0xFF));
  put((uint8_t)(crc >> 8));
}
