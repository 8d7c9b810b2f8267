/* The RC receiver's pulse decoder: see fw_rc.h for the rules and why they live here. */
#include "fw_rc.h"

#include <string.h>

void fw_rc_init(fw_rc_channel_t *ch) { memset(ch, 0, sizeof(*ch)); }

/* A bad pulse: before the channel counts, the run starts over; once it counts, the pulse is
 * dropped and the last good width stays (only FW_RC_LOSS_MS without a good one ends it). */
static void reject(fw_rc_channel_t *ch) {
  if (!ch->valid) {
    ch->run = 0u;
  }
}

static void lose(fw_rc_channel_t *ch) {
  ch->run = 0u;
  ch->valid = 0u;
}

void fw_rc_edge(fw_rc_channel_t *ch, uint8_t level, uint32_t ticks, uint32_t now_ms) {
  if (level) {
    uint32_t period = ticks - ch->rise_ticks;
    ch->period_ok = (uint8_t)(ch->have_rise &&
                              period >= FW_RC_MIN_PERIOD_US * FW_RC_TICKS_PER_US &&
                              period <= FW_RC_MAX_PERIOD_US * FW_RC_TICKS_PER_US);
    if (ch->have_rise && !ch->period_ok) {
      reject(ch); /* pulses too close or too far apart: not a receiver's frame */
    }
    ch->rise_ticks = ticks;
    ch->have_rise = 1u;
    ch->high = 1u;
    return;
  }
  if (!ch->high) {
    return; /* a falling edge without its rising one (power-up, glitch): nothing to time */
  }
  ch->high = 0u;
  uint32_t width = ticks - ch->rise_ticks;
  if (width < FW_RC_MIN_WIDTH_US * FW_RC_TICKS_PER_US ||
      width > FW_RC_MAX_WIDTH_US * FW_RC_TICKS_PER_US) {
    reject(ch);
    return;
  }
  if (!ch->period_ok) {
    return; /* the first pulse after a gap: its width is fine, its period unknown */
  }
  ch->width_us = (uint16_t)(width / FW_RC_TICKS_PER_US);
  ch->last_good_ms = now_ms;
  if (ch->run < FW_RC_MIN_RUN) {
    ch->run++;
  }
  ch->valid = (uint8_t)(ch->run >= FW_RC_MIN_RUN);
}

void fw_rc_poll(fw_rc_channel_t *ch, uint32_t now_ms) {
  if (ch->run > 0u && (uint32_t)(now_ms - ch->last_good_ms) > FW_RC_LOSS_MS) {
    lose(ch);
  }
}

uint8_t fw_rc_valid(const fw_rc_channel_t *ch) { return ch->valid; }

uint16_t fw_rc_width_us(const fw_rc_channel_t *ch) { return ch->valid ? ch->width_us : 0u; }
