/* Framing of the serial protocol; see fw_frame.h. Byte-at-a-time so the receiver needs no
 * more RAM than one encoded frame, and every rejection is counted, never silent. */
#include "fw_frame.h"

/* The CRC-32C table lives in flash on an AVR (1 KB of its 32 KB, read with pgm_read_dword),
 * so it costs no RAM; elsewhere it is a plain const array. */
#ifdef __AVR__
#include <avr/pgmspace.h>
#define FW_CRC_TABLE_ATTR PROGMEM
#define FW_CRC_TABLE_READ(i) pgm_read_dword(&crc32c_table[(i)])
#else
#define FW_CRC_TABLE_ATTR
#define FW_CRC_TABLE_READ(i) crc32c_table[(i)]
#endif

static void sat_inc(uint16_t *counter) {
  if (*counter != 0xFFFFu) {
    *counter = (uint16_t)(*counter + 1u);
  }
}

/* crc32c_table[n]: the reflected polynomial 0x82F63B78 applied to n over 8 bit steps (the same
 * loop as codec.py's _crc32c_table; test_protocol_agreement.py checks the two agree). */
static const uint32_t crc32c_table[256] FW_CRC_TABLE_ATTR = {
    0x00000000UL, 0xF26B8303UL, 0xE13B70F7UL, 0x1350F3F4UL,
    0xC79A971FUL, 0x35F1141CUL, 0x26A1E7E8UL, 0xD4CA64EBUL,
    0x8AD958CFUL, 0x78B2DBCCUL, 0x6BE22838UL, 0x9989AB3BUL,
    0x4D43CFD0UL, 0xBF284CD3UL, 0xAC78BF27UL, 0x5E133C24UL,
    0x105EC76FUL, 0xE235446CUL, 0xF165B798UL, 0x030E349BUL,
    0xD7C45070UL, 0x25AFD373UL, 0x36FF2087UL, 0xC494A384UL,
    0x9A879FA0UL, 0x68EC1CA3UL, 0x7BBCEF57UL, 0x89D76C54UL,
    0x5D1D08BFUL, 0xAF768BBCUL, 0xBC267848UL, 0x4E4DFB4BUL,
    0x20BD8EDEUL, 0xD2D60DDDUL, 0xC186FE29UL, 0x33ED7D2AUL,
    0xE72719C1UL, 0x154C9AC2UL, 0x061C6936UL, 0xF477EA35UL,
    0xAA64D611UL, 0x580F5512UL, 0x4B5FA6E6UL, 0xB93425E5UL,
    0x6DFE410EUL, 0x9F95C20DUL, 0x8CC531F9UL, 0x7EAEB2FAUL,
    0x30E349B1UL, 0xC288CAB2UL, 0xD1D83946UL, 0x23B3BA45UL,
    0xF779DEAEUL, 0x05125DADUL, 0x1642AE59UL, 0xE4292D5AUL,
    0xBA3A117EUL, 0x4851927DUL, 0x5B016189UL, 0xA96AE28AUL,
    0x7DA08661UL, 0x8FCB0562UL, 0x9C9BF696UL, 0x6EF07595UL,
    0x417B1DBCUL, 0xB3109EBFUL, 0xA0406D4BUL, 0x522BEE48UL,
    0x86E18AA3UL, 0x748A09A0UL, 0x67DAFA54UL, 0x95B17957UL,
    0xCBA24573UL, 0x39C9C670UL, 0x2A993584UL, 0xD8F2B687UL,
    0x0C38D26CUL, 0xFE53516FUL, 0xED03A29BUL, 0x1F682198UL,
    0x5125DAD3UL, 0xA34E59D0UL, 0xB01EAA24UL, 0x42752927UL,
    0x96BF4DCCUL, 0x64D4CECFUL, 0x77843D3BUL, 0x85EFBE38UL,
    0xDBFC821CUL, 0x2997011FUL, 0x3AC7F2EBUL, 0xC8AC71E8UL,
    0x1C661503UL, 0xEE0D9600UL, 0xFD5D65F4UL, 0x0F36E6F7UL,
    0x61C69362UL, 0x93AD1061UL, 0x80FDE395UL, 0x72966096UL,
    0xA65C047DUL, 0x5437877EUL, 0x4767748AUL, 0xB50CF789UL,
    0xEB1FCBADUL, 0x197448AEUL, 0x0A24BB5AUL, 0xF84F3859UL,
    0x2C855CB2UL, 0xDEEEDFB1UL, 0xCDBE2C45UL, 0x3FD5AF46UL,
    0x7198540DUL, 0x83F3D70EUL, 0x90A324FAUL, 0x62C8A7F9UL,
    0xB602C312UL, 0x44694011UL, 0x5739B3E5UL, 0xA55230E6UL,
    0xFB410CC2UL, 0x092A8FC1UL, 0x1A7A7C35UL, 0xE811FF36UL,
    0x3CDB9BDDUL, 0xCEB018DEUL, 0xDDE0EB2AUL, 0x2F8B6829UL,
    0x82F63B78UL, 0x709DB87BUL, 0x63CD4B8FUL, 0x91A6C88CUL,
    0x456CAC67UL, 0xB7072F64UL, 0xA457DC90UL, 0x563C5F93UL,
    0x082F63B7UL, 0xFA44E0B4UL, 0xE9141340UL, 0x1B7F9043UL,
    0xCFB5F4A8UL, 0x3DDE77ABUL, 0x2E8E845FUL, 0xDCE5075CUL,
    0x92A8FC17UL, 0x60C37F14UL, 0x73938CE0UL, 0x81F80FE3UL,
    0x55326B08UL, 0xA759E80BUL, 0xB4091BFFUL, 0x466298FCUL,
    0x1871A4D8UL, 0xEA1A27DBUL, 0xF94AD42FUL, 0x0B21572CUL,
    0xDFEB33C7UL, 0x2D80B0C4UL, 0x3ED04330UL, 0xCCBBC033UL,
    0xA24BB5A6UL, 0x502036A5UL, 0x4370C551UL, 0xB11B4652UL,
    0x65D122B9UL, 0x97BAA1BAUL, 0x84EA524EUL, 0x7681D14DUL,
    0x2892ED69UL, 0xDAF96E6AUL, 0xC9A99D9EUL, 0x3BC21E9DUL,
    0xEF087A76UL, 0x1D63F975UL, 0x0E330A81UL, 0xFC588982UL,
    0xB21572C9UL, 0x407EF1CAUL, 0x532E023EUL, 0xA145813DUL,
    0x758FE5D6UL, 0x87E466D5UL, 0x94B49521UL, 0x66DF1622UL,
    0x38CC2A06UL, 0xCAA7A905UL, 0xD9F75AF1UL, 0x2B9CD9F2UL,
    0xFF56BD19UL, 0x0D3D3E1AUL, 0x1E6DCDEEUL, 0xEC064EEDUL,
    0xC38D26C4UL, 0x31E6A5C7UL, 0x22B65633UL, 0xD0DDD530UL,
    0x0417B1DBUL, 0xF67C32D8UL, 0xE52CC12CUL, 0x1747422FUL,
    0x49547E0BUL, 0xBB3FFD08UL, 0xA86F0EFCUL, 0x5A048DFFUL,
    0x8ECEE914UL, 0x7CA56A17UL, 0x6FF599E3UL, 0x9D9E1AE0UL,
    0xD3D3E1ABUL, 0x21B862A8UL, 0x32E8915CUL, 0xC083125FUL,
    0x144976B4UL, 0xE622F5B7UL, 0xF5720643UL, 0x07198540UL,
    0x590AB964UL, 0xAB613A67UL, 0xB831C993UL, 0x4A5A4A90UL,
    0x9E902E7BUL, 0x6CFBAD78UL, 0x7FAB5E8CUL, 0x8DC0DD8FUL,
    0xE330A81AUL, 0x115B2B19UL, 0x020BD8EDUL, 0xF0605BEEUL,
    0x24AA3F05UL, 0xD6C1BC06UL, 0xC5914FF2UL, 0x37FACCF1UL,
    0x69E9F0D5UL, 0x9B8273D6UL, 0x88D28022UL, 0x7AB90321UL,
    0xAE7367CAUL, 0x5C18E4C9UL, 0x4F48173DUL, 0xBD23943EUL,
    0xF36E6F75UL, 0x0105EC76UL, 0x12551F82UL, 0xE03E9C81UL,
    0x34F4F86AUL, 0xC69F7B69UL, 0xD5CF889DUL, 0x27A40B9EUL,
    0x79B737BAUL, 0x8BDCB4B9UL, 0x988C474DUL, 0x6AE7C44EUL,
    0xBE2DA0A5UL, 0x4C4623A6UL, 0x5F16D052UL, 0xAD7D5351UL,
};

uint32_t fw_crc32c(const uint8_t *data, uint16_t len) {
  return fw_crc32c_update(0xFFFFFFFFUL, data, len) ^ 0xFFFFFFFFUL;
}

uint32_t fw_crc32c_update(uint32_t crc, const uint8_t *data, uint16_t len) {
  uint16_t i;
  for (i = 0; i < len; i++) {
    crc = FW_CRC_TABLE_READ((uint8_t)((uint8_t)crc ^ data[i])) ^ (crc >> 8);
  }
  return crc;
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
  uint32_t crc;
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
  crc = fw_crc32c(body, n);
  for (i = 0; i < CARRT_CRC_SIZE; i++) {
    body[n + i] = (uint8_t)(crc >> (8u * i));
  }
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
  uint32_t crc = 0;
  int expected;
  uint16_t i;
  if (decoded < (int16_t)FW_FRAME_MIN_DECODED) {
    sat_inc(&rx->bad_length);
    return 0;
  }
  len = (uint16_t)decoded;
  for (i = 0; i < CARRT_CRC_SIZE; i++) {
    crc |= (uint32_t)body[len - CARRT_CRC_SIZE + i] << (8u * i);
  }
  if (fw_crc32c(body, (uint16_t)(len - CARRT_CRC_SIZE)) != crc) {
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
