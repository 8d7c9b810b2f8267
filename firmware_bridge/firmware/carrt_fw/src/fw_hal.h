/* The firmware core's only view of the hardware.
 *
 * The core never touches a register, a clock or a global: the Arduino sketch fills this struct
 * with thin wrappers around Servo/Serial/EEPROM, and the host harness (host/fw_host.c) fills it
 * with in-memory fakes, so the very same core runs on the car and inside the Python tests.
 * Time is not part of the HAL: every core call takes the current time (uint32 ms) as an
 * argument, and all timing uses unsigned subtraction so it survives the 49-day wrap. */
#ifndef CARRT_FW_HAL_H
#define CARRT_FW_HAL_H

#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define FW_PWM_STEERING 0u /* steering servo */
#define FW_PWM_THROTTLE 1u /* ESC */

typedef struct fw_hal {
  void *ctx; /* passed back to every function below */
  /* Set the pulse width (microseconds) of an output channel (FW_PWM_*). */
  void (*pwm_write)(void *ctx, uint8_t channel, uint16_t pulse_us);
  /* Cumulative wheel-encoder ticks since boot (wrapping int32 is fine). */
  int32_t (*encoder_read)(void *ctx);
  /* Queue bytes for the serial port; the core hands over one whole frame per call. */
  void (*serial_write)(void *ctx, const uint8_t *data, uint16_t len);
  /* Read/write the persistent config blob (FW_STORAGE_SIZE bytes). Return 1 on success.
   * Either may be NULL on a board without persistent storage. */
  uint8_t (*storage_load)(void *ctx, uint8_t *data, uint16_t len);
  uint8_t (*storage_store)(void *ctx, const uint8_t *data, uint16_t len);
  /* Start the next output frame as soon as the pulses now on the pins have ended, instead of
   * at the end of the 20 ms period: called when a safety change (e-stop, failsafe, a receiver
   * take-over) must reach the servo and the ESC within one pulse period of its cause. May be
   * NULL (outputs that follow a new width at once, as the host harness's). */
  void (*pwm_sync)(void *ctx);
} fw_hal_t;

#ifdef __cplusplus
}
#endif

#endif /* CARRT_FW_HAL_H */
