// mocaprig sync box — reference firmware, protocol version 1 (docs/syncbox-protocol.md).
//
// Board: Arduino Uno or Nano (ATmega328P, 16 MHz). Build with the Arduino IDE or
//   arduino-cli compile --fqbn arduino:avr:uno firmware/syncbox
//   arduino-cli upload  --fqbn arduino:avr:uno -p /dev/ttyACM0 firmware/syncbox
// or, with the Debian/Ubuntu packages gcc-avr binutils-avr avr-libc arduino-core-avr,
//   make firmware   (firmware/syncbox/build.py: build/firmware/{uno,nano}/syncbox.hex)
//   avrdude -p m328p -c arduino -P /dev/ttyACM0 -b 115200 -U flash:w:build/firmware/uno/syncbox.hex:i
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
//               start of a run. Flipped by `sbi PINB, 2`, the very first instruction of both
//               pulse interrupts (naked entry stubs, below), before any register is saved: 9
//               cycles (0.56 us at 16 MHz) from the interrupt request to the flip, counted in this
//               firmware's disassembly (firmware/syncbox/build.py --latency). So D10 flips
//               ~0.6-0.9 us after the D2 edge in LISTEN, up to ~9.6 us when the edge comes
//               while a millis/serial interrupt runs; in GENERATE within one Timer1 tick of the
//               D9 rising edge (the overflow flag is set at TOP, one tick before D9 rises at
//               BOTTOM, or with it: the datasheet can be read both ways). Table, and what is
//               measured and what assumed: docs/syncbox-protocol.md, "Latency". Verify with a
//               scope (D2 or D9 against D10).
//   D13 (LED)   on while a run is active.
//
// Timing: PULSES' <t_us> is micros() captured in the interrupt of each pulse, ~4 us after the
// D10 flip (4 us resolution on a 16 MHz board; u32, wraps every 71.6 min). In GENERATE mode the
// Timer1 overflow interrupt comes at TOP, at most one timer tick before the rising edge (the
// output is set at BOTTOM, right after TOP); the first pulse rises one period after START.
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

#if !defined(__AVR_ATmega328P__)
#error "the pulse interrupt stubs below are written for the ATmega328P (Uno/Nano)"
#endif

// The work shared by both pulse sources. Entered by a jmp from the two entry stubs below, never
// called: a signal handler, so it saves what it uses and returns from the interrupt (reti).
// Its name starts with "__vector" only because avr-gcc warns about a signal handler named
// otherwise.
extern "C" void __vector_syncbox_pulse(void) __attribute__((signal, used, externally_visible));
void __vector_syncbox_pulse(void) {
  g_count++;
  g_last_us = micros();
}

// The two pulse vectors: flip D10 first, then continue in the shared handler. Writing 1 to a
// PINx bit flips that PORTx bit (ATmega328P); `sbi` does it in 2 cycles and touches no register
// and no status flag, so nothing needs saving before it (ISR_NAKED: no prologue). The two asm
// strings differ (the comment), so the compiler's identical code folding cannot merge the
// stubs: with ordinary ISRs of identical bodies, -flto folded one into a wrapper that saved
// every register and called the other (the toggle ~4.8 us late, and a nested reti).
// tests/firmware/ checks in the built ELF that each vector jumps to its own stub that starts
// with this sbi.
ISR(TIMER1_OVF_vect, ISR_NAKED) {
  asm volatile(
      "sbi %0, %1 ; TIMER1_OVF: flip D10\n\t"
      "jmp __vector_syncbox_pulse" ::"I"(_SFR_IO_ADDR(PINB)),
      "I"(PINB2));
}

// INT0 directly rather than attachInterrupt(): no call through the core's handler table.
ISR(INT0_vect, ISR_NAKED) {
  asm volatile(
      "sbi %0, %1 ; INT0: flip D10\n\t"
      "jmp __vector_syncbox_pulse" ::"I"(_SFR_IO_ADDR(PINB)),
      "I"(PINB2));
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

// D9 low, the OC1A output latch included. Timer1 drives D9 from that latch, which keeps its
// level when the timer stops: after a STOP during a pulse it stays high, and the next START
// would emit a partial pulse the moment the output is reconnected, before the first count.
// Forcing a compare match (FOC1A, non-PWM mode only) with "clear on match" clears the latch.
// Call with the Timer1 clock stopped.
static void force_out_low() {
  TCCR1A = _BV(COM1A1);  // normal mode, clear OC1A on compare match
  TCCR1C = _BV(FOC1A);   // forced compare match: the latch goes low
  TCCR1A = 0;            // OC1A disconnected: D9 follows PORTB1
  PORTB &= ~_BV(PORTB1);
}

// Timer1 fast PWM mode 14: period = (ICR1 + 1) ticks, high time = (OCR1A + 1) ticks. The
// counter starts at 0 with D9 low and the first pulse rises one full period after START (the
// overflow at TOP counts it one tick earlier).
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
    TCCR1B = 0;  // clock stopped
    force_out_low();
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
  TIMSK1 = 0;
  force_out_low();  // a pulse in progress is cut short
  EIMSK &= ~_BV(INT0);
  interrupts();
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
