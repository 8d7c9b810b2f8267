/* The RC receiver's pulses, decoded.
 *
 * A hobby receiver repeats each channel as a 1000-2000 us pulse every 10-25 ms. The Arduino
 * shim only timestamps the pin's edges against Timer1's 0.5 us counter (extended to 32 bits);
 * everything else is decided here, in the portable core, so the host tests run the very code
 * the board runs: a pulse counts when its width and the period since the previous rising edge
 * are both in range; a channel becomes valid after FW_RC_MIN_RUN such pulses in a row (a bad one
 * before that starts the count again). A valid channel drops a bad pulse and keeps its last good
 * width, as a receiver's own failsafe holds its last frame: one glitch on the wire must not stop
 * a car. It stops being valid when no good pulse came for FW_RC_LOSS_MS (polled every tick; the
 * protocol's timing table, CARRT_T_RC_LOSS_MS). Times use unsigned subtraction: the 32-bit
 * counters may wrap.
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
#define FW_RC_LOSS_MS CARRT_T_RC_LOSS_MS /* no good pulse this long: the signal is lost */

typedef struct fw_rc_channel {
  uint32_t rise_ticks;      /* the last rising edge */
  uint32_t last_good_ms;    /* when the last good pulse ended */
  uint16_t recent_us[FW_RC_MEDIAN]; /* the last good widths, newest first (0: none yet) */
  uint16_t steady_us;       /* the width for the outputs (see above) */
  uint8_t high;             /* a rising edge came and its falling edge has not */
  uint8_t have_rise;        /* a previous rising edge exists (for the period) */
  uint8_t period_ok;        /* the period to the pulse now high was in range */
  uint8_t run;              /* good pulses in a row (saturates at FW_RC_MIN_RUN) */
  uint8_t valid;
} fw_rc_channel_t;

void fw_rc_init(fw_rc_channel_t *ch);
/* An edge of the channel's pin: level 1 rising, 0 falling; ticks from Timer1 (0.5 us), now_ms
 * the board's millisecond clock at the edge. */
void fw_rc_edge(fw_rc_channel_t *ch, uint8_t level, uint32_t ticks, uint32_t now_ms);
/* Every tick: the signal-loss rule. */
void fw_rc_poll(fw_rc_channel_t *ch, uint32_t now_ms);
uint8_t fw_rc_valid(const fw_rc_channel_t *ch);
uint16_t fw_rc_width_us(const fw_rc_channel_t *ch);  /* 0 while not valid */
uint16_t fw_rc_steady_us(const fw_rc_channel_t *ch); /* 0 while not valid */

#ifdef __cplusplus
}
#endif

#endif
