// mocaprig sync box — reference firmware, protocol version 1 (docs/syncbox-protocol.md).
//
// Board: Arduino Uno or Nano (ATmega328P, 16 MHz). Build with the Arduino IDE or
//   arduino-cli compile --fqbn arduino:avr:uno firmware/syncbox
//   arduino-cli upload  --fqbn arduino:avr:uno -p /dev/ttyACM0 firmware/syncbox
//
// Pins (wiring: docs/wiring.md):
//   D9  (OC1A)  OUT: the generated pulse train, 5 V logic, driven by Timer1 in hardware
//               (fast PWM, TOP = ICR1), so period and width do not depend on the main loop.
//               Idle low. Level-shift to 1.8 V before a D415 pin 5.
//   D2  (INT0)  IN: pulses to count in LISTEN mode (rising edges), e.g. the D415 master's sync
//               output through the 1.8 V -> 5 V level shifter. Has no pull-up; tie it to GND
//               through 100 kOhm if left open.
//   D10 (PB2)   TOGGLE OUT (feature "toggle"): flips at every pulse of a run (each counted edge in
//               LISTEN, each generated pulse in GENERATE), so each of its edges, rising or
//               falling, is one pulse: a square wave at half the frame rate that a Vicon analog
//               input resolves at any rate (docs/wiring.md section 7). Low when idle and at the
//               start of a run. Flipped by a write to PINB as the first instruction of the pulse
//               interrupt: ~1-2 us after the D2 edge in LISTEN (the interrupt response plus the
//               ISR prologue; up to ~5 us more when the millis/serial interrupts are running);
//               in GENERATE the Timer1 overflow fires one timer tick before D9 rises, so D10
//               leads D9 by about one tick minus that latency (~2-3 us at 30 Hz). Verify with a
//               scope (D2 or D9 against D10).
//   D13 (LED)   on while a run is active.
//
// Timing: PULSES' <t_us> is micros() captured in the interrupt of each pulse (4 us resolution
// on a 16 MHz board; u32, wraps every 71.6 min). In GENERATE mode the Timer1 overflow interrupt
// fires one timer tick before the rising edge (the output is set at BOTTOM, right after TOP).
// The rate comes from the board's crystal (or ceramic resonator on many clones: up to
// +-0.5 %, check the real rate with a scope or frequency counter).

#include <Arduino.h>

#define PROTOCOL_VERSION 1
#if defined(ARDUINO_AVR_NANO)
#define BOARD_NAME "nano"
#elif defined(ARDUINO_AVR_UNO)
#define BOARD_NAME "uno"
#else
#define BOARD_NAME "avr"
#endif

static const uint8_t PIN_OUT = 9;   // OC1A
static const uint8_t PIN_IN = 2;    // INT0
static const uint8_t PIN_TOGGLE = 10;  // PB2
static const uint8_t PIN_LED = 13;
static const uint8_t LINE_MAX = 64;

enum Mode : uint8_t { MODE_IDLE, MODE_GENERATE, MODE_LISTEN };

static volatile uint32_t g_count = 0;     // pulses of the current run
static volatile uint32_t g_last_us = 0;   // micros() at the last pulse
static Mode g_mode = MODE_IDLE;
static uint16_t g_hz = 0;
static uint32_t g_width_us = 0;
static uint16_t g_report_ms = 1000;
static uint32_t g_last_report_ms = 0;

static char g_line[LINE_MAX + 1];
static uint8_t g_len = 0;
static bool g_overflow = false;

// -- pulse sources ---------------------------------------------------------------------------

// Writing 1 to a PINx bit flips that PORTx bit (ATmega328P): one instruction, done first.
#define TOGGLE_OUT() (PINB = _BV(PINB2))

ISR(TIMER1_OVF_vect) {
  TOGGLE_OUT();
  g_count++;
  g_last_us = micros();
}

// INT0 directly rather than attachInterrupt(): no call through the core's handler table, so
// the toggle comes sooner and with less jitter.
ISR(INT0_vect) {
  TOGGLE_OUT();
  g_count++;
  g_last_us = micros();
}

static void start_listening() {
  noInterrupts();
  EICRA = (EICRA & ~(_BV(ISC01) | _BV(ISC00))) | _BV(ISC01) | _BV(ISC00);  // rising edge
  EIFR = _BV(INTF0);                                                      // no stale edge
  EIMSK |= _BV(INT0);
  interrupts();
}

static void read_counter(uint32_t *count, uint32_t *t_us) {
  noInterrupts();
  *count = g_count;
  *t_us = g_last_us;
  interrupts();
}

// Timer1 fast PWM mode 14: period = (ICR1 + 1) ticks, high time = (OCR1A + 1) ticks.
static bool start_generator(uint16_t hz, uint32_t width_us) {
  static const uint16_t prescalers[] = {1, 8, 64, 256, 1024};
  static const uint8_t cs_bits[] = {_BV(CS10), _BV(CS11), _BV(CS11) | _BV(CS10), _BV(CS12),
                                    _BV(CS12) | _BV(CS10)};
  for (uint8_t i = 0; i < 5; i++) {
    uint32_t tick_hz = F_CPU / prescalers[i];
    uint32_t period = (tick_hz + hz / 2) / hz;  // ticks, rounded
    if (period > 65536UL) continue;
    // round the width up: a D415 slave needs at least the requested width (>= 100 us)
    uint32_t width = (uint32_t)(((uint64_t)width_us * tick_hz + 999999UL) / 1000000UL);
    if (width < 1 || width >= period) return false;
    noInterrupts();
    TCCR1A = 0;
    TCCR1B = 0;
    TCNT1 = 0;
    PORTB &= ~_BV(PORTB2);  // the toggle output starts low
    ICR1 = (uint16_t)(period - 1);
    OCR1A = (uint16_t)(width - 1);
    g_count = 0;
    g_last_us = micros();
    TIFR1 = _BV(TOV1);                                   // no stale overflow
    TIMSK1 = _BV(TOIE1);                                 // count at every TOP
    TCCR1A = _BV(COM1A1) | _BV(WGM11);                   // non-inverting OC1A, mode 14
    TCCR1B = _BV(WGM13) | _BV(WGM12) | cs_bits[i];       // start the clock
    interrupts();
    return true;
  }
  return false;  // below 1 Hz at the largest prescaler (not reachable for hz >= 1)
}

static void stop_sources() {
  noInterrupts();
  TCCR1B = 0;
  TCCR1A = 0;
  TIMSK1 = 0;
  interrupts();
  EIMSK &= ~_BV(INT0);
  digitalWrite(PIN_OUT, LOW);
  digitalWrite(PIN_TOGGLE, LOW);
  digitalWrite(PIN_LED, LOW);
}

// -- protocol ----------------------------------------------------------------------------------

static void send_banner() {
  Serial.print(F("MOCAPRIG-SYNCBOX "));
  Serial.print(PROTOCOL_VERSION);
  Serial.print(' ');
  Serial.print(F(BOARD_NAME));
  Serial.println(F(" toggle"));  // feature tokens (docs/syncbox-protocol.md)
}

static void send_err(uint8_t code, const __FlashStringHelper *text) {
  Serial.print(F("ERR "));
  Serial.print(code);
  Serial.print(' ');
  Serial.println(text);
}

// Parse an unsigned decimal token (1..9 digits); advance *p past it and one space.
static bool parse_uint(char **p, uint32_t *out) {
  char *s = *p;
  uint8_t digits = 0;
  uint32_t v = 0;
  while (*s >= '0' && *s <= '9') {
    if (++digits > 9) return false;
    v = v * 10 + (uint32_t)(*s - '0');
    s++;
  }
  if (digits == 0 || (*s != '\0' && *s != ' ')) return false;
  if (*s == ' ') s++;
  *p = s;
  *out = v;
  return true;
}

static void handle_line(char *line) {
  char *args = strchr(line, ' ');
  if (args != NULL) *args++ = '\0';
  else args = line + strlen(line);  // empty argument string

  if (strcmp(line, "HELLO") == 0) {
    if (*args) return send_err(2, F("bad argument"));
    send_banner();
  } else if (strcmp(line, "START") == 0) {
    uint32_t hz, width;
    if (!parse_uint(&args, &hz) || !parse_uint(&args, &width) || *args) {
      return send_err(2, F("bad argument"));
    }
    if (hz < 1 || hz > 1000 || width < 10 || width > 500000UL / hz) {
      return send_err(2, F("bad argument"));
    }
    if (g_mode != MODE_IDLE) return send_err(3, F("busy"));
    if (!start_generator((uint16_t)hz, width)) return send_err(2, F("bad argument"));
    g_mode = MODE_GENERATE;
    g_hz = (uint16_t)hz;
    g_width_us = width;
    g_last_report_ms = millis();
    digitalWrite(PIN_LED, HIGH);
    Serial.print(F("OK START "));
    Serial.print(hz);
    Serial.print(' ');
    Serial.println(width);
  } else if (strcmp(line, "LISTEN") == 0) {
    if (*args) return send_err(2, F("bad argument"));
    if (g_mode != MODE_IDLE) return send_err(3, F("busy"));
    noInterrupts();
    g_count = 0;
    g_last_us = micros();
    PORTB &= ~_BV(PORTB2);  // the toggle output starts low
    interrupts();
    start_listening();
    g_mode = MODE_LISTEN;
    g_last_report_ms = millis();
    digitalWrite(PIN_LED, HIGH);
    Serial.println(F("OK LISTEN"));
  } else if (strcmp(line, "STOP") == 0) {
    if (*args) return send_err(2, F("bad argument"));
    uint32_t count = 0, t_us;
    if (g_mode != MODE_IDLE) {
      stop_sources();
      read_counter(&count, &t_us);
    }
    g_mode = MODE_IDLE;
    g_hz = 0;
    g_width_us = 0;
    Serial.print(F("OK STOP "));
    Serial.println(count);
  } else if (strcmp(line, "STATUS") == 0) {
    if (*args) return send_err(2, F("bad argument"));
    uint32_t count = 0, t_us;
    if (g_mode != MODE_IDLE) read_counter(&count, &t_us);
    Serial.print(F("STATUS "));
    Serial.print(g_mode == MODE_IDLE ? F("IDLE") : g_mode == MODE_GENERATE ? F("GENERATE") : F("LISTEN"));
    Serial.print(' ');
    Serial.print(g_hz);
    Serial.print(' ');
    Serial.print(g_width_us);
    Serial.print(' ');
    Serial.print(count);
    Serial.print(' ');
    Serial.println(micros());
  } else if (strcmp(line, "REPORT") == 0) {
    uint32_t ms;
    if (!parse_uint(&args, &ms) || *args || (ms != 0 && (ms < 100 || ms > 60000))) {
      return send_err(2, F("bad argument"));
    }
    g_report_ms = (uint16_t)ms;
    g_last_report_ms = millis();
    Serial.print(F("OK REPORT "));
    Serial.println(ms);
  } else {
    send_err(1, F("unknown command"));
  }
}

static void poll_serial() {
  while (Serial.available() > 0) {
    char c = (char)Serial.read();
    if (c == '\r') continue;
    if (c == '\n') {
      if (g_overflow) {
        send_err(4, F("line too long"));
      } else if (g_len > 0) {
        g_line[g_len] = '\0';
        handle_line(g_line);
      }
      g_len = 0;
      g_overflow = false;
    } else if (g_len < LINE_MAX) {
      g_line[g_len++] = c;
    } else {
      g_overflow = true;  // discard the rest of the line
    }
  }
}

static void maybe_report() {
  if (g_mode == MODE_IDLE || g_report_ms == 0) return;
  uint32_t now = millis();
  if (now - g_last_report_ms < g_report_ms) return;
  g_last_report_ms += g_report_ms;
  if (now - g_last_report_ms >= g_report_ms) g_last_report_ms = now;  // fell behind: resync
  uint32_t count, t_us;
  read_counter(&count, &t_us);
  if (count == 0) t_us = micros();
  Serial.print(F("PULSES "));
  Serial.print(count);
  Serial.print(' ');
  Serial.println(t_us);
}

void setup() {
  pinMode(PIN_OUT, OUTPUT);
  digitalWrite(PIN_OUT, LOW);
  pinMode(PIN_IN, INPUT);
  pinMode(PIN_TOGGLE, OUTPUT);
  digitalWrite(PIN_TOGGLE, LOW);
  pinMode(PIN_LED, OUTPUT);
  digitalWrite(PIN_LED, LOW);
  Serial.begin(115200);
  send_banner();  // once at boot; the host also asks with HELLO
}

void loop() {
  poll_serial();
  maybe_report();
}
