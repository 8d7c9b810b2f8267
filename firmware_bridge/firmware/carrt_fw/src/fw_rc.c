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
  ch->steady_us = 0u;
  memset(ch->recent_us, 0, sizeof(ch->recent_us));
}

/* The median of the recent widths that are within FW_RC_JITTER_US of the newest (those since
 * the last real move); with an even count, the lower middle one. */
static uint16_t recent_median(const fw_rc_channel_t *ch) {
  uint16_t sorted[FW_RC_MEDIAN];
  uint16_t newest = ch->recent_us[0];
  uint8_t n = 0u;
  uint8_t i;
  for (i = 0u; i < FW_RC_MEDIAN; i++) {
    uint16_t v = ch->recent_us[i];
    uint16_t d = (uint16_t)(v > newest ? v - newest : newest - v);
    if (v != 0u && d <= FW_RC_JITTER_US) {
      uint8_t j = n++;
      while (j > 0u && sorted[j - 1u] > v) { /* insertion sort of at most five */
        sorted[j] = sorted[j - 1u];
        j--;
      }
      sorted[j] = v;
    }
  }
  return sorted[(uint8_t)((n - 1u) / 2u)];
}

static void steady(fw_rc_channel_t *ch) {
  uint16_t w = ch->recent_us[0];
  uint16_t step = (uint16_t)(w > ch->steady_us ? w - ch->steady_us : ch->steady_us - w);
  if (ch->steady_us == 0u || step > FW_RC_JITTER_US) {
    ch->steady_us = w; /* a real move (or the first pulse): at once */
  } else {
    ch->steady_us = recent_median(ch);
  }
}

/* The pulse that settled counts: its width joins the recent ones. */
static uint8_t take(fw_rc_channel_t *ch) {
  memmove(&ch->recent_us[1], &ch->recent_us[0], sizeof(ch->recent_us) - sizeof(ch->recent_us[0]));
  ch->recent_us[0] = ch->settling_us;
  ch->settling_us = 0u;
  steady(ch);
  ch->last_good_ms = ch->fall_ms;
  if (ch->run < FW_RC_MIN_RUN) {
    ch->run++;
  }
  ch->valid = (uint8_t)(ch->run >= FW_RC_MIN_RUN);
  return 1u;
}

/* Has the line stayed low long enough since the settling pulse's end? (A time before that end,
 * which a caller should not pass, counts as not yet.) */
static uint8_t settled(const fw_rc_channel_t *ch, uint32_t ticks) {
  uint32_t quiet = ticks - ch->fall_ticks;
  return (quiet >= FW_RC_SETTLE_US * FW_RC_TICKS_PER_US && quiet < 0x80000000UL) ? 1u : 0u;
}

uint8_t fw_rc_edge(fw_rc_channel_t *ch, uint8_t level, uint32_t ticks, uint32_t now_ms) {
  uint8_t taken = 0u;
  if (level) {
    if (ch->settling_us != 0u) {
      if (settled(ch, ticks)) {
        taken = take(ch);
      } else {
        ch->settling_us = 0u; /* more edges right after its end: noise cut it short */
        reject(ch);
      }
    }
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
    return taken;
  }
  if (!ch->high) {
    return 0u; /* a falling edge without its rising one (power-up, glitch): nothing to time */
  }
  ch->high = 0u;
  uint32_t width = ticks - ch->rise_ticks;
  if (width < FW_RC_MIN_WIDTH_US * FW_RC_TICKS_PER_US ||
      width > FW_RC_MAX_WIDTH_US * FW_RC_TICKS_PER_US) {
    reject(ch);
    return 0u;
  }
  if (!ch->period_ok) {
    return 0u; /* the first pulse after a gap: its width is fine, its period unknown */
  }
  ch->settling_us = (uint16_t)(width / FW_RC_TICKS_PER_US); /* counts once the line is quiet */
  ch->fall_ticks = ticks;
  ch->fall_ms = now_ms;
  return 0u;
}

uint8_t fw_rc_settle_due(const fw_rc_channel_t *ch, uint32_t now_ticks) {
  return (ch->settling_us != 0u && settled(ch, now_ticks)) ? 1u : 0u;
}

uint8_t fw_rc_settle(fw_rc_channel_t *ch, uint32_t now_ticks) {
  return fw_rc_settle_due(ch, now_ticks) ? take(ch) : 0u;
}

void fw_rc_restart(fw_rc_channel_t *ch) { fw_rc_init(ch); }


void fw_rc_poll(fw_rc_channel_t *ch, uint32_t now_ms) {
  if (ch->run > 0u && (uint32_t)(now_ms - ch->last_good_ms) > FW_RC_LOSS_MS) {
    lose(ch);
  }
}

uint8_t fw_rc_valid(const fw_rc_channel_t *ch) { return ch->valid; }

uint16_t fw_rc_width_us(const fw_rc_channel_t *ch) { return ch->valid ? ch->recent_us[0] : 0u; }

uint16_t fw_rc_steady_us(const fw_rc_channel_t *ch) { return ch->valid ? ch->steady_us : 0u; }
