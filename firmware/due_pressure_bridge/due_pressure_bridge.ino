// Arduino Due pressure bridge: six proportional regulators (Camozzi K8P) driven from a host.
//
// Host protocol, clamping, watchdog and state streaming live in bridge_core.h (plain C++,
// tested on the host against test/data/protocol_vectors.json). This file only maps Pa to
// output counts and input counts to Pa. Wire format: docs/protocol.md.
//
// Electrical: the K8P takes a 0-10 V set-point and returns 0-10 V feedback. The Due's DACs
// span 0.55-2.75 V (1/6..5/6 of 3.3 V) and its PWM pins 0-3.3 V, so each output goes through
// an op-amp stage (and, for PWM, an RC low-pass, 10 kOhm / 1 uF, ~16 Hz corner, well above
// the regulators' bandwidth but 100x below the 20 kHz+ PWM carrier); each feedback goes
// through a 10 V -> 3.3 V divider. The numbers below describe that analogue front end.
#include "bridge_core.h"

// ------------------------------------------------------------------ pin table (edit here)
enum OutKind { OUT_DAC, OUT_PWM };
struct Channel {
  const char* name;      // as config/rig.yaml chambers[].name
  uint8_t out_pin;       // DAC0/DAC1 or a hardware PWM pin (6..9 on the Due)
  OutKind kind;
  uint8_t in_pin;        // analog feedback input
  // set-point: Pa -> output volts at the pin = pa * out_v_per_pa + out_v_offset
  float out_v_per_pa, out_v_offset;
  // feedback: input volts at the pin -> Pa = (v - in_v_offset) * in_pa_per_v
  float in_v_offset, in_pa_per_v;
  uint32_t max_pressure_pa;   // the firmware's own hard limit; the host can only lower it
};

const float VREF = 3.3f;
const float DAC_LO = VREF / 6.0f, DAC_HI = VREF * 5.0f / 6.0f;   // SAM3X DAC output span

// K8P 0-2 bar model: 0-10 V <-> 0-200 kPa; op-amp gain 10/2.2 after the DAC (0.55..2.75 V
// -> 0..10 V with offset removal), 10/3.3 after PWM; feedback divider 10 V -> 3.3 V.
Channel CH[ssb::N_CH] = {
  {"seg1_ch1", DAC0, OUT_DAC, A0, 2.2f / 200000.0f, DAC_LO, 0.0f, 200000.0f / VREF, 150000},
  {"seg1_ch2", DAC1, OUT_DAC, A1, 2.2f / 200000.0f, DAC_LO, 0.0f, 200000.0f / VREF, 150000},
  {"seg1_ch3", 6,    OUT_PWM, A2, VREF / 200000.0f, 0.0f,   0.0f, 200000.0f / VREF, 150000},
  {"seg2_ch1", 7,    OUT_PWM, A3, VREF / 200000.0f, 0.0f,   0.0f, 200000.0f / VREF, 150000},
  {"seg2_ch2", 8,    OUT_PWM, A4, VREF / 200000.0f, 0.0f,   0.0f, 200000.0f / VREF, 150000},
  {"seg2_ch3", 9,    OUT_PWM, A5, VREF / 200000.0f, 0.0f,   0.0f, 200000.0f / VREF, 150000},
};
// Feedback outside [-5 %, 105 %] of the sensor span means a broken wire or sensor: FAULT flag.
const float FEEDBACK_MIN_PA = -10000.0f, FEEDBACK_MAX_PA = 210000.0f;

// SerialUSB = the Due's native USB port (full speed, baud ignored); Serial = programming port.
#define HOST SerialUSB
const uint32_t BAUD = 115200;

// --------------------------------------------------------------------------------------
static uint32_t fw_limits[ssb::N_CH];
static ssb::Core* core;
static uint32_t last_written[ssb::N_CH];

static uint32_t pa_to_counts(const Channel& c, uint32_t pa) {
  float v = pa * c.out_v_per_pa + c.out_v_offset;
  float lo = c.kind == OUT_DAC ? DAC_LO : 0.0f, hi = c.kind == OUT_DAC ? DAC_HI : VREF;
  if (v < lo) v = lo;
  if (v > hi) v = hi;
  float counts = (v - lo) / (hi - lo) * 4095.0f;
  return (uint32_t)(counts + 0.5f);
}

static void write_outputs() {
  for (int i = 0; i < ssb::N_CH; ++i) {
    uint32_t sp = core->setpoints[i];
    if (sp == last_written[i]) continue;
    analogWrite(CH[i].out_pin, pa_to_counts(CH[i], sp));
    last_written[i] = sp;
  }
}

static void read_inputs() {
  for (int i = 0; i < ssb::N_CH; ++i) {
    float v = analogRead(CH[i].in_pin) * (VREF / 4095.0f);
    float pa = (v - CH[i].in_v_offset) * CH[i].in_pa_per_v;
    core->set_measured(i, (int32_t)pa, pa >= FEEDBACK_MIN_PA && pa <= FEEDBACK_MAX_PA);
  }
}

void setup() {
  analogWriteResolution(12);
  analogReadResolution(12);
  for (int i = 0; i < ssb::N_CH; ++i) {
    fw_limits[i] = CH[i].max_pressure_pa;
    last_written[i] = 1;                 // force the first write of zero
  }
  static ssb::Core instance(fw_limits);
  core = &instance;
  write_outputs();                       // vented from the first microsecond
  HOST.begin(BAUD);
}

void loop() {
  uint8_t buf[64];
  int n = 0;
  while (n < (int)sizeof(buf) && HOST.available() > 0) buf[n++] = (uint8_t)HOST.read();
  uint32_t now = micros();
  if (n > 0) core->receive(buf, (size_t)n, now);
  read_inputs();
  core->tick(micros());
  write_outputs();                       // after every frame and every watchdog decision
  // SAM core's SerialUSB.write() drops data while no host has the port open, and waits
  // (bounded) for USB buffer space otherwise; the core's tx buffer is bounded too.
  uint8_t out[128];
  size_t k;
  while ((k = core->take_tx(out, sizeof(out))) > 0) HOST.write(out, k);
}
