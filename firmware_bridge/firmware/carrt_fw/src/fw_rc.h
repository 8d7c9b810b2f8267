/* The RC receiver's pulses, decoded.
 *
 * A hobby receiver repeats each channel as a 1000-2000 us pulse every 10-25 ms. The Arduino
 * shim only timestamps the pin's edges against Timer1's 0.5 us counter (extended to 32 bits);
 * everything else is decided here, in the portable core, so the host tests run the very code
 * the board runs: a pulse counts when its width and the period since the previous rising edge
 * are both in range and its line then stays low for FW_RC_SETTLE_US (noise that cuts a pulse
 * short is a falling edge with more edges right behind it: a bad pulse, not a shorter width); a
 * channel becomes valid after FW_RC_MIN_RUN such pulses in a row (a bad one before that starts
 * the count again). A valid channel drops a bad pulse and keeps its last good
 * width, as a receiver's own failsafe holds its last frame: one glitch on the wire must not stop
 * a car. It stops being valid when no good pulse came for FW_RC_LOSS_MS (polled every tick; the
 * protocol's timing table, CARRT_T_RC_LOSS_MS). Edges the shim could not stamp (its queue was
 * full) restart the channel (fw_rc_restart): it is not valid until a new run of good pulses, as
 * at power-up, since a width timed across a lost edge would be wrong. Times use unsigned
 * subtraction: the 32-bit counters may wrap.
 *
 * Two widths come out. The rules (deadzone, switch) use the last good pulse as measured, so a
 * stick is seen at its very pulse. The outputs use a steadied width: an edge's timestamp is late
 * by however long another interrupt (the millisecond timer, the UART) held the pin-change
 * interrupt off (the UART's, the millisecond timer's), a few microseconds now and then; so a
 * width within FW_RC_JITTER_US of the one already passed through is replaced by the median of
 * the last FW_RC_MEDIAN pulses (two late edges in five never reach the servo), while a larger
 * step is passed through at once. */
#ifndef CARRT_FW_RC_H
#define CARRT_FW_RC_H

#include <stdint.h>

#include "protocol_generated.h"

#ifdef __cplusplus
extern "C" {
#endif

#define FW_RC_TICKS_PER_US 2u      /* Timer1 at 2 MHz: 0.5 us per tick */
#define FW_RC_MIN_WIDTH_US 800u    /* narrower: noise, not a servo pulse */
#define FW_RC_MAX_WIDTH_US 2200u
#define FW_RC_MIN_PERIOD_US 8000u  /* rising edge to rising edge */
#define FW_RC_MAX_PERIOD_US 30000u
#define FW_RC_MIN_RUN 5u           /* good pulses in a row before the channel counts */
#define FW_RC_JITTER_US 12u        /* two interrupts back to back, at most, delay an edge */
#define FW_RC_MEDIAN 5u
#define FW_RC_SETTLE_US 500u       /* quiet after a falling edge before its pulse counts */
#define FW_RC_LOSS_MS CARRT_T_RC_LOSS_MS /* no good pulse this long: the signal is lost */

typedef struct fw_rc_channel {
  uint32_t rise_ticks;      /* the last rising edge */
  uint32_t fall_ticks;      /* the falling edge of the pulse waiting to settle */
  uint32_t fall_ms;
  uint32_t last_good_ms;    /* when the last good pulse ended */
  uint16_t recent_us[FW_RC_MEDIAN]; /* the last good widths, newest first (0: none yet) */
  uint16_t steady_us;       /* the width for the outputs (see above) */
  uint16_t settling_us;     /* a good pulse waiting for FW_RC_SETTLE_US of quiet (0: none) */
  uint8_t high;             /* a rising edge came and its falling edge has not */
  uint8_t have_rise;        /* a previous rising edge exists (for the period) */
  uint8_t period_ok;        /* the period to the pulse now high was in range */
  uint8_t run;              /* good pulses in a row (saturates at FW_RC_MIN_RUN) */
  uint8_t valid;
} fw_rc_channel_t;

void fw_rc_init(fw_rc_channel_t *ch);
/* An edge of the channel's pin: level 1 rising, 0 falling; ticks from Timer1 (0.5 us), now_ms
 * the board's millisecond clock at the edge. Returns 1 when a pulse counted (the width or the
 * validity may have changed): a rising edge FW_RC_SETTLE_US or more after a good pulse's end. */
uint8_t fw_rc_edge(fw_rc_channel_t *ch, uint8_t level, uint32_t ticks, uint32_t now_ms);
/* The time now (ticks as for edges, every edge before it already handed over): a good pulse
 * whose line has stayed low FW_RC_SETTLE_US since counts. Returns 1 when one did. */
uint8_t fw_rc_settle(fw_rc_channel_t *ch, uint32_t now_ticks);
/* Edges of this channel were lost: no valid signal, and a new run of good pulses to count. */
void fw_rc_restart(fw_rc_channel_t *ch);
/* Would fw_rc_settle count a pulse at now_ticks? */
uint8_t fw_rc_settle_due(const fw_rc_channel_t *ch, uint32_t now_ticks);
/* Every tick: the signal-loss rule. */
void fw_rc_poll(fw_rc_channel_t *ch, uint32_t now_ms);
uint8_t fw_rc_valid(const fw_rc_channel_t *ch);
uint16_t fw_rc_width_us(const fw_rc_channel_t *ch);  /* 0 while not valid */
uint16_t fw_rc_steady_us(const fw_rc_channel_t *ch); /* 0 while not valid */

#ifdef __cplusplus
}
#endif

#endif
