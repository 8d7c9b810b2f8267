/* Framing of the serial protocol: COBS with 0x00 delimiters and a CRC-32C.
 *
 * Decoded frame: type u8 · sequence u16 LE · payload (fixed size per type) · CRC-32C u32 LE
 * over everything before it. (CRC-16 let about 1 in 65,536 damaged frames through; see
 * PROTOCOL.md for the rate now.) This mirrors firmware_bridge/codec.py; tests/test_protocol_agreement.py
 * checks the two byte for byte. */
#ifndef CARRT_FW_FRAME_H
#define CARRT_FW_FRAME_H

#include <stdint.h>

#include "protocol_generated.h"

#ifdef __cplusplus
extern "C" {
#endif

#define FW_FRAME_MIN_DECODED (CARRT_HEADER_SIZE + CARRT_CRC_SIZE)
#define FW_FRAME_MAX_PAYLOAD (CARRT_MAX_FRAME_DECODED - FW_FRAME_MIN_DECODED)
/* COBS adds one code byte per started 254-byte block: 64 decoded bytes encode to 65. */
#define FW_FRAME_MAX_COBS (CARRT_MAX_FRAME_DECODED + CARRT_MAX_FRAME_DECODED / 254 + 1)
/* Encoded frame on the wire, including the trailing 0x00 delimiter. */
#define FW_FRAME_MAX_ENCODED (FW_FRAME_MAX_COBS + 1)

/* CRC-32C (Castagnoli): reflected poly 0x82F63B78, init and final xor 0xFFFFFFFF; 0xE3069283
 * for "123456789". The frames' CRC. */
uint32_t fw_crc32c(const uint8_t *data, uint16_t len);
/* Continue over more bytes on the raw register (fw_crc32c == update(0xFFFFFFFF) ^ 0xFFFFFFFF). */
uint32_t fw_crc32c_update(uint32_t crc, const uint8_t *data, uint16_t len);

/* CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, no reflection, no final xor. Only the stored
 * config blob uses it (fw_core.c), so a board's EEPROM contents stay valid. */
uint16_t fw_crc16(const uint8_t *data, uint16_t len);
/* Continue a CRC over more bytes (fw_crc16 == fw_crc16_update(0xFFFF, ...)). */
uint16_t fw_crc16_update(uint16_t crc, const uint8_t *data, uint16_t len);

/* COBS-encode len bytes; out needs len + len / 254 + 1 bytes. Returns the encoded length.
 * No delimiter is written. */
uint16_t fw_cobs_encode(const uint8_t *in, uint16_t len, uint8_t *out);

/* COBS-decode (input without its delimiter). Returns the decoded length, or -1 when the input
 * is malformed (a zero byte, a block running past the end) or the result exceeds out_max. */
int16_t fw_cobs_decode(const uint8_t *in, uint16_t len, uint8_t *out, uint16_t out_max);

/* A whole wire frame (COBS bytes + one 0x00) into out (FW_FRAME_MAX_ENCODED bytes).
 * Returns the number of bytes written, or 0 when the payload is too long. */
uint16_t fw_frame_encode(uint8_t type, uint16_t seq, const uint8_t *payload, uint16_t len,
                         uint8_t *out);

/* One accepted frame: known type, exact payload size, good CRC. */
typedef struct fw_frame {
  uint8_t type;
  uint16_t seq;
  uint8_t len;
  uint8_t payload[FW_FRAME_MAX_PAYLOAD];
} fw_frame_t;

/* Streaming receiver, fed one byte at a time. Counters saturate at 0xFFFF. */
typedef struct fw_rx {
  uint8_t buf[FW_FRAME_MAX_COBS];
  uint8_t len;
  uint8_t discarding; /* an overrun happened: skip to the next 0x00 */
  uint16_t bad_crc;
  uint16_t bad_length;
  uint16_t overruns;
} fw_rx_t;

void fw_rx_init(fw_rx_t *rx);

/* Push one byte. Returns 1 and fills *frame when the byte completed a valid frame. */
uint8_t fw_rx_push(fw_rx_t *rx, uint8_t byte, fw_frame_t *frame);

#ifdef __cplusplus
}
#endif

#endif /* CARRT_FW_FRAME_H */
