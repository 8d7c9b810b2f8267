// carrt_fw: thin Arduino shim over the portable firmware core in src/.
//
// All protocol handling and every safety rule (watchdog, e-stop latch, arming, slew limit,
// stall check) live in src/fw_core.c, which the host tests run unchanged. This file only wires
// the core to the board: two Servo outputs, an interrupt-counted wheel encoder, the serial port,
// EEPROM for the persistent config, and millis() as the clock. (ESP32 boards need the
// ESP32Servo library, whose header is also called Servo.h.)

#include <Arduino.h>
#include <Servo.h>

#if defined(__has_include)
#if __has_include(<EEPROM.h>)
#include <EEPROM.h>
#define CARRT_HAVE_EEPROM 1
#endif
#endif

#include "src/fw_core.h"

#define STEERING_PIN 9     // steering servo signal
#define ESC_PIN 10         // ESC (throttle) signal
#define ENCODER_PIN 2      // wheel encoder, must be an interrupt-capable pin
#define SERIAL_BAUD 250000 // 0 % divisor error at 16 MHz; native USB boards ignore it
#define RX_CHUNK 64        // bytes handled per loop() so tick() is never starved

// EEPROM layout: boot counter (uint32) at 0, config blob (FW_STORAGE_SIZE bytes) at 8.
#define EEPROM_BOOT_COUNT_ADDR 0
#define EEPROM_CONFIG_ADDR 8
#define EEPROM_BYTES 64
static_assert(EEPROM_CONFIG_ADDR + FW_STORAGE_SIZE <= EEPROM_BYTES, "config blob too large");

// Boards that emulate EEPROM in flash need begin()/commit().
#if defined(ESP32) || defined(ESP8266) || defined(ARDUINO_ARCH_RP2040)
#define CARRT_EEPROM_EMULATED 1
#endif

#ifndef IRAM_ATTR
#define IRAM_ATTR  // only ESP boards need ISRs placed in IRAM
#endif

static Servo steering;
static Servo esc;
static volatile int32_t encoder_ticks = 0;
static fw_core_t core;
static fw_hal_t hal;

static void IRAM_ATTR on_encoder_edge() { encoder_ticks++; }

// ---------------------------------------------------------------- HAL for the core

static void hal_pwm_write(void *ctx, uint8_t channel, uint16_t pulse_us) {
  (void)ctx;
  Servo &servo = (channel == FW_PWM_STEERING) ? steering : esc;
  // Attach on the first write, so the very first pulse is already the configured neutral.
  if (!servo.attached()) {
    servo.attach(channel == FW_PWM_STEERING ? STEERING_PIN : ESC_PIN);
  }
  servo.writeMicroseconds(pulse_us);
}

static int32_t hal_encoder_read(void *ctx) {
  (void)ctx;
  noInterrupts();  // a 32-bit read is not atomic on an 8-bit CPU
  int32_t ticks = encoder_ticks;
  interrupts();
  return ticks;
}

static void hal_serial_write(void *ctx, const uint8_t *data, uint16_t len) {
  (void)ctx;
  Serial.write(data, len);
}

static uint8_t hal_storage_load(void *ctx, uint8_t *data, uint16_t len) {
  (void)ctx;
#ifdef CARRT_HAVE_EEPROM
  for (uint16_t i = 0; i < len; i++) {
    data[i] = EEPROM.read(EEPROM_CONFIG_ADDR + i);
  }
  return 1;  // blank or corrupt contents are rejected by the core (magic + CRC)
#else
  (void)data;
  (void)len;
  return 0;
#endif
}

static uint8_t hal_storage_store(void *ctx, const uint8_t *data, uint16_t len) {
  (void)ctx;
#ifdef CARRT_HAVE_EEPROM
  for (uint16_t i = 0; i < len; i++) {
    if (EEPROM.read(EEPROM_CONFIG_ADDR + i) != data[i]) {  // spare the EEPROM's write cycles
      EEPROM.write(EEPROM_CONFIG_ADDR + i, data[i]);
    }
  }
#ifdef CARRT_EEPROM_EMULATED
  return EEPROM.commit() ? 1 : 0;
#else
  return 1;
#endif
#else
  (void)data;
  (void)len;
  return 0;
#endif
}

// A boot id that differs on every reset, so the host notices a reboot even when it was quick:
// a persistent boot counter mixed with ADC noise from a floating pin and the boot timing.
static uint32_t make_boot_id() {
  uint32_t count = 0;
#ifdef CARRT_HAVE_EEPROM
  EEPROM.get(EEPROM_BOOT_COUNT_ADDR, count);
  count++;
  EEPROM.put(EEPROM_BOOT_COUNT_ADDR, count);
#ifdef CARRT_EEPROM_EMULATED
  EEPROM.commit();
#endif
#endif
  uint32_t noise = 0;
  for (uint8_t i = 0; i < 16; i++) {
    noise = (noise << 3) ^ (noise >> 29) ^ (uint32_t)analogRead(A0) ^ (uint32_t)micros();
  }
  return (count * 2654435761UL) ^ noise;
}

// ---------------------------------------------------------------- Arduino entry points

void setup() {
  Serial.begin(SERIAL_BAUD);  // no while (!Serial): the board must run without a host
#ifdef CARRT_EEPROM_EMULATED
  EEPROM.begin(EEPROM_BYTES);
#endif
  pinMode(ENCODER_PIN, INPUT_PULLUP);
  attachInterrupt(digitalPinToInterrupt(ENCODER_PIN), on_encoder_edge, RISING);

  hal.ctx = 0;
  hal.pwm_write = hal_pwm_write;
  hal.encoder_read = hal_encoder_read;
  hal.serial_write = hal_serial_write;
  hal.storage_load = hal_storage_load;
  hal.storage_store = hal_storage_store;
  // Writes neutral pulses (attaching the servos) and sends HELLO.
  fw_core_init(&core, &hal, make_boot_id(), millis());
}

void loop() {
  uint8_t buf[RX_CHUNK];
  uint16_t n = 0;
  while (n < RX_CHUNK && Serial.available() > 0) {
    buf[n++] = (uint8_t)Serial.read();
  }
  if (n > 0) {
    fw_core_rx(&core, buf, n, millis());
  }
  fw_core_tick(&core, millis());
}
