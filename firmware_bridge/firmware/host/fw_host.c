/* Host harness: the firmware core behind an in-memory HAL, exported for Python (ctypes).
 *
 * This is what the tests and the simulator's virtual microcontroller run, so it stays a thin
 * adapter: no behaviour of its own beyond what a board's hardware would do (outputs hold their
 * last pulse, the serial TX buffer is finite, the config storage survives reboots, the encoder
 * counter restarts at 0 on reset). Python owns the memory (fwh_size + fwh_create). */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "fw_core.h"
#include "fw_frame.h"
#include "fw_rc.h"
#include "protocol_generated.h"

#define FWH_TX_CAPACITY 8192u

typedef struct fwh {
  fw_core_t core;
  fw_hal_t hal;
  uint8_t booted;
  uint16_t pwm[2];
  int32_t encoder;
  uint16_t tx_dropped;
  uint32_t pwm_syncs;
  size_t tx_len;
  uint8_t tx[FWH_TX_CAPACITY];
  uint8_t storage[FW_STORAGE_SIZE];
} fwh_t;

/* ------------------------------------------------------------------ HAL */

static void hal_pwm_write(void *ctx, uint8_t channel, uint16_t pulse_us) {
  fwh_t *h = (fwh_t *)ctx;
  if (channel < 2u) {
    h->pwm[channel] = pulse_us;
  }
}

/* The harness's outputs take a new width at once, so a sync only counts (the tests check that a
 * safety change asks for one). */
static void hal_pwm_sync(void *ctx) { ((fwh_t *)ctx)->pwm_syncs++; }

static int32_t hal_encoder_read(void *ctx) { return ((fwh_t *)ctx)->encoder; }

/* A frame that does not fit is dropped whole, as a board's UART driver would rather than
 * sending half a frame. */
static void hal_serial_write(void *ctx, const uint8_t *data, uint16_t len) {
  fwh_t *h = (fwh_t *)ctx;
  if ((size_t)len > FWH_TX_CAPACITY - h->tx_len) {
    if (h->tx_dropped != 0xFFFFu) {
      h->tx_dropped++;
    }
    return;
  }
  memcpy(&h->tx[h->tx_len], data, len);
  h->tx_len += len;
}

static uint8_t hal_storage_load(void *ctx, uint8_t *data, uint16_t len) {
  fwh_t *h = (fwh_t *)ctx;
  if (len > sizeof h->storage) {
    return 0;
  }
  memcpy(data, h->storage, len);
  return 1;
}

static uint8_t hal_storage_store(void *ctx, const uint8_t *data, uint16_t len) {
  fwh_t *h = (fwh_t *)ctx;
  if (len > sizeof h->storage) {
    return 0;
  }
  memcpy(h->storage, data, len);
  return 1;
}

/* ------------------------------------------------------------------ lifecycle */

size_t fwh_size(void) { return sizeof(fwh_t); }

void fwh_create(void *mem) {
  fwh_t *h = (fwh_t *)mem;
  memset(h, 0, sizeof *h);
  h->hal.ctx = h;
  h->hal.pwm_write = hal_pwm_write;
  h->hal.encoder_read = hal_encoder_read;
  h->hal.serial_write = hal_serial_write;
  h->hal.storage_load = hal_storage_load;
  h->hal.storage_store = hal_storage_store;
  h->hal.pwm_sync = hal_pwm_sync;
}

void fwh_boot(void *mem, uint32_t boot_id, uint8_t reset_cause, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  h->encoder = 0;
  h->pwm[0] = 0;
  h->pwm[1] = 0;
  h->tx_len = 0; /* a reset loses what the UART had still to send (a previous boot's HELLO) */
  fw_core_init(&h->core, &h->hal, boot_id, reset_cause, now_ms);
  h->booted = 1;
}

void fwh_rx(void *mem, const uint8_t *data, size_t len, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  if (!h->booted) {
    return;
  }
  while (len > 0u) {
    uint16_t chunk = len > 0xFFFFu ? 0xFFFFu : (uint16_t)len;
    fw_core_rx(&h->core, data, chunk, now_ms);
    data += chunk;
    len -= chunk;
  }
}

void fwh_tick(void *mem, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  if (h->booted) {
    fw_core_tick(&h->core, now_ms);
  }
}

size_t fwh_tx_take(void *mem, uint8_t *out, size_t max) {
  fwh_t *h = (fwh_t *)mem;
  size_t n = h->tx_len < max ? h->tx_len : max;
  memcpy(out, h->tx, n);
  memmove(h->tx, &h->tx[n], h->tx_len - n);
  h->tx_len -= n;
  return n;
}

void fwh_set_encoder(void *mem, int32_t ticks) { ((fwh_t *)mem)->encoder = ticks; }

uint16_t fwh_pwm_us(void *mem, uint8_t channel) {
  fwh_t *h = (fwh_t *)mem;
  return channel < 2u ? h->pwm[channel] : 0u;
}

uint8_t fwh_state(void *mem) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_state(&h->core) : (uint8_t)CARRT_STATE_DISARMED;
}

uint8_t fwh_reason(void *mem) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_reason(&h->core) : (uint8_t)CARRT_REASON_NONE;
}

uint8_t fwh_arm_refusal(void *mem) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_arm_refusal(&h->core) : (uint8_t)CARRT_ARM_REFUSAL_NONE;
}

void fwh_counters(void *mem, uint16_t out[4]) {
  fwh_t *h = (fwh_t *)mem;
  const fw_rx_t *rx = fw_core_rx_stats(&h->core);
  out[0] = rx->bad_crc;
  out[1] = rx->bad_length;
  out[2] = rx->overruns;
  out[3] = h->tx_dropped;
}

size_t fwh_storage_size(void) { return FW_STORAGE_SIZE; }

void fwh_storage_get(void *mem, uint8_t *out) {
  memcpy(out, ((fwh_t *)mem)->storage, FW_STORAGE_SIZE);
}

void fwh_storage_set(void *mem, const uint8_t *in) {
  memcpy(((fwh_t *)mem)->storage, in, FW_STORAGE_SIZE);
}

/* ------------------------------------------------------------------ protocol checks */

uint32_t fwh_protocol_hash(void) { return (uint32_t)CARRT_PROTOCOL_HASH; }

/* The digest of the sources this library was built from (setup.py passes it), so the Python
 * side can refuse a library that is older than the C files beside it. */
#ifndef CARRT_FW_SOURCE_DIGEST
#define CARRT_FW_SOURCE_DIGEST "unknown"
#endif
const char *fwh_source_digest(void) { return CARRT_FW_SOURCE_DIGEST; }

int fwh_payload_size(uint8_t type) { return carrt_payload_size(type); }

#define FWH_ROUNDTRIP(id, name)        \
  case id: {                           \
    carrt_##name##_t msg;              \
    carrt_unpack_##name(in, &msg);     \
    carrt_pack_##name(&msg, out);      \
    break;                             \
  }

int fwh_proto_roundtrip(uint8_t type, const uint8_t *in, size_t len, uint8_t *out) {
  int size = carrt_payload_size(type);
  if (size < 0 || (size_t)size != len) {
    return -1;
  }
  switch (type) {
    FWH_ROUNDTRIP(CARRT_MSG_HELLO_REQUEST, hello_request)
    FWH_ROUNDTRIP(CARRT_MSG_HELLO, hello)
    FWH_ROUNDTRIP(CARRT_MSG_PING, ping)
    FWH_ROUNDTRIP(CARRT_MSG_PONG, pong)
    FWH_ROUNDTRIP(CARRT_MSG_COMMAND, command)
    FWH_ROUNDTRIP(CARRT_MSG_CONFIG, config)
    FWH_ROUNDTRIP(CARRT_MSG_CONFIG_REQUEST, config_request)
    FWH_ROUNDTRIP(CARRT_MSG_CONFIG_ACK, config_ack)
    FWH_ROUNDTRIP(CARRT_MSG_TELEMETRY, telemetry)
    default:
      return -1; /* a type in carrt_payload_size but not here: the harness is out of date */
  }
  return size;
}

size_t fwh_encode_frame(uint8_t type, uint16_t seq, const uint8_t *payload, size_t len,
                        uint8_t *out) {
  if (len > FW_FRAME_MAX_PAYLOAD) {
    return 0;
  }
  return fw_frame_encode(type, seq, payload, (uint16_t)len, out);
}

uint16_t fwh_crc16(const uint8_t *data, size_t len) {
  uint16_t crc = 0xFFFFu;
  while (len > 0u) {
    uint16_t chunk = len > 0xFFFFu ? 0xFFFFu : (uint16_t)len;
    crc = fw_crc16_update(crc, data, chunk);
    data += chunk;
    len -= chunk;
  }
  return crc;
}

uint32_t fwh_crc32c(const uint8_t *data, size_t len) {
  uint32_t crc = 0xFFFFFFFFUL;
  while (len > 0u) {
    uint16_t chunk = len > 0xFFFFu ? 0xFFFFu : (uint16_t)len;
    crc = fw_crc32c_update(crc, data, chunk);
    data += chunk;
    len -= chunk;
  }
  return crc ^ 0xFFFFFFFFUL;
}

/* ------------------------------------------------------------------ RC receiver decoder */

size_t fwh_rc_size(void) { return sizeof(fw_rc_channel_t); }

void fwh_rc_edge(void *mem, uint8_t channel, uint8_t level, uint32_t ticks, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  if (h->booted) {
    fw_core_rc_edge(&h->core, channel, level, ticks, now_ms);
  }
}

void fwh_rc_settle(void *mem, uint32_t now_ticks, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  if (h->booted) {
    fw_core_rc_settle(&h->core, now_ticks, now_ms);
  }
}

uint8_t fwh_rc_settle_due(void *mem, uint32_t now_ticks) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_rc_settle_due(&h->core, now_ticks) : 0u;
}

void fwh_rc_overflow(void *mem, uint8_t channel_mask, uint32_t now_ms) {
  fwh_t *h = (fwh_t *)mem;
  if (h->booted) {
    fw_core_rc_overflow(&h->core, channel_mask, now_ms);
  }
}

uint32_t fwh_rc_settle_us(void) { return FW_RC_SETTLE_US; }

uint8_t fwh_rc_drives(void *mem) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_rc_drives(&h->core) : 0u;
}

uint16_t fwh_rc_width_us(void *mem, uint8_t channel) {
  fwh_t *h = (fwh_t *)mem;
  return h->booted ? fw_core_rc_width_us(&h->core, channel) : 0u;
}

uint32_t fwh_pwm_syncs(void *mem) { return ((fwh_t *)mem)->pwm_syncs; }
