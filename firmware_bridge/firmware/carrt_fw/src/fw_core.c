/* The safety state machine; see fw_core.h for the contract.
 *
 * Portability notes (the same file runs on a 16 MHz AVR where int is 16 bits): every
 * intermediate that can leave int16 range is computed in int32_t/uint32_t, constants that
 * need it carry UL, and time is only ever compared through unsigned differences. */
#include "fw_core.h"

#include <string.h>

#define FW_FULL_SCALE 10000
#define FW_HALF_RANGE 0x80000000UL
/* Timestamps older than this are pulled forward in tick so that ages never alias across the
 * 49-day wrap of uint32 milliseconds (an idle car must still count as "wheels stopped"). */
#define FW_AGE_CAP_MS 3600000UL

/* ------------------------------------------------------------------ small helpers */

static uint8_t elapsed_at_least(uint32_t now, uint32_t since, uint32_t period) {
  return (uint32_t)(now - since) >= period ? 1u : 0u;
}

static uint8_t deadline_reached(uint32_t now, uint32_t deadline) {
  return (uint32_t)(now - deadline) < FW_HALF_RANGE ? 1u : 0u;
}

static void cap_age(uint32_t now, uint32_t *since) {
  if ((uint32_t)(now - *since) > FW_AGE_CAP_MS) {
    *since = (uint32_t)(now - (uint32_t)FW_AGE_CAP_MS);
  }
}

static int32_t clamp32(int32_t v, int32_t lo, int32_t hi) {
  if (v < lo) {
    return lo;
  }
  return v > hi ? hi : v;
}

static int32_t abs32(int32_t v) { return v < 0 ? -v : v; }

static uint8_t between(uint16_t v, uint16_t a, uint16_t b) {
  uint16_t lo = a < b ? a : b;
  uint16_t hi = a < b ? b : a;
  return (v >= lo && v <= hi) ? 1u : 0u;
}

static uint8_t pulse_ok(uint16_t us) { return (us >= 800u && us <= 2200u) ? 1u : 0u; }

/* -10000..0..10000 piecewise linear onto neg..mid..pos, clamped to the endpoints whatever
 * their order, so a reversed servo is as safe as a normal one. */
static uint16_t map_pulse(int32_t v, uint16_t neg, uint16_t mid, uint16_t pos) {
  int32_t out;
  int32_t lo = neg < pos ? (int32_t)neg : (int32_t)pos;
  int32_t hi = neg < pos ? (int32_t)pos : (int32_t)neg;
  v = clamp32(v, -FW_FULL_SCALE, FW_FULL_SCALE);
  if (v >= 0) {
    out = (int32_t)mid + ((int32_t)pos - (int32_t)mid) * v / FW_FULL_SCALE;
  } else {
    out = (int32_t)mid + ((int32_t)mid - (int32_t)neg) * v / FW_FULL_SCALE;
  }
  return (uint16_t)clamp32(out, lo, hi);
}

/* The inverse of map_pulse: which -10000..10000 a pulse stands for (0 beyond a missing side). */
static int16_t unmap_pulse(uint16_t us, uint16_t neg, uint16_t mid, uint16_t pos) {
  int32_t d = (int32_t)us - (int32_t)mid;
  int32_t up = (int32_t)pos - (int32_t)mid;
  int32_t down = (int32_t)mid - (int32_t)neg;
  if (d != 0 && up != 0 && ((d > 0) == (up > 0))) {
    return (int16_t)clamp32(d * FW_FULL_SCALE / up, -FW_FULL_SCALE, FW_FULL_SCALE);
  }
  if (d != 0 && down != 0 && ((d < 0) == (down > 0))) {
    return (int16_t)clamp32(d * FW_FULL_SCALE / down, -FW_FULL_SCALE, FW_FULL_SCALE);
  }
  return 0;
}

static uint16_t clamp_between(uint16_t v, uint16_t a, uint16_t b) {
  uint16_t lo = a < b ? a : b;
  uint16_t hi = a < b ? b : a;
  return v < lo ? lo : (v > hi ? hi : v);
}

static uint16_t udiff16(uint16_t a, uint16_t b) { return (uint16_t)(a > b ? a - b : b - a); }

/* ------------------------------------------------------------------ config */

void fw_config_defaults(carrt_config_t *config) {
  config->steer_left_us = 1000u;
  config->steer_center_us = 1500u;
  config->steer_right_us = 2000u;
  config->throttle_reverse_us = 1000u;
  config->throttle_neutral_us = 1500u;
  config->throttle_forward_us = 2000u;
  config->max_forward = 10000u;
  config->max_reverse = 10000u;
  config->slew_per_s = 20000UL;
  config->persist = 0u;
  config->controls = (uint8_t)CARRT_CONTROLS_PAD; /* a car with no receiver wired */
  config->rc_steer_center_us = 1500u;
  config->rc_throttle_center_us = 1500u;
  config->rc_deadzone_us = 60u;
  config->rc_estop_us = 1700u;
}

uint8_t fw_config_valid(const carrt_config_t *c) {
  if (!pulse_ok(c->steer_left_us) || !pulse_ok(c->steer_center_us) ||
      !pulse_ok(c->steer_right_us) || !pulse_ok(c->throttle_reverse_us) ||
      !pulse_ok(c->throttle_neutral_us) || !pulse_ok(c->throttle_forward_us)) {
    return 0;
  }
  if (c->steer_left_us == c->steer_right_us ||
      !between(c->steer_center_us, c->steer_left_us, c->steer_right_us)) {
    return 0;
  }
  /* reverse may equal neutral: forward-only ESCs have no reverse travel */
  if (c->throttle_forward_us == c->throttle_neutral_us ||
      !between(c->throttle_neutral_us, c->throttle_reverse_us, c->throttle_forward_us)) {
    return 0;
  }
  if (c->max_forward > 10000u || c->max_reverse > 10000u) {
    return 0;
  }
  if (c->controls > (uint8_t)CARRT_CONTROLS_BOTH || !pulse_ok(c->rc_steer_center_us) ||
      !pulse_ok(c->rc_throttle_center_us) || !pulse_ok(c->rc_estop_us) ||
      c->rc_deadzone_us < 10u || c->rc_deadzone_us > 500u) {
    return 0;
  }
  return (c->slew_per_s >= 100UL && c->slew_per_s <= 1000000UL) ? 1u : 0u;
}

static void storage_blob(const carrt_config_t *config, uint8_t *blob) {
  uint16_t crc;
  carrt_config_t copy = *config;
  copy.persist = 0u;
  blob[0] = (uint8_t)(FW_STORAGE_MAGIC & 0xFFu);
  blob[1] = (uint8_t)(FW_STORAGE_MAGIC >> 8);
  blob[2] = (uint8_t)FW_STORAGE_VERSION;
  carrt_pack_config(&copy, &blob[3]);
  crc = fw_crc16(blob, (uint16_t)(FW_STORAGE_SIZE - 2u));
  blob[FW_STORAGE_SIZE - 2u] = (uint8_t)(crc & 0xFFu);
  blob[FW_STORAGE_SIZE - 1u] = (uint8_t)(crc >> 8);
}

/* Blank (0xFF/0x00) or corrupt storage is ignored: magic, version, CRC and the values
 * themselves must all check out before a stored config may drive the outputs. */
static uint8_t load_config(fw_core_t *core) {
  uint8_t blob[FW_STORAGE_SIZE];
  uint8_t expect[FW_STORAGE_SIZE];
  carrt_config_t stored;
  uint16_t i;
  if (core->hal.storage_load == 0 ||
      !core->hal.storage_load(core->hal.ctx, blob, (uint16_t)FW_STORAGE_SIZE)) {
    return 0;
  }
  carrt_unpack_config(&blob[3], &stored);
  if (!fw_config_valid(&stored)) {
    return 0;
  }
  storage_blob(&stored, expect);
  for (i = 0; i < FW_STORAGE_SIZE; i++) {
    if (blob[i] != expect[i]) {
      return 0;
    }
  }
  stored.persist = 1u;
  core->config = stored;
  return 1;
}

static uint8_t store_config(fw_core_t *core, const carrt_config_t *config) {
  uint8_t blob[FW_STORAGE_SIZE];
  if (core->hal.storage_store == 0) {
    return 0;
  }
  storage_blob(config, blob);
  return core->hal.storage_store(core->hal.ctx, blob, (uint16_t)FW_STORAGE_SIZE) ? 1u : 0u;
}

/* ------------------------------------------------------------------ outputs and messages */

static void send_frame(fw_core_t *core, uint8_t type, const uint8_t *payload, uint16_t len) {
  uint8_t wire[FW_FRAME_MAX_ENCODED];
  uint16_t n = fw_frame_encode(type, core->tx_seq, payload, len, wire);
  core->tx_seq++;
  if (n != 0u && core->hal.serial_write != 0) {
    core->hal.serial_write(core->hal.ctx, wire, n);
  }
}

/* ------------------------------------------------------------------ the receiver */

static uint8_t rc_wired(const fw_core_t *core) {
  return core->config.controls != (uint8_t)CARRT_CONTROLS_PAD ? 1u : 0u;
}

static uint8_t rc_signal(const fw_core_t *core) {
  uint8_t i;
  for (i = 0; i < FW_RC_CHANNELS; i++) {
    if (!fw_rc_valid(&core->rc[i])) {
      return 0u;
    }
  }
  return 1u;
}

static uint8_t rc_throttle_moved(const fw_core_t *core) {
  return udiff16(fw_rc_width_us(&core->rc[FW_RC_THROTTLE]), core->config.rc_throttle_center_us) >
                 core->config.rc_deadzone_us
             ? 1u
             : 0u;
}

static uint8_t rc_sticks_moved(const fw_core_t *core) {
  return (rc_throttle_moved(core) ||
          udiff16(fw_rc_width_us(&core->rc[FW_RC_STEERING]), core->config.rc_steer_center_us) >
              core->config.rc_deadzone_us)
             ? 1u
             : 0u;
}

static uint8_t rc_switch_estop(const fw_core_t *core) {
  const fw_rc_channel_t *sw = &core->rc[FW_RC_SWITCH];
  return (fw_rc_valid(sw) && fw_rc_width_us(sw) >= core->config.rc_estop_us) ? 1u : 0u;
}

/* The receiver's pulses as outputs: each clamped between its endpoints, the throttle also to
 * max_forward/max_reverse, as a command would be; the applied throttle follows (stall rule). */
static void rc_outputs(fw_core_t *core, uint16_t *steer, uint16_t *throttle) {
  const carrt_config_t *c = &core->config;
  uint16_t fwd = map_pulse((int32_t)c->max_forward, c->throttle_reverse_us, c->throttle_neutral_us,
                           c->throttle_forward_us);
  uint16_t rev = map_pulse(-(int32_t)c->max_reverse, c->throttle_reverse_us,
                           c->throttle_neutral_us, c->throttle_forward_us);
  *steer = clamp_between(fw_rc_steady_us(&core->rc[FW_RC_STEERING]), c->steer_left_us,
                         c->steer_right_us);
  *throttle = clamp_between(fw_rc_steady_us(&core->rc[FW_RC_THROTTLE]), rev, fwd);
  core->applied_throttle =
      unmap_pulse(*throttle, c->throttle_reverse_us, c->throttle_neutral_us, c->throttle_forward_us);
}

static void write_outputs(fw_core_t *core, uint8_t force) {
  const carrt_config_t *c = &core->config;
  uint16_t steer = c->steer_center_us;
  uint16_t throttle = c->throttle_neutral_us;
  if (core->state == CARRT_STATE_ARMED && core->rc_drives) {
    rc_outputs(core, &steer, &throttle);
  } else if (core->state == CARRT_STATE_ARMED) {
    steer = map_pulse(core->target_steer, c->steer_left_us, c->steer_center_us,
                      c->steer_right_us);
    throttle = map_pulse(core->applied_throttle, c->throttle_reverse_us,
                         c->throttle_neutral_us, c->throttle_forward_us);
  }
  if (force || steer != core->steer_us) {
    core->steer_us = steer;
    if (core->hal.pwm_write != 0) {
      core->hal.pwm_write(core->hal.ctx, (uint8_t)FW_PWM_STEERING, steer);
    }
  }
  if (force || throttle != core->throttle_us) {
    core->throttle_us = throttle;
    if (core->hal.pwm_write != 0) {
      core->hal.pwm_write(core->hal.ctx, (uint8_t)FW_PWM_THROTTLE, throttle);
    }
  }
}

static void sync_outputs(fw_core_t *core) {
  if (core->hal.pwm_sync != 0) {
    core->hal.pwm_sync(core->hal.ctx);
  }
}

static void enter_state(fw_core_t *core, uint8_t state, uint8_t reason) {
  uint8_t stopping = (core->state == CARRT_STATE_ARMED && state != CARRT_STATE_ARMED) ? 1u : 0u;
  core->state = state;
  core->reason = reason;
  core->applied_throttle = 0;
  core->slew_rem = 0u;
  core->stall_timing = 0u;
  core->rc_drives = 0u;
  write_outputs(core, 0u);
  if (stopping) {
    sync_outputs(core); /* neutral reaches the pins now, not at the end of the period */
  }
}

/* The receiver's rules, after each of its pulses, each tick and each COMMAND. */
static void apply_receiver(fw_core_t *core) {
  if (!rc_wired(core)) {
    core->rc_drives = 0u;
    return;
  }
  if (rc_switch_estop(core) && core->state != CARRT_STATE_ESTOP) {
    enter_state(core, CARRT_STATE_ESTOP, CARRT_REASON_RC_SWITCH);
  }
  if (core->state != CARRT_STATE_ARMED) {
    core->rc_drives = 0u;
    return;
  }
  if (!rc_signal(core)) {
    enter_state(core, CARRT_STATE_FAILSAFE, CARRT_REASON_RC_LOST);
    return;
  }
  if (!core->rc_drives &&
      ((!core->auto_flag && core->config.controls == (uint8_t)CARRT_CONTROLS_RECEIVER) ||
       rc_sticks_moved(core))) {
    core->rc_drives = 1u; /* held until the AUTO flag's next 0 -> 1 edge */
    write_outputs(core, 0u);
    sync_outputs(core);
  }
}

static void send_hello(fw_core_t *core) {
  carrt_hello_t hello;
  uint8_t payload[CARRT_MSG_HELLO_SIZE];
  hello.protocol_hash = (uint32_t)CARRT_PROTOCOL_HASH;
  hello.boot_id = core->boot_id;
  hello.fw_major = (uint8_t)CARRT_FW_MAJOR;
  hello.fw_minor = (uint8_t)CARRT_FW_MINOR;
  hello.fw_patch = (uint8_t)CARRT_FW_PATCH;
  hello.config_from_storage = core->config.persist;
  hello.reset_cause = core->reset_cause;
  carrt_pack_hello(&hello, payload);
  send_frame(core, CARRT_MSG_HELLO, payload, CARRT_MSG_HELLO_SIZE);
}

static void send_config(fw_core_t *core) {
  uint8_t payload[CARRT_MSG_CONFIG_SIZE];
  carrt_pack_config(&core->config, payload);
  send_frame(core, CARRT_MSG_CONFIG, payload, CARRT_MSG_CONFIG_SIZE);
}

static void send_telemetry(fw_core_t *core, uint32_t now_ms) {
  carrt_telemetry_t t;
  uint8_t payload[CARRT_MSG_TELEMETRY_SIZE];
  t.mcu_time_ms = now_ms;
  t.encoder_ticks = core->encoder;
  t.steer_us = core->steer_us;
  t.throttle_us = core->throttle_us;
  t.state = core->state;
  t.reason = core->reason;
  t.arm_refusal = core->arm_refusal;
  t.flags = 0u;
  if (core->config.persist) {
    t.flags |= CARRT_TELEMETRY_FLAGS_CONFIG_FROM_STORAGE;
  }
  if (core->have_command &&
      !elapsed_at_least(now_ms, core->last_command_ms, FW_LINK_TIMEOUT_MS)) {
    t.flags |= CARRT_TELEMETRY_FLAGS_LINK_OK;
  }
  t.bad_crc = core->rx.bad_crc;
  t.bad_length = core->rx.bad_length;
  t.overruns = core->rx.overruns;
  t.last_seq = core->last_seq;
  t.decision_id = core->decision_id;
  t.rc_steer_us = fw_rc_steady_us(&core->rc[FW_RC_STEERING]);
  t.rc_throttle_us = fw_rc_steady_us(&core->rc[FW_RC_THROTTLE]);
  t.rc_switch_us = fw_rc_steady_us(&core->rc[FW_RC_SWITCH]);
  if (rc_signal(core)) {
    t.flags |= CARRT_TELEMETRY_FLAGS_RC_SIGNAL;
  }
  if (core->rc_drives) {
    t.flags |= CARRT_TELEMETRY_FLAGS_RC_DRIVES;
  }
  carrt_pack_telemetry(&t, payload);
  send_frame(core, CARRT_MSG_TELEMETRY, payload, CARRT_MSG_TELEMETRY_SIZE);
}

/* ------------------------------------------------------------------ safety logic */

static void sample_encoder(fw_core_t *core, uint32_t now_ms) {
  int32_t count = core->hal.encoder_read != 0 ? core->hal.encoder_read(core->hal.ctx) : 0;
  if (count != core->encoder) {
    core->encoder = count;
    core->encoder_change_ms = now_ms;
    core->stall_since_ms = now_ms; /* only read while stall_timing */
  }
}

/* Link watchdog and decision freshness; run before a COMMAND refreshes them, too, so a late
 * tick cannot hide a gap. While the receiver drives, the person's hand reaches the wheels
 * through the board alone: the host's rules give way to the receiver's loss rule. */
static void check_timeouts(fw_core_t *core, uint32_t now_ms) {
  if (core->state != CARRT_STATE_ARMED || core->rc_drives) {
    return;
  }
  if (elapsed_at_least(now_ms, core->last_command_ms, FW_LINK_TIMEOUT_MS)) {
    enter_state(core, CARRT_STATE_FAILSAFE, CARRT_REASON_LINK_TIMEOUT);
  } else if (elapsed_at_least(now_ms, core->decision_change_ms, FW_DECISION_STALE_MS)) {
    enter_state(core, CARRT_STATE_FAILSAFE, CARRT_REASON_DECISION_STALE);
  }
}

/* Largest rise allowed over dt ms; the sub-unit remainder is kept so that slow rates still
 * advance at 1 ms ticks (100/s is one unit every 10 ms). */
static int32_t slew_step(fw_core_t *core, uint32_t dt) {
  uint32_t rate = core->config.slew_per_s;
  uint32_t acc;
  uint32_t step;
  uint32_t whole = dt / 1000u;
  const uint32_t full_travel = 2UL * FW_FULL_SCALE;
  if (rate == 0u) {
    return 0;
  }
  acc = (dt % 1000u) * rate + core->slew_rem; /* < 1000 * 1e6 + 1000: fits */
  step = acc / 1000u;
  core->slew_rem = (uint16_t)(acc % 1000u);
  if (whole > full_travel / rate) {
    return (int32_t)full_travel;
  }
  step += whole * rate;
  return step > full_travel ? (int32_t)full_travel : (int32_t)step;
}

/* Falls toward zero and sign changes are immediate; rises are limited (only when rise=1). */
static void slew_throttle(fw_core_t *core, uint32_t dt, uint8_t rise) {
  int32_t target = core->target_throttle;
  int32_t applied = core->applied_throttle;
  int32_t gap;
  if ((target > 0 && applied < 0) || (target < 0 && applied > 0)) {
    applied = 0;
    core->slew_rem = 0u;
  }
  if (abs32(target) <= abs32(applied)) {
    applied = target;
    core->slew_rem = 0u;
  } else if (rise) {
    int32_t step = slew_step(core, dt);
    gap = abs32(target) - abs32(applied);
    if (step >= gap) {
      applied = target;
      core->slew_rem = 0u;
    } else {
      applied += target > 0 ? step : -step;
    }
  }
  core->applied_throttle = (int16_t)applied;
}

static void try_arm(fw_core_t *core, int16_t throttle, uint32_t now_ms) {
  if (abs32(throttle) > FW_ARM_THROTTLE_MAX) {
    core->arm_refusal = CARRT_ARM_REFUSAL_THROTTLE_NOT_NEUTRAL;
  } else if (!elapsed_at_least(now_ms, core->encoder_change_ms, FW_WHEELS_STOPPED_MS)) {
    core->arm_refusal = CARRT_ARM_REFUSAL_WHEELS_MOVING;
  } else if (rc_wired(core) && !rc_signal(core)) {
    core->arm_refusal = CARRT_ARM_REFUSAL_RC_NO_SIGNAL;
  } else if (rc_wired(core) && rc_throttle_moved(core)) {
    core->arm_refusal = CARRT_ARM_REFUSAL_RC_NOT_NEUTRAL;
  } else {
    core->arm_refusal = CARRT_ARM_REFUSAL_NONE;
    core->decision_change_ms = now_ms; /* freshness is measured from arming */
    enter_state(core, CARRT_STATE_ARMED, CARRT_REASON_ARMED_OK);
  }
}

static void on_command(fw_core_t *core, const uint8_t *payload, uint32_t now_ms) {
  carrt_command_t cmd;
  uint8_t arm;
  uint8_t edge;
  carrt_unpack_command(payload, &cmd);
  arm = (cmd.flags & CARRT_COMMAND_FLAGS_ARM) ? 1u : 0u;
  edge = (arm && !core->prev_arm) ? 1u : 0u;
  if ((cmd.flags & CARRT_COMMAND_FLAGS_AUTO) && !core->auto_flag) {
    core->rc_drives = 0u; /* the host resumes the policy: the wheels go back to it */
  }
  core->auto_flag = (cmd.flags & CARRT_COMMAND_FLAGS_AUTO) ? 1u : 0u;
  sample_encoder(core, now_ms);
  check_timeouts(core, now_ms);

  core->have_command = 1u;
  core->last_command_ms = now_ms;
  if (cmd.decision_id != core->decision_id) {
    core->decision_change_ms = now_ms;
    core->decision_id = cmd.decision_id;
  }
  core->target_steer = (int16_t)clamp32(cmd.steering, -FW_FULL_SCALE, FW_FULL_SCALE);
  core->target_throttle = (int16_t)clamp32(cmd.throttle, -(int32_t)core->config.max_reverse,
                                           (int32_t)core->config.max_forward);

  if (cmd.flags & CARRT_COMMAND_FLAGS_ESTOP) {
    if (core->state != CARRT_STATE_ESTOP) {
      enter_state(core, CARRT_STATE_ESTOP, CARRT_REASON_ESTOP_COMMAND);
    }
    if (edge) {
      core->arm_refusal = CARRT_ARM_REFUSAL_NOT_DISARMED;
    }
  } else if (core->state == CARRT_STATE_ESTOP || core->state == CARRT_STATE_FAILSAFE) {
    if ((cmd.flags & CARRT_COMMAND_FLAGS_CLEAR) && !arm) {
      enter_state(core, CARRT_STATE_DISARMED, CARRT_REASON_CLEARED);
    } else if (edge) {
      core->arm_refusal = CARRT_ARM_REFUSAL_NOT_DISARMED;
    }
  } else if (core->state == CARRT_STATE_DISARMED) {
    if (edge) {
      try_arm(core, cmd.throttle, now_ms);
    } else if (arm && core->arm_refusal == CARRT_ARM_REFUSAL_NONE) {
      /* held without an edge (e.g. across a reboot); a more specific refusal is kept */
      core->arm_refusal = CARRT_ARM_REFUSAL_NO_EDGE;
    }
  } else if (!arm) {
    enter_state(core, CARRT_STATE_DISARMED, CARRT_REASON_HOST_DISARM);
  }
  core->prev_arm = arm;

  apply_receiver(core);
  check_timeouts(core, now_ms);
  if (core->state == CARRT_STATE_ARMED && !core->rc_drives) {
    slew_throttle(core, 0u, 0u);
    if (core->applied_throttle <= FW_STALL_THROTTLE) {
      core->stall_timing = 0u;
    }
  }
  write_outputs(core, 0u);
}

static void on_config(fw_core_t *core, uint16_t seq, const uint8_t *payload) {
  carrt_config_t config;
  carrt_config_ack_t ack;
  uint8_t out[CARRT_MSG_CONFIG_ACK_SIZE];
  carrt_unpack_config(payload, &config);
  ack.config_seq = seq;
  ack.persisted = 0u;
  if (core->state == CARRT_STATE_ARMED) {
    ack.result = CARRT_CONFIG_RESULT_REJECTED_ARMED;
  } else if (!fw_config_valid(&config)) {
    ack.result = CARRT_CONFIG_RESULT_REJECTED_INVALID;
  } else {
    uint8_t want_store = config.persist ? 1u : 0u;
    config.persist = 0u;
    if (want_store) {
      config.persist = store_config(core, &config);
    }
    core->config = config;
    ack.result = CARRT_CONFIG_RESULT_ACCEPTED;
    ack.persisted = config.persist;
    write_outputs(core, 0u); /* the neutral pulses may have moved */
  }
  carrt_pack_config_ack(&ack, out);
  send_frame(core, CARRT_MSG_CONFIG_ACK, out, CARRT_MSG_CONFIG_ACK_SIZE);
}

static void on_frame(fw_core_t *core, const fw_frame_t *frame, uint32_t now_ms) {
  switch (frame->type) {
    case CARRT_MSG_COMMAND:
      core->last_seq = frame->seq;
      on_command(core, frame->payload, now_ms);
      break;
    case CARRT_MSG_PING: {
      carrt_ping_t ping;
      carrt_pong_t pong;
      uint8_t out[CARRT_MSG_PONG_SIZE];
      core->last_seq = frame->seq;
      carrt_unpack_ping(frame->payload, &ping);
      pong.nonce = ping.nonce;
      pong.mcu_time_ms = now_ms;
      carrt_pack_pong(&pong, out);
      send_frame(core, CARRT_MSG_PONG, out, CARRT_MSG_PONG_SIZE);
      break;
    }
    case CARRT_MSG_HELLO_REQUEST:
      core->last_seq = frame->seq;
      send_hello(core);
      break;
    case CARRT_MSG_CONFIG_REQUEST:
      core->last_seq = frame->seq;
      send_config(core);
      break;
    case CARRT_MSG_CONFIG:
      core->last_seq = frame->seq;
      on_config(core, frame->seq, frame->payload);
      break;
    default:
      break; /* board->host types echoed back at us: valid frames, nothing to do */
  }
}

/* ------------------------------------------------------------------ public API */

void fw_core_init(fw_core_t *core, const fw_hal_t *hal, uint32_t boot_id, uint8_t reset_cause,
                  uint32_t now_ms) {
  memset(core, 0, sizeof *core);
  core->hal = *hal;
  fw_rx_init(&core->rx);
  fw_config_defaults(&core->config);
  (void)load_config(core);
  core->boot_id = boot_id;
  core->reset_cause = reset_cause <= (uint8_t)CARRT_RESET_CAUSE_WATCHDOG
                          ? reset_cause
                          : (uint8_t)CARRT_RESET_CAUSE_UNKNOWN;
  core->state = CARRT_STATE_DISARMED;
  core->reason = CARRT_REASON_BOOT;
  core->arm_refusal = CARRT_ARM_REFUSAL_NONE;
  core->prev_arm = 1u; /* a host holding ARM across our reboot must make a fresh edge */
  core->encoder = hal->encoder_read != 0 ? hal->encoder_read(hal->ctx) : 0;
  /* Wheels count as stopped only after 100 ms of observation since boot. */
  core->encoder_change_ms = now_ms;
  core->last_tick_ms = now_ms;
  core->last_command_ms = now_ms;
  core->decision_change_ms = now_ms;
  core->stall_since_ms = now_ms;
  core->telemetry_due_ms = now_ms;
  write_outputs(core, 1u);
  send_hello(core);
}

void fw_core_rx(fw_core_t *core, const uint8_t *data, uint16_t len, uint32_t now_ms) {
  fw_frame_t frame;
  uint16_t i;
  for (i = 0; i < len; i++) {
    if (fw_rx_push(&core->rx, data[i], &frame)) {
      on_frame(core, &frame, now_ms);
    }
  }
}

/* A pulse counted (or a channel restarted): it may move a stick, the switch, or the outputs. */
static void rc_changed(fw_core_t *core) {
  apply_receiver(core);
  if (core->rc_drives) {
    write_outputs(core, 0u);
  }
}

void fw_core_rc_edge(fw_core_t *core, uint8_t channel, uint8_t level, uint32_t ticks,
                     uint32_t now_ms) {
  if (channel >= FW_RC_CHANNELS) {
    return;
  }
  if (fw_rc_edge(&core->rc[channel], level, ticks, now_ms)) {
    rc_changed(core);
  }
}

void fw_core_rc_settle(fw_core_t *core, uint32_t now_ticks, uint32_t now_ms) {
  uint8_t taken = 0u;
  uint8_t i;
  (void)now_ms;
  for (i = 0; i < FW_RC_CHANNELS; i++) {
    taken |= fw_rc_settle(&core->rc[i], now_ticks);
  }
  if (taken) {
    rc_changed(core);
  }
}

uint8_t fw_core_rc_settle_due(const fw_core_t *core, uint32_t now_ticks) {
  uint8_t i;
  for (i = 0; i < FW_RC_CHANNELS; i++) {
    if (fw_rc_settle_due(&core->rc[i], now_ticks)) {
      return 1u;
    }
  }
  return 0u;
}

void fw_core_rc_overflow(fw_core_t *core, uint8_t channel_mask, uint32_t now_ms) {
  uint8_t i;
  (void)now_ms;
  for (i = 0; i < FW_RC_CHANNELS; i++) {
    if (channel_mask & (uint8_t)(1u << i)) {
      fw_rc_restart(&core->rc[i]);
    }
  }
  if (channel_mask & (uint8_t)((1u << FW_RC_CHANNELS) - 1u)) {
    rc_changed(core); /* armed with the receiver wired: its signal is gone, FAILSAFE */
  }
}

void fw_core_tick(fw_core_t *core, uint32_t now_ms) {
  uint32_t dt = now_ms - core->last_tick_ms;
  uint8_t i;
  core->last_tick_ms = now_ms;
  cap_age(now_ms, &core->last_command_ms);
  cap_age(now_ms, &core->decision_change_ms);
  cap_age(now_ms, &core->encoder_change_ms);
  cap_age(now_ms, &core->stall_since_ms);
  sample_encoder(core, now_ms);
  for (i = 0; i < FW_RC_CHANNELS; i++) {
    fw_rc_poll(&core->rc[i], now_ms);
  }
  apply_receiver(core);
  check_timeouts(core, now_ms);
  if (core->state == CARRT_STATE_ARMED) {
    if (!core->rc_drives) {
      slew_throttle(core, dt, 1u);
    }
    if (core->applied_throttle > FW_STALL_THROTTLE) {
      if (!core->stall_timing) {
        core->stall_timing = 1u;
        core->stall_since_ms = now_ms;
      }
      if (elapsed_at_least(now_ms, core->stall_since_ms, FW_STALL_MS)) {
        enter_state(core, CARRT_STATE_FAILSAFE, CARRT_REASON_STALL);
      }
    } else {
      core->stall_timing = 0u;
    }
  }
  write_outputs(core, 0u);
  if (deadline_reached(now_ms, core->telemetry_due_ms)) {
    send_telemetry(core, now_ms);
    core->telemetry_due_ms += FW_TELEMETRY_PERIOD_MS;
    if (deadline_reached(now_ms, core->telemetry_due_ms)) {
      core->telemetry_due_ms = now_ms + FW_TELEMETRY_PERIOD_MS; /* far behind: resync */
    }
  }
}

uint8_t fw_core_state(const fw_core_t *core) { return core->state; }
uint8_t fw_core_reason(const fw_core_t *core) { return core->reason; }
uint8_t fw_core_arm_refusal(const fw_core_t *core) { return core->arm_refusal; }
uint16_t fw_core_steer_us(const fw_core_t *core) { return core->steer_us; }
uint16_t fw_core_throttle_us(const fw_core_t *core) { return core->throttle_us; }
int16_t fw_core_applied_throttle(const fw_core_t *core) { return core->applied_throttle; }
const fw_rx_t *fw_core_rx_stats(const fw_core_t *core) { return &core->rx; }
const carrt_config_t *fw_core_config(const fw_core_t *core) { return &core->config; }
uint8_t fw_core_rc_drives(const fw_core_t *core) { return core->rc_drives; }
uint16_t fw_core_rc_width_us(const fw_core_t *core, uint8_t channel) {
  return channel < FW_RC_CHANNELS ? fw_rc_width_us(&core->rc[channel]) : 0u;
}
