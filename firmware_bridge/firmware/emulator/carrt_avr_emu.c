/* carrt_avr_emu: the carrt firmware ELF on an emulated ATmega328P, for the tests and the CLI.
 *
 * Why: the x86 build of the core (host/fw_host.c) checks the logic, but not the binary that is
 * flashed: the Arduino core, Timer1's pulses, the UART at 250000 baud, the encoder interrupt,
 * EEPROM and 16-bit int arithmetic. Here the real ELF runs in simavr at 16 MHz with:
 *   - UART0 bridged to a pseudo-terminal, so the host opens it like /dev/ttyACM0;
 *   - emulated time paced to wall time (the host link's timeouts are wall-clock);
 *   - every edge of OC1A/OC1B (steering/ESC pulses on PB1/PB2), PB5 (ARMED LED) and PB4/PB3 (rx/tick busy)
 *     recorded
 *     with its cycle, so pulse widths and watchdog delays are measured in emulated time;
 *   - PD2 (INT0, wheel encoder) driven with a square wave at a commanded rate;
 *   - PD4/PD5/PD6 (the RC receiver's steering, throttle and switch channels) driven with pulse
 *     trains of a commanded width, period and phase, or with random edges (noise);
 *   - a reset that keeps EEPROM and sets the reset flag of its cause, and EEPROM saved to /
 *     loaded from a file.
 *
 * Control channel: one command per line on stdin, one reply line on stdout (firmware_bridge/
 * avr_emulator.py speaks it). The first line out is "ready <pty path>".
 *   time            -> "time <cycle> <lag_us>"   (lag: how far emulation trails wall time)
 *   pulses          -> "pulses <A width> <A count> <B width> <B count>" (widths in cycles)
 *   busy            -> "busy <rx total> <rx count> <rx max> <tick ...> <rc ...>" (3 each)
 *                      cycles PB4 (fw_core_rx) / PB3 (fw_core_tick) / PB0 (receiver edges)
 *                      were high since the last busy, how often they went high, the longest;
 *                      then starts over
 *   events          -> "events <dropped> <kind><value>@<cycle> ..." and clears the log; kinds:
 *                      L ARMED LED level, F host frame delimiter into the UART, A/B pulse width
 *                      changed (cycles), R reset (value: its cause), W/O receiver width taken / train stopped,
 *                      N/E a burst's first / last edge
 *   encoder <hz>    -> "ok" (rising edges per second on PD2; 0 stops)
 *   rc <ch> <width_us> <period_us> <phase_us>
 *                   -> "ok": receiver channel ch (0 steering PD4, 1 throttle PD5, 2 switch PD6)
 *                      sends pulses of width_us every period_us; a running train takes a new
 *                      width at its next rising edge (never cutting a pulse) and logs W<ch> at
 *                      the falling edge of the first pulse with it; phase: first rise from now
 *   rc <ch> off     -> "ok": the train stops after the pulse in flight (line low); O<ch> is
 *                      logged at its last falling edge
 *   rc <ch> noise <mean_gap_us> <seed> -> "ok": random edges, gaps 1 .. 2*mean_gap_us
 *   rc <ch> burst <edges> <gap_min_us> <gap_max_us> <seed> <delay_us> [<train>]
 *                   -> "ok": glitches on top of whatever drives the line (a train, noise, the
 *                      idle level): delay_us from now (or, with a running train's channel,
 *                      from that train's next falling edge: then the delay may be negative),
 *                      the line flips <edges> times (rounded up to even, so it ends at the
 *                      level it would have had), gap_min_us .. gap_max_us apart (uniform,
 *                      whole cycles); logs N<ch> at its first edge and E<ch> at its last
 *   reset [<cause>] -> "ok": emulated reset, EEPROM kept, with the reset flag in MCUSR the
 *                      cause sets on the chip: external (the reset pin; the default),
 *                      watchdog, brown-out, power-on; R<code> is logged (code: 2, 4, 3, 1 as
 *                      in messages.ResetCause)
 *   eeprom          -> "eeprom <hex of the first 64 bytes>"
 *   quit / EOF      -> EEPROM saved, exit 0 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include "avr_eeprom.h"
#include "avr_ioport.h"
#include "avr_timer.h"
#include "avr_uart.h"
#include "sim_avr.h"
#include "sim_elf.h"

#define F_CPU 16000000u
#define SLICE_CYCLES 16000u    /* service the pty and the control channel every 1 ms */
#define MAX_LAG_CYCLES 320000u /* behind wall time by more than 20 ms: forgive the debt */
#define EEPROM_SIZE 1024u
#define EVENT_CAPACITY 16384u
#define HOST_QUEUE 4096u

typedef struct {
  char kind;
  uint64_t cycle;
  uint64_t value;
} event_t;

typedef struct {
  uint64_t rise;
  uint64_t width;
  uint64_t logged;
  uint64_t count;
  int high;
} pulse_pin_t;

static avr_t *avr;
static int pty_master = -1;
static int uart_xon = 1;
static avr_irq_t *uart_in;
static avr_irq_t *pd2;
static uint8_t host_queue[HOST_QUEUE];
static size_t host_len;
static event_t events[EVENT_CAPACITY];
static size_t event_len;
static uint64_t events_dropped;
static pulse_pin_t pulse[2]; /* PB1 (OC1A, steering), PB2 (OC1B, ESC) */
typedef struct {
  uint64_t rise;
  uint64_t total; /* cycles high */
  uint64_t count; /* times it went high */
  uint64_t max;   /* longest high */
  int high;
} busy_pin_t;
static busy_pin_t busy[3]; /* PB4: fw_core_rx(), PB3: fw_core_tick(), PB0: receiver edges */
static double encoder_hz;
static double encoder_next;  /* cycle of the next PD2 toggle */
static int encoder_level = 1;
static const char *eeprom_path;
static volatile sig_atomic_t stop_requested;

static void log_event_at(char kind, uint64_t value, uint64_t cycle) {
  if (event_len == EVENT_CAPACITY) {
    events_dropped++;
    return;
  }
  events[event_len].kind = kind;
  events[event_len].cycle = cycle;
  events[event_len].value = value;
  event_len++;
}

static void log_event(char kind, uint64_t value) { log_event_at(kind, value, avr->cycle); }

/* ------------------------------------------------------------------ pins */

/* simavr 1.6 computes Timer1's compare points only when the timer is (re)configured, so in fast
 * PWM mode a new OCR1A/OCR1B never reaches the comparator. The hardware latches OCR1x at BOTTOM
 * (double buffering); the emulator does the same: a write marks the registers dirty, and one
 * cycle after the next BOTTOM it makes simavr reconfigure Timer1 by rewriting TCCR1B with the
 * clock off and on again (which restarts the count there, i.e. one cycle late at most). */
#define REG_TCCR1B 0x81u
#define REG_OCR1AL 0x88u
#define REG_OCR1BL 0x8Au
static avr_io_write_t ocr_write_orig[2];
static void *ocr_param_orig[2];
static int ocr_dirty;

static void on_ocr_write(struct avr_t *a, avr_io_addr_t addr, uint8_t v, void *param) {
  int i = (int)(intptr_t)param;
  ocr_write_orig[i](a, addr, v, ocr_param_orig[i]);
  ocr_dirty = 1;
}

static avr_cycle_count_t latch_ocr(struct avr_t *a, avr_cycle_count_t when, void *param) {
  (void)when;
  (void)param;
  uint8_t tccr1b = a->data[REG_TCCR1B];
  avr_io_write_t write = a->io[AVR_DATA_TO_IO(REG_TCCR1B)].w.c;
  void *wparam = a->io[AVR_DATA_TO_IO(REG_TCCR1B)].w.param;
  write(a, REG_TCCR1B, (uint8_t)(tccr1b & ~0x07u), wparam);
  write(a, REG_TCCR1B, tccr1b, wparam);
  return 0;
}

static void hook_ocr_writes(void) {
  const avr_io_addr_t regs[2] = {REG_OCR1AL, REG_OCR1BL};
  for (int i = 0; i < 2; i++) {
    unsigned io = AVR_DATA_TO_IO(regs[i]);
    ocr_write_orig[i] = avr->io[io].w.c;
    ocr_param_orig[i] = avr->io[io].w.param;
    avr->io[io].w.c = on_ocr_write;
    avr->io[io].w.param = (void *)(intptr_t)i;
  }
}

static void on_pulse_pin(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  int ch = (int)(intptr_t)param;
  pulse_pin_t *p = &pulse[ch];
  if (value && !p->high) {
    p->rise = avr->cycle;
    if (ocr_dirty) {
      ocr_dirty = 0;
      avr_cycle_timer_register(avr, 1, latch_ocr, NULL);
    }
  } else if (!value && p->high) {
    uint64_t width = avr->cycle - p->rise;
    /* logged when it moves by a timer count (8 cycles) or more, not on instruction jitter */
    if (width + 8u <= p->logged || width >= p->logged + 8u) {
      log_event(ch == 0 ? 'A' : 'B', width);
      p->logged = width;
    }
    p->width = width;
    p->count++;
  }
  p->high = value ? 1 : 0;
}

static void on_busy_pin(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  busy_pin_t *p = &busy[(intptr_t)param];
  if (value && !p->high) {
    p->rise = avr->cycle;
    p->count++;
  } else if (!value && p->high) {
    uint64_t width = avr->cycle - p->rise;
    p->total += width;
    if (width > p->max) {
      p->max = width;
    }
  }
  p->high = value ? 1 : 0;
}

static void on_led_pin(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)param;
  log_event('L', value ? 1u : 0u);
}

static avr_cycle_count_t encoder_toggle(struct avr_t *a, avr_cycle_count_t when, void *param) {
  (void)a;
  (void)when;
  (void)param;
  if (encoder_hz <= 0.0) {
    return 0;
  }
  encoder_level = !encoder_level;
  avr_raise_irq(pd2, (uint32_t)encoder_level);
  encoder_next += (double)F_CPU / (2.0 * encoder_hz);
  return (avr_cycle_count_t)encoder_next;
}

static void set_encoder(double hz) {
  avr_cycle_timer_cancel(avr, encoder_toggle, NULL);
  encoder_hz = hz;
  if (hz > 0.0) {
    encoder_next = (double)avr->cycle + (double)F_CPU / (2.0 * hz);
    avr_cycle_timer_register(avr, (avr_cycle_count_t)((double)F_CPU / (2.0 * hz)),
                             encoder_toggle, NULL);
  }
}

/* ------------------------------------------------------------------ RC receiver */

enum { RC_OFF, RC_TRAIN, RC_STOPPING, RC_NOISE };

typedef struct {
  int mode;
  int level;
  uint64_t width;     /* cycles, of the pulse in flight */
  uint64_t next_width;
  uint64_t period;    /* cycles */
  uint64_t rise;      /* cycle of the last rising edge */
  uint64_t fall;      /* cycle of the last falling edge */
  uint64_t gap_mean;  /* noise: mean cycles between edges */
  unsigned seed;
  int announce;       /* log W at this pulse's falling edge */
  int glitch;         /* a burst's state: the pin is level XOR glitch */
  unsigned burst_left;     /* the burst's edges still to come */
  unsigned burst_edges;    /* of how many */
  uint64_t burst_gap_min;  /* cycles */
  uint64_t burst_gap_span; /* gaps are min .. min + span cycles */
  unsigned burst_seed;
  avr_irq_t *pin;
} rc_channel_t;

static rc_channel_t rc[3];

/* The pin: what drives it (train, noise, idle level) with a burst's glitches on top. */
static void rc_drive(rc_channel_t *c) { avr_raise_irq(c->pin, (uint32_t)(c->level ^ c->glitch)); }

/* One edge of a burst: the line flips, whatever the train or the noise is doing. */
static avr_cycle_count_t rc_burst_edge(struct avr_t *a, avr_cycle_count_t when, void *param) {
  (void)a;
  rc_channel_t *c = &rc[(intptr_t)param];
  if (c->burst_left == 0u) {
    return 0;
  }
  if (c->burst_left == c->burst_edges) {
    log_event('N', (uint64_t)(intptr_t)param);
  }
  c->glitch = !c->glitch;
  rc_drive(c);
  c->burst_left--;
  if (c->burst_left == 0u) {
    log_event('E', (uint64_t)(intptr_t)param);
    return 0;
  }
  uint64_t gap = c->burst_gap_min;
  if (c->burst_gap_span > 0u) {
    gap += (uint64_t)rand_r(&c->burst_seed) % (c->burst_gap_span + 1u);
  }
  return when + (gap > 0u ? gap : 1u);
}

static avr_cycle_count_t rc_edge(struct avr_t *a, avr_cycle_count_t when, void *param) {
  (void)a;
  rc_channel_t *c = &rc[(intptr_t)param];
  if (c->mode == RC_NOISE) {
    c->level = !c->level;
    rc_drive(c);
    return when + 1u + (uint64_t)(rand_r(&c->seed) % (unsigned)(2u * c->gap_mean));
  }
  if (!c->level) { /* rising edge */
    if (c->mode != RC_TRAIN) {
      c->mode = RC_OFF;
      return 0;
    }
    c->level = 1;
    rc_drive(c);
    c->rise = when;
    c->announce = c->next_width != c->width;
    c->width = c->next_width;
    return when + c->width;
  }
  c->level = 0; /* falling edge */
  c->fall = when;
  rc_drive(c);
  if (c->announce) {
    log_event('W', (uint64_t)(intptr_t)param);
    c->announce = 0;
  }
  if (c->mode == RC_STOPPING) {
    log_event('O', (uint64_t)(intptr_t)param);
    c->mode = RC_OFF;
    return 0;
  }
  return c->rise + c->period;
}

static void rc_command(char *args) {
  int ch = atoi(args);
  char *rest = strchr(args, ' ');
  if (ch < 0 || ch > 2 || rest == NULL) {
    printf("error usage: rc <0-2> <width_us> <period_us> <phase_us> | off | noise <gap_us> <seed>"
           " | burst <edges> <gap_min_us> <gap_max_us> <seed> <delay_us>\n");
    return;
  }
  rest++;
  rc_channel_t *c = &rc[ch];
  void *param = (void *)(intptr_t)ch;
  if (strncmp(rest, "off", 3) == 0) {
    if (c->mode == RC_TRAIN && c->level) {
      c->mode = RC_STOPPING; /* the pulse in flight ends normally */
    } else {
      avr_cycle_timer_cancel(avr, rc_edge, param);
      if (c->mode == RC_TRAIN) {
        log_event_at('O', (uint64_t)ch, c->fall); /* the last pulse ended then */
      }
      c->mode = RC_OFF;
      c->level = 0;
      rc_drive(c);
    }
  } else if (strncmp(rest, "burst ", 6) == 0) {
    unsigned edges = 0, seed = 0;
    double gap_min_us = 0, gap_max_us = 0, delay_us = 0;
    int anchor = -1;
    int n = sscanf(rest + 6, "%u %lf %lf %u %lf %d", &edges, &gap_min_us, &gap_max_us, &seed,
                   &delay_us, &anchor);
    if (n < 5 || gap_max_us < gap_min_us || gap_min_us < 0 || anchor < -1 || anchor > 2 ||
        (anchor < 0 && delay_us < 0) || (anchor >= 0 && rc[anchor].mode != RC_TRAIN)) {
      printf("error usage: rc <0-2> burst <edges> <gap_min_us> <gap_max_us> <seed> <delay_us>"
             " [<train 0-2>]\n");
      return;
    }
    /* From now, or from the anchor train's next falling edge (the delay may then be < 0). */
    int64_t start = (int64_t)avr->cycle + 1;
    if (anchor >= 0) {
      const rc_channel_t *t = &rc[anchor];
      start = t->level ? (int64_t)(t->rise + t->width)
                       : (int64_t)(t->rise + t->period + t->next_width);
    }
    start += (int64_t)(delay_us * (F_CPU / 1000000u));
    while (anchor >= 0 && start <= (int64_t)avr->cycle) {
      start += (int64_t)rc[anchor].period;
    }
    avr_cycle_timer_cancel(avr, rc_burst_edge, param);
    if (c->glitch) { /* a burst cut short: the line back to what drives it */
      c->glitch = 0;
      rc_drive(c);
    }
    c->burst_left = edges + (edges & 1u); /* even: the line ends where it would have been */
    c->burst_edges = c->burst_left;
    c->burst_gap_min = (uint64_t)(gap_min_us * (F_CPU / 1000000u) + 0.5);
    c->burst_gap_span = (uint64_t)(gap_max_us * (F_CPU / 1000000u) + 0.5) - c->burst_gap_min;
    c->burst_seed = seed;
    if (c->burst_left > 0u) {
      avr_cycle_timer_register(avr, (avr_cycle_count_t)(start - (int64_t)avr->cycle),
                               rc_burst_edge, param);
    }
  } else if (strncmp(rest, "noise ", 6) == 0) {
    double gap_us = 0;
    unsigned seed = 0;
    sscanf(rest + 6, "%lf %u", &gap_us, &seed);
    avr_cycle_timer_cancel(avr, rc_edge, param);
    c->mode = RC_NOISE;
    c->seed = seed;
    c->gap_mean = (uint64_t)(gap_us * (F_CPU / 1000000u));
    if (c->gap_mean < 1u) {
      c->gap_mean = 1u;
    }
    avr_cycle_timer_register(avr, 1, rc_edge, param);
  } else {
    double width_us = 0, period_us = 0, phase_us = 0;
    sscanf(rest, "%lf %lf %lf", &width_us, &period_us, &phase_us);
    c->next_width = (uint64_t)(width_us * (F_CPU / 1000000u) + 0.5);
    c->period = (uint64_t)(period_us * (F_CPU / 1000000u) + 0.5);
    if (c->mode != RC_TRAIN && c->mode != RC_STOPPING) {
      avr_cycle_timer_cancel(avr, rc_edge, param);
      if (c->level) {
        c->level = 0;
        rc_drive(c);
      }
      c->width = 0;
      avr_cycle_timer_register(avr, 1u + (avr_cycle_count_t)(phase_us * (F_CPU / 1000000u)),
                               rc_edge, param);
    }
    c->mode = RC_TRAIN;
  }
  printf("ok\n");
}

/* ------------------------------------------------------------------ UART <-> pty */

static void on_uart_byte_out(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)param;
  uint8_t byte = (uint8_t)value;
  /* Nobody reading, or the pty buffer full: the byte is lost, as on a real UART. */
  if (write(pty_master, &byte, 1) < 0 && errno != EAGAIN && errno != EIO) {
    perror("carrt_avr_emu: pty write");
  }
}

static void on_uart_xon(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)value;
  (void)param;
  uart_xon = 1;
}

static void on_uart_xoff(struct avr_irq_t *irq, uint32_t value, void *param) {
  (void)irq;
  (void)value;
  (void)param;
  uart_xon = 0;
}

static void service_pty(void) {
  if (host_len < HOST_QUEUE) {
    ssize_t n = read(pty_master, host_queue + host_len, HOST_QUEUE - host_len);
    if (n > 0) {
      host_len += (size_t)n;
    }
  }
  size_t sent = 0;
  while (sent < host_len && uart_xon) {
    uint8_t byte = host_queue[sent++];
    avr_raise_irq(uart_in, byte);
    if (byte == 0u) {
      log_event('F', 0);
    }
  }
  memmove(host_queue, host_queue + sent, host_len - sent);
  host_len -= sent;
}

/* ------------------------------------------------------------------ EEPROM */

static void eeprom_get(uint8_t *out) {
  avr_eeprom_desc_t d = {.ee = NULL, .offset = 0, .size = EEPROM_SIZE};
  avr_ioctl(avr, AVR_IOCTL_EEPROM_GET, &d);
  memcpy(out, d.ee, EEPROM_SIZE);
}

static void eeprom_set(const uint8_t *in) {
  avr_eeprom_desc_t d = {.ee = (uint8_t *)in, .offset = 0, .size = EEPROM_SIZE};
  avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d);
}

static void eeprom_save(void) {
  if (eeprom_path == NULL) {
    return;
  }
  uint8_t data[EEPROM_SIZE];
  eeprom_get(data);
  FILE *f = fopen(eeprom_path, "wb");
  if (f == NULL || fwrite(data, 1, EEPROM_SIZE, f) != EEPROM_SIZE) {
    fprintf(stderr, "carrt_avr_emu: cannot write EEPROM file %s\n", eeprom_path);
  }
  if (f != NULL) {
    fclose(f);
  }
}

/* simavr's reset cancels every cycle timer, and with them what drives the pins from outside the
 * chip (a receiver, noise, a burst, the encoder), which a reset of the chip would not stop:
 * each one goes on from where it was (an edge that fell due meanwhile comes at once). */
static void restart_pin_drivers(void) {
  for (int ch = 0; ch < 3; ch++) {
    rc_channel_t *c = &rc[ch];
    void *param = (void *)(intptr_t)ch;
    rc_drive(c);
    uint64_t due = 0;
    if (c->mode == RC_NOISE) {
      due = avr->cycle + 1u;
    } else if (c->mode == RC_TRAIN || c->mode == RC_STOPPING) {
      due = c->level ? c->rise + c->width : c->rise + c->period;
    }
    if (due != 0u) {
      avr_cycle_timer_register(avr, due > avr->cycle ? due - avr->cycle : 1u, rc_edge, param);
    }
    if (c->burst_left > 0u) {
      avr_cycle_timer_register(avr, 1u, rc_burst_edge, param);
    }
  }
  avr_raise_irq(pd2, (uint32_t)encoder_level);
  set_encoder(encoder_hz);
}

/* A reset, with the reset flag in MCUSR that the cause sets on the chip: simavr's own reset
 * clears the I/O registers and sets none (it sets PORF once, at start: the power-on). */
static int emulated_reset(const char *cause) {
  avr_regbit_t flag;
  uint64_t code;
  if (cause[0] == '\0' || strcmp(cause, "external") == 0) {
    flag = avr->reset_flags.extrf;
    code = 2;
  } else if (strcmp(cause, "watchdog") == 0) {
    flag = avr->reset_flags.wdrf;
    code = 4;
  } else if (strcmp(cause, "brown-out") == 0) {
    flag = avr->reset_flags.borf;
    code = 3;
  } else if (strcmp(cause, "power-on") == 0) {
    flag = avr->reset_flags.porf;
    code = 1;
  } else {
    return -1;
  }
  if (flag.reg == 0) {
    return -1; /* this simavr does not know the chip's reset flags */
  }
  uint8_t data[EEPROM_SIZE];
  eeprom_get(data); /* simavr's reset would leave EEPROM as it was, but do not rely on it */
  avr_reset(avr);
  eeprom_set(data);
  avr_regbit_set(avr, flag);
  restart_pin_drivers();
  memset(pulse, 0, sizeof pulse);
  log_event('R', code);
  return 0;
}

/* ------------------------------------------------------------------ control channel */

static double wall_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + (double)ts.tv_nsec * 1e-9;
}

static double pace_wall0;
static uint64_t pace_cycle0;
static double lag_s;

static void reply_events(void) {
  printf("events %llu", (unsigned long long)events_dropped);
  for (size_t i = 0; i < event_len; i++) {
    printf(" %c%llu@%llu", events[i].kind, (unsigned long long)events[i].value,
           (unsigned long long)events[i].cycle);
  }
  printf("\n");
  event_len = 0;
  events_dropped = 0;
}

static void handle_command(char *line) {
  char *nl = strchr(line, '\n');
  if (nl != NULL) {
    *nl = '\0';
  }
  if (strcmp(line, "time") == 0) {
    printf("time %llu %.0f\n", (unsigned long long)avr->cycle, lag_s * 1e6);
  } else if (strcmp(line, "pulses") == 0) {
    printf("pulses %llu %llu %llu %llu\n", (unsigned long long)pulse[0].width,
           (unsigned long long)pulse[0].count, (unsigned long long)pulse[1].width,
           (unsigned long long)pulse[1].count);
  } else if (strcmp(line, "busy") == 0) {
    printf("busy");
    for (int i = 0; i < 3; i++) {
      printf(" %llu %llu %llu", (unsigned long long)busy[i].total,
             (unsigned long long)busy[i].count, (unsigned long long)busy[i].max);
    }
    printf("\n");
    memset(busy, 0, sizeof busy); /* a pin high right now starts counting at its next rise */
  } else if (strcmp(line, "events") == 0) {
    reply_events();
  } else if (strncmp(line, "encoder ", 8) == 0) {
    set_encoder(atof(line + 8));
    printf("ok\n");
  } else if (strncmp(line, "rc ", 3) == 0) {
    rc_command(line + 3);
  } else if (strcmp(line, "reset") == 0 || strncmp(line, "reset ", 6) == 0) {
    if (emulated_reset(line[5] == ' ' ? line + 6 : "") == 0) {
      printf("ok\n");
    } else {
      printf("error usage: reset [external|watchdog|brown-out|power-on]\n");
    }
  } else if (strcmp(line, "eeprom") == 0) {
    uint8_t data[EEPROM_SIZE];
    eeprom_get(data);
    printf("eeprom ");
    for (unsigned i = 0; i < 64u; i++) {
      printf("%02x", data[i]);
    }
    printf("\n");
  } else if (strcmp(line, "quit") == 0) {
    stop_requested = 1;
    printf("ok\n");
  } else {
    printf("error unknown command: %s\n", line);
  }
  fflush(stdout);
}

static char control_buf[256];
static size_t control_len;

static void service_control(void) {
  struct pollfd pfd = {.fd = STDIN_FILENO, .events = POLLIN};
  while (poll(&pfd, 1, 0) > 0) {
    ssize_t n = read(STDIN_FILENO, control_buf + control_len, sizeof control_buf - 1 - control_len);
    if (n <= 0) {
      stop_requested = 1; /* the launcher went away */
      return;
    }
    control_len += (size_t)n;
    control_buf[control_len] = '\0';
    char *nl;
    while ((nl = strchr(control_buf, '\n')) != NULL) {
      *nl = '\0';
      handle_command(control_buf);
      size_t used = (size_t)(nl - control_buf) + 1u;
      memmove(control_buf, nl + 1, control_len - used + 1u);
      control_len -= used;
    }
    if (control_len == sizeof control_buf - 1u) {
      control_len = 0; /* an over-long line: dropped */
    }
  }
}

/* Emulated time runs at wall speed: sleep when ahead; when far behind (a loaded machine), let
 * the debt go rather than run fast, which would stretch the host's 20 ms between commands. */
static void pace(void) {
  double target = pace_wall0 + (double)(avr->cycle - pace_cycle0) / (double)F_CPU;
  double now = wall_s();
  if (target > now + 0.0002) {
    struct timespec ts = {.tv_sec = 0, .tv_nsec = (long)((target - now) * 1e9)};
    nanosleep(&ts, NULL);
    lag_s = 0.0;
  } else {
    lag_s = now - target;
    if (now - target > (double)MAX_LAG_CYCLES / (double)F_CPU) {
      pace_wall0 = now;
      pace_cycle0 = avr->cycle;
    }
  }
}

static void on_signal(int sig) {
  (void)sig;
  stop_requested = 1;
}

/* ------------------------------------------------------------------ setup */

static void connect_pin(char port, int pin, avr_irq_notify_t fn, void *param) {
  avr_irq_t *irq = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ(port), pin);
  avr_irq_register_notify(irq, fn, param);
}

static int open_pty(const char *link_path) {
  int slave;
  char name[256];
  struct termios tio;
  if (openpty(&pty_master, &slave, name, NULL, NULL) != 0) {
    perror("carrt_avr_emu: openpty");
    return -1;
  }
  tcgetattr(slave, &tio);
  cfmakeraw(&tio);
  tcsetattr(slave, TCSANOW, &tio);
  /* The slave stays open here, so the master never hangs up between host sessions. */
  fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
  if (link_path != NULL) {
    char tmp[4096];
    snprintf(tmp, sizeof tmp, "%s.tmp", link_path);
    unlink(tmp);
    if (symlink(name, tmp) != 0 || rename(tmp, link_path) != 0) {
      fprintf(stderr, "carrt_avr_emu: cannot link %s: %s\n", link_path, strerror(errno));
      return -1;
    }
    printf("ready %s\n", link_path);
  } else {
    printf("ready %s\n", name);
  }
  fflush(stdout);
  return 0;
}

int main(int argc, char **argv) {
  const char *elf_path = NULL;
  const char *link_path = NULL;
  for (int i = 1; i < argc; i++) {
    if (strcmp(argv[i], "--eeprom") == 0 && i + 1 < argc) {
      eeprom_path = argv[++i];
    } else if (strcmp(argv[i], "--link") == 0 && i + 1 < argc) {
      link_path = argv[++i];
    } else if (argv[i][0] != '-' && elf_path == NULL) {
      elf_path = argv[i];
    } else {
      fprintf(stderr, "usage: carrt_avr_emu FIRMWARE.elf [--eeprom FILE] [--link PATH]\n");
      return 2;
    }
  }
  if (elf_path == NULL) {
    fprintf(stderr, "usage: carrt_avr_emu FIRMWARE.elf [--eeprom FILE] [--link PATH]\n");
    return 2;
  }
  if (access(elf_path, R_OK) != 0) {
    fprintf(stderr, "carrt_avr_emu: cannot read firmware %s\n", elf_path);
    return 2;
  }
  elf_firmware_t fw;
  memset(&fw, 0, sizeof fw);
  if (elf_read_firmware(elf_path, &fw) != 0) {
    fprintf(stderr, "carrt_avr_emu: %s is not an AVR ELF\n", elf_path);
    return 2;
  }
  avr = avr_make_mcu_by_name("atmega328p");
  if (avr == NULL || avr_init(avr) != 0) {
    fprintf(stderr, "carrt_avr_emu: simavr has no atmega328p\n");
    return 2;
  }
  avr->log = LOG_ERROR;
  avr_load_firmware(avr, &fw);
  avr->frequency = F_CPU;

  if (eeprom_path != NULL) {
    FILE *f = fopen(eeprom_path, "rb");
    if (f != NULL) {
      uint8_t data[EEPROM_SIZE];
      if (fread(data, 1, EEPROM_SIZE, f) == EEPROM_SIZE) {
        eeprom_set(data);
      }
      fclose(f);
    }
  }

  uint32_t flags = 0;
  avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
  flags &= ~(uint32_t)(AVR_UART_FLAG_STDIO | AVR_UART_FLAG_POLL_SLEEP);
  avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
  uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                          on_uart_byte_out, NULL);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XON),
                          on_uart_xon, NULL);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF),
                          on_uart_xoff, NULL);
  /* The pulses are taken from Timer1's compare-output units (OC1A/OC1B), which drive PB1/PB2
   * while COM1x1 is set. Not from the port pins: simavr 1.6 lets any later PORTB write (the
   * LED, the busy pin) overwrite the pin level, which the hardware's OC1x override prevents. */
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_TIMER_GETIRQ('1'), TIMER_IRQ_OUT_COMP + 0),
                          on_pulse_pin, (void *)(intptr_t)0);
  avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_TIMER_GETIRQ('1'), TIMER_IRQ_OUT_COMP + 1),
                          on_pulse_pin, (void *)(intptr_t)1);
  connect_pin('B', 4, on_busy_pin, (void *)(intptr_t)0);
  connect_pin('B', 3, on_busy_pin, (void *)(intptr_t)1);
  connect_pin('B', 0, on_busy_pin, (void *)(intptr_t)2);
  connect_pin('B', 5, on_led_pin, NULL);
  hook_ocr_writes();
  pd2 = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 2);
  avr_raise_irq(pd2, 1); /* the encoder line idles high, like the pull-up */
  for (int i = 0; i < 3; i++) {
    rc[i].pin = avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('D'), 4 + i);
    avr_raise_irq(rc[i].pin, 1); /* no receiver: the pull-ups hold the lines high */
    rc[i].level = 1;
    rc[i].mode = RC_OFF;
  }

  signal(SIGTERM, on_signal);
  signal(SIGINT, on_signal);
  signal(SIGPIPE, SIG_IGN);
  if (open_pty(link_path) != 0) {
    return 2;
  }
  pace_wall0 = wall_s();
  pace_cycle0 = avr->cycle;
  while (!stop_requested) {
    uint64_t slice_end = avr->cycle + SLICE_CYCLES;
    while (avr->cycle < slice_end) {
      int state = avr_run(avr);
      if (state == cpu_Done || state == cpu_Crashed) {
        fprintf(stderr, "carrt_avr_emu: the AVR stopped (state %d) at pc 0x%04x\n", state,
                avr->pc);
        eeprom_save();
        return 1;
      }
    }
    service_pty();
    service_control();
    pace();
  }
  eeprom_save();
  if (link_path != NULL) {
    unlink(link_path);
  }
  return 0;
}
