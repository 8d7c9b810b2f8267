/* Framing of the serial protocol; see fw_frame.h. Byte-at-a-time so the receiver needs no
 * more RAM than one encoded frame, and every rejection is counted, never silent. */
#include "fw_frame.h"

static void sat_inc(uint16_t *counter) {
  if (*counter != 0xFFFFu) {
    *counter = (uint16_t)(*counter + 1u);
  }
}

uint16_t fw_crc16(const uint8_t *data, uint16_t len) {
  return fw_crc16_update(0xFFFFu, data, len);
}

uint16_t fw_crc16_update(uint16_t crc, const uint8_t *data, uint16_t len) {
  uint16_t i;
  for (i = 0; i < len; i++) {
    uint8_t bit;
    crc = (uint16_t)(crc ^ (uint16_t)((uint16_t)data[i] << 8));
    for (bit = 0; bit < 8u; bit++) {
      if (crc & 0x8000u) {
        crc = (uint16_t)((uint16_t)(crc << 1) ^ 0x1021u);
      } else {
        crc = (uint16_t)(crc << 1);
      }
    }
  }
  return crc;
}

uint16_t fw_cobs_encode(const uint8_t *in, uint16_t len, uint8_t *out) {
  uint16_t code_at = 0; /* where the current block's code byte goes */
  uint16_t o = 1;
  uint8_t code = 1;
  uint16_t i;
  for (i = 0; i < len; i++) {
    if (in[i] == 0u) {
      out[code_at] = code;
      code_at = o++;
      code = 1;
    } else {
      out[o++] = in[i];
      code++;
      if (code == 0xFFu && i + 1u < len) {
        out[code_at] = code;
        code_at = o++;
        code = 1;
      }
    }
  }
  out[code_at] = code;
  return o;
}

int16_t fw_cobs_decode(const uint8_t *in, uint16_t len, uint8_t *out, uint16_t out_max) {
  uint16_t i = 0;
  uint16_t o = 0;
  while (i < len) {
    uint8_t code = in[i++];
    uint8_t k;
    if (code == 0u) {
      return -1;
    }
    for (k = 1; k < code; k++) {
      if (i >= len || in[i] == 0u || o >= out_max) {
        return -1;
      }
      out[o++] = in[i++];
    }
    if (code != 0xFFu && i < len) {
      if (o >= out_max) {
        return -1;
      }
      out[o++] = 0;
    }
  }
  return (int16_t)o;
}

uint16_t fw_frame_encode(uint8_t type, uint16_t seq, const uint8_t *payload, uint16_t len,
                         uint8_t *out) {
  uint8_t body[CARRT_MAX_FRAME_DECODED];
  uint16_t n;
  uint16_t crc;
  uint16_t i;
  if (len > FW_FRAME_MAX_PAYLOAD) {
    return 0;
  }
  body[0] = type;
  body[1] = (uint8_t)(seq & 0xFFu);
  body[2] = (uint8_t)(seq >> 8);
  for (i = 0; i < len; i++) {
    body[CARRT_HEADER_SIZE + i] = payload[i];
  }
  n = (uint16_t)(CARRT_HEADER_SIZE + len);
  crc = fw_crc16(body, n);
  body[n] = (uint8_t)(crc & 0xFFu);
  body[n + 1u] = (uint8_t)(crc >> 8);
  n = (uint16_t)(n + CARRT_CRC_SIZE);
  n = fw_cobs_encode(body, n, out);
  out[n] = 0;
  return (uint16_t)(n + 1u);
}

void fw_rx_init(fw_rx_t *rx) {
  uint16_t i;
  for (i = 0; i < sizeof rx->buf; i++) {
    rx->buf[i] = 0;
  }
  rx->len = 0;
  rx->discarding = 0;
  rx->bad_crc = 0;
  rx->bad_length = 0;
  rx->overruns = 0;
}

/* Validate one complete encoded frame, in the order the protocol specifies. */
static uint8_t rx_finish(fw_rx_t *rx, uint8_t n, fw_frame_t *frame) {
  uint8_t body[CARRT_MAX_FRAME_DECODED];
  int16_t decoded = fw_cobs_decode(rx->buf, n, body, (uint16_t)sizeof body);
  uint16_t len;
  uint16_t payload_len;
  uint16_t crc;
  int expected;
  uint16_t i;
  if (decoded < (int16_t)FW_FRAME_MIN_DECODED) {
    sat_inc(&rx->bad_length);
    return 0;
  }
  len = (uint16_t)decoded;
  crc = (uint16_t)(body[len - 2u] | (uint16_t)((uint16_t)body[len - 1u] << 8));
  if (fw_crc16(body, (uint16_t)(len - CARRT_CRC_SIZE)) != crc) {
    sat_inc(&rx->bad_crc);
    return 0;
  }
  payload_len = (uint16_t)(len - FW_FRAME_MIN_DECODED);
  expected = carrt_payload_size(body[0]);
  if (expected < 0 || (uint16_t)expected != payload_len) {
    sat_inc(&rx->bad_length);
    return 0;
  }
  frame->type = body[0];
  frame->seq = (uint16_t)(body[1] | (uint16_t)((uint16_t)body[2] << 8));
  frame->len = (uint8_t)payload_len;
  for (i = 0; i < payload_len; i++) {
    frame->payload[i] = body[CARRT_HEADER_SIZE + i];
  }
  return 1;
}

uint8_t fw_rx_push(fw_rx_t *rx, uint8_t byte, fw_frame_t *frame) {
  if (byte == 0u) {
    uint8_t n = rx->len;
    uint8_t skipped = rx->discarding;
    rx->len = 0;
    rx->discarding = 0;
    if (skipped || n == 0u) {
      return 0; /* end of a discarded frame, or an empty frame: ignored silently */
    }
    return rx_finish(rx, n, frame);
  }
  if (rx->discarding) {
    return 0;
  }
  if (rx->len >= sizeof rx->buf) {
    sat_inc(&rx->overruns);
    rx->len = 0;
    rx->discarding = 1;
    return 0;
  }
  rx->buf[rx->len++] = byte;
  return 0;
}
