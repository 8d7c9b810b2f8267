/* The microcontroller's safety core: the last word on what reaches the servo and the ESC.
 *
 * Portable C99, no dynamic allocation, no globals, no hidden clock: all state lives in a
 * caller-provided fw_core_t, hardware goes through fw_hal_t, and the current time (uint32 ms,
 * wrapping) is an argument of every call. The Arduino sketch calls fw_core_rx() with the bytes
 * it read and fw_core_tick() every loop(); the host harness does the same from Python tests.
 *
 * States: DISARMED (boot) -> ARMED on a 0->1 edge of the ARM flag with neutral throttle and
 * stopped wheels; ARMED -> FAILSAFE on link timeout (200 ms), stale decision (300 ms) or stall
 * (500 ms); any state -> ESTOP (latched) on the e-stop flag; ESTOP/FAILSAFE -> DISARMED only on
 * an explicit CLEAR (with ESTOP and ARM clear). Outputs are neutral in every state but ARMED.
 *
 * The RC receiver (config.controls RECEIVER or BOTH): the shim hands every edge of its three
 * pins to fw_core_rc_edge(), the time to fw_core_rc_settle() and any edges it lost to
 * fw_core_rc_overflow(); the decoder (fw_rc.h) validates each channel, and the rules here
 * decide: the switch channel in its e-stop position latches ESTOP; ARMED with the receiver's
 * signal lost is FAILSAFE; in ARMED, a stick out of its deadzone (or, with RECEIVER, any COMMAND
 * without the AUTO flag) hands the wheels to the receiver until the AUTO flag's next 0->1 edge.
 * While the receiver drives, its pulses go straight to the outputs (clamped like commands), the
 * host's watchdog and freshness rules give way to the receiver's loss rule, and TELEMETRY says so. */
#ifndef CARRT_FW_CORE_H
#define CARRT_FW_CORE_H

#include <stdint.h>

#include "fw_frame.h"
#include "fw_hal.h"
#include "fw_rc.h"
#include "protocol_generated.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Timing comes from firmware_bridge/timing.py through protocol_generated.h (and is part of the
 * protocol hash): one table for the host and the board. */
#define FW_LINK_TIMEOUT_MS CARRT_T_LINK_TIMEOUT_MS
#define FW_DECISION_STALE_MS CARRT_T_DECISION_STALE_MS
#define FW_STALL_MS CARRT_T_STALL_MS
#define FW_WHEELS_STOPPED_MS CARRT_T_WHEELS_STOPPED_MS
#define FW_TELEMETRY_PERIOD_MS CARRT_T_TELEMETRY_PERIOD_MS
#define FW_ARM_THROTTLE_MAX 200     /* |throttle| <= 2 % counts as neutral for arming */
#define FW_STALL_THROTTLE 1500      /* applied throttle above 15 % forward can stall */

#define FW_RC_STEERING 0u /* receiver channels, in the order of fw_core_rc_edge() */
#define FW_RC_THROTTLE 1u
#define FW_RC_SWITCH 2u
#define FW_RC_CHANNELS 3u

/* Persistent config blob: magic u16, version u8, config payload, CRC u16 (all LE). */
#define FW_STORAGE_MAGIC 0xCA27u
#define FW_STORAGE_VERSION 2u /* 2: the receiver's fields */
#define FW_STORAGE_SIZE (2u + 1u + CARRT_MSG_CONFIG_SIZE + 2u)

typedef struct fw_core {
  fw_hal_t hal;
  fw_rx_t rx;
  carrt_config_t config; /* config.persist: 1 when it came from / was written to storage */
  uint32_t boot_id;
  uint8_t reset_cause;   /* CARRT_RESET_CAUSE_*: why the board last started, for HELLO */
  uint8_t state;
  uint8_t reason;
  uint8_t arm_refusal;
  uint8_t prev_arm;      /* ARM bit of the previous accepted COMMAND (1 after boot) */
  uint8_t have_command;  /* a COMMAND was accepted since boot */
  uint8_t stall_timing;  /* applied throttle is above the stall threshold */
  uint16_t tx_seq;
  uint16_t last_seq;
  uint32_t decision_id;
  int16_t target_steer;     /* last commanded, clamped to +-10000 */
  int16_t target_throttle;  /* last commanded, clamped to [-max_reverse, max_forward] */
  int16_t applied_throttle; /* after the slew limit; 0 unless ARMED */
  uint16_t slew_rem;        /* sub-unit remainder of the slew (units * ms, < 1000) */
  uint16_t steer_us;        /* pulses last written to the HAL */
  uint16_t throttle_us;
  int32_t encoder;          /* encoder count last observed */
  uint32_t last_tick_ms;
  uint32_t last_command_ms;
  uint32_t decision_change_ms;
  uint32_t encoder_change_ms;
  uint32_t stall_since_ms;
  uint32_t telemetry_due_ms;
  fw_rc_channel_t rc[FW_RC_CHANNELS];
  uint8_t rc_drives;     /* the receiver's pulses drive the outputs */
  uint8_t auto_flag;     /* AUTO flag of the last accepted COMMAND */
} fw_core_t;

/* Boot: defaults or stored config, neutral outputs, DISARMED(BOOT), HELLO sent. The HAL struct
 * is copied; reset_cause (CARRT_RESET_CAUSE_*, from the MCU's reset flags) goes into every
 * HELLO of this boot. */
void fw_core_init(fw_core_t *core, const fw_hal_t *hal, uint32_t boot_id, uint8_t reset_cause,
                  uint32_t now_ms);

/* Feed bytes read from the serial port; frames are handled as soon as they complete. */
void fw_core_rx(fw_core_t *core, const uint8_t *data, uint16_t len, uint32_t now_ms);

/* Call often (every loop, ideally about 1 ms): timeouts, slew, stall check, telemetry. */
void fw_core_tick(fw_core_t *core, uint32_t now_ms);

/* An edge of a receiver pin (FW_RC_*): level 1 rising, 0 falling, ticks Timer1's 0.5 us count
 * (32-bit, wrapping) at the edge. Rules that a pulse may trigger are applied as it counts. */
void fw_core_rc_edge(fw_core_t *core, uint8_t channel, uint8_t level, uint32_t ticks,
                     uint32_t now_ms);
/* The receiver's clock, now_ticks in the edges' count, once every edge stamped before it has
 * been handed over (the shim: every loop() pass after its edges): a pulse counts once its line
 * has been quiet FW_RC_SETTLE_US after it (fw_rc.h), and its rules are applied then. */
void fw_core_rc_settle(fw_core_t *core, uint32_t now_ticks, uint32_t now_ms);
/* Would fw_core_rc_settle count a pulse at now_ticks? (the shim asks before it does the work) */
uint8_t fw_core_rc_settle_due(const fw_core_t *core, uint32_t now_ticks);
/* Edges of the channels in channel_mask (bit FW_RC_*) could not be stamped (the shim's queue was
 * full): those channels have no valid signal until a new run of good pulses, at once (ARMED
 * with the receiver wired: FAILSAFE, RC_LOST), instead of a width timed across a lost edge. */
void fw_core_rc_overflow(fw_core_t *core, uint8_t channel_mask, uint32_t now_ms);

/* Is this config acceptable (pulse ranges, centre between endpoints, limits, slew)? */
uint8_t fw_config_valid(const carrt_config_t *config);
void fw_config_defaults(carrt_config_t *config);

uint8_t fw_core_state(const fw_core_t *core);
uint8_t fw_core_reason(const fw_core_t *core);
uint8_t fw_core_arm_refusal(const fw_core_t *core);
uint16_t fw_core_steer_us(const fw_core_t *core);
uint16_t fw_core_throttle_us(const fw_core_t *core);
int16_t fw_core_applied_throttle(const fw_core_t *core);
const fw_rx_t *fw_core_rx_stats(const fw_core_t *core);
const carrt_config_t *fw_core_config(const fw_core_t *core);
uint8_t fw_core_rc_drives(const fw_core_t *core);
uint16_t fw_core_rc_width_us(const fw_core_t *core, uint8_t channel); /* 0: no valid signal */

#ifdef __cplusplus
}
#endif

#endif /* CARRT_FW_CORE_H */
