// Protocol and safety logic of the Due pressure bridge: plain C++, no Arduino calls.
//
// The sketch (due_pressure_bridge.ino) only moves bytes and volts; everything that decides
// what reaches a regulator lives here, so it compiles on the host with g++ and is run in
// `make test` against test/data/protocol_vectors.json, the same golden vectors the Python
// side (softshape_ros/hardware/protocol.py, due_core.py) is tested with. docs/protocol.md
// describes the wire format.
#ifndef SOFTSHAPE_BRIDGE_CORE_H
#define SOFTSHAPE_BRIDGE_CORE_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

namespace ssb {

const uint8_t PROTOCOL_VERSION = 1;
const uint8_t FW_MAJOR = 1;
const uint8_t FW_MINOR = 0;
const uint8_t SYNC0 = 0xA5;
const uint8_t SYNC1 = 0x5A;
const size_t HEADER = 4;
const size_t TRAILER = 4;
const size_t MAX_PAYLOAD = 64;
const size_t MAX_FRAME = HEADER + MAX_PAYLOAD + TRAILER;
const int N_CH = 6;

enum FrameType : uint8_t {
  T_HELLO = 0x01, T_CONFIG = 0x02, T_COMMAND = 0x03, T_VENT = 0x04, T_HEARTBEAT = 0x05,
  T_HELLO_REPLY = 0x81, T_STATE = 0x82,
};

enum Flags : uint8_t {
  F_CLAMPED = 0x01, F_WATCHDOG = 0x02, F_VENTED = 0x04, F_FAULT = 0x08, F_ACK = 0x10,
};

const uint16_t DEFAULT_STATE_RATE_HZ = 100;
const uint16_t DEFAULT_WATCHDOG_MS = 500;
const uint16_t MIN_RATE_HZ = 1, MAX_RATE_HZ = 1000;
const uint16_t MIN_WATCHDOG_MS = 20, MAX_WATCHDOG_MS = 10000;
const uint32_t IDLE_FLUSH_US = 20000;  // a partial frame older than this is given up

// IEEE CRC-32 (as zlib): reflected polynomial 0xEDB88320, init and final xor 0xFFFFFFFF.
inline uint32_t crc32_update(uint32_t crc, const uint8_t* data, size_t n) {
  crc = ~crc;
  for (size_t i = 0; i < n; ++i) {
    crc ^= data[i];
    for (int k = 0; k < 8; ++k) crc = (crc >> 1) ^ (0xEDB88320u & (0u - (crc & 1u)));
  }
  return ~crc;
}
inline uint32_t crc32(const uint8_t* data, size_t n) { return crc32_update(0, data, n); }

inline void put_u16(uint8_t* p, uint16_t v) { p[0] = v & 0xFF; p[1] = v >> 8; }
inline void put_u32(uint8_t* p, uint32_t v) {
  for (int i = 0; i < 4; ++i) p[i] = (v >> (8 * i)) & 0xFF;
}
inline uint16_t get_u16(const uint8_t* p) { return (uint16_t)(p[0] | (p[1] << 8)); }
inline uint32_t get_u32(const uint8_t* p) {
  return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

// Frame into out (at least HEADER + n + TRAILER bytes); returns the frame length.
inline size_t encode_frame(uint8_t type, const uint8_t* payload, size_t n, uint8_t* out) {
  out[0] = SYNC0; out[1] = SYNC1; out[2] = type; out[3] = (uint8_t)n;
  if (n) memcpy(out + HEADER, payload, n);
  put_u32(out + HEADER + n, crc32(out + 2, 2 + n));
  return HEADER + n + TRAILER;
}

// Streaming parser, byte at a time, fixed buffer. Same algorithm as the Python FrameParser:
// on bad sync drop bytes up to the next sync; on a bad length or CRC drop one byte and
// rescan what is buffered, so the next good frame is always found.
struct Parser {
  uint8_t buf[MAX_FRAME];
  size_t len = 0;
  uint32_t frames_ok = 0, bad_crc = 0, skipped = 0;
  uint8_t type = 0, n = 0;
  uint8_t payload[MAX_PAYLOAD];

  void drop(size_t k) {
    memmove(buf, buf + k, len - k);
    len -= k;
    skipped += k;
  }

  // Feed one byte; calls sink.on_parsed(type, payload, n) for each good frame completed.
  template <class Sink> void feed(uint8_t b, Sink& sink) {
    buf[len++] = b;
    scan(sink);
  }

  // The line went idle: give up on a partial frame and rescan what follows it.
  template <class Sink> void flush(Sink& sink) {
    while (len) {
      drop(1);
      scan(sink);
    }
  }

  template <class Sink> void scan(Sink& sink) {
    for (;;) {
      if (len < 2) {
        if (len == 1 && buf[0] != SYNC0) drop(1);
        return;
      }
      if (buf[0] != SYNC0 || buf[1] != SYNC1) {
        size_t i = 1;
        while (i + 1 < len && !(buf[i] == SYNC0 && buf[i + 1] == SYNC1)) ++i;
        if (i + 1 >= len) i = (buf[len - 1] == SYNC0) ? len - 1 : len;
        drop(i);
        continue;
      }
      if (len < HEADER) return;
      size_t plen = buf[3];
      if (plen > MAX_PAYLOAD) { ++bad_crc; drop(1); continue; }
      size_t total = HEADER + plen + TRAILER;
      if (len < total) return;
      if (get_u32(buf + HEADER + plen) != crc32(buf + 2, 2 + plen)) {
        ++bad_crc; drop(1); continue;
      }
      type = buf[2]; n = (uint8_t)plen;
      memcpy(payload, buf + HEADER, plen);
      ++frames_ok;
      memmove(buf, buf + total, len - total);
      len -= total;
      sink.on_parsed(type, payload, n);
    }
  }
};

// Wrap-safe comparisons on the 32-bit microsecond clock.
inline uint32_t elapsed(uint32_t now, uint32_t then) { return now - then; }
inline bool due(uint32_t now, uint32_t deadline) { return (uint32_t)(now - deadline) < 0x80000000u; }

// The firmware's brain: frames in, set-points and frames out.
struct Core {
  uint32_t fw_limits[N_CH];
  uint32_t limits[N_CH];
  uint32_t setpoints[N_CH];
  int32_t measured[N_CH];
  uint16_t seq = 0;
  bool clamped = false, watchdog = false, vented = true, fault = false, armed = false;
  uint16_t rx_errors = 0;
  uint32_t last_rx = 0, next_state = 0, last_byte = 0;
  uint16_t state_rate_hz = DEFAULT_STATE_RATE_HZ;
  uint32_t state_period_us = 1000000u / DEFAULT_STATE_RATE_HZ;
  uint32_t watchdog_us = DEFAULT_WATCHDOG_MS * 1000u;
  uint32_t now = 0;           // time of the bytes being processed
  Parser parser;
  uint8_t tx[512];
  size_t tx_len = 0;

  explicit Core(const uint32_t* fw_limits_pa) {
    for (int i = 0; i < N_CH; ++i) {
      fw_limits[i] = limits[i] = fw_limits_pa[i];
      setpoints[i] = 0;
      measured[i] = 0;
    }
  }

  uint8_t flags() const {
    return (clamped ? F_CLAMPED : 0) | (watchdog ? F_WATCHDOG : 0) | (vented ? F_VENTED : 0) |
           (fault ? F_FAULT : 0);
  }

  void bad() { if (rx_errors < 0xFFFF) ++rx_errors; }

  void emit(uint8_t type, const uint8_t* p, size_t n) {
    if (tx_len + HEADER + n + TRAILER > sizeof(tx)) return;  // host not reading: drop
    tx_len += encode_frame(type, p, n, tx + tx_len);
  }

  void send_state(bool ack) {
    uint8_t p[33];
    put_u16(p, seq);
    put_u32(p + 2, now);
    for (int i = 0; i < N_CH; ++i) put_u32(p + 6 + 4 * i, (uint32_t)measured[i]);
    p[30] = flags() | (ack ? F_ACK : 0);
    put_u16(p + 31, rx_errors);
    emit(T_STATE, p, sizeof(p));
  }

  void send_hello_reply() {
    uint8_t p[32];
    p[0] = PROTOCOL_VERSION; p[1] = FW_MAJOR; p[2] = FW_MINOR; p[3] = N_CH;
    put_u16(p + 4, state_rate_hz);
    put_u16(p + 6, (uint16_t)(watchdog_us / 1000u));
    for (int i = 0; i < N_CH; ++i) put_u32(p + 8 + 4 * i, limits[i]);
    emit(T_HELLO_REPLY, p, sizeof(p));
  }

  void vent() {
    vented = true;
    armed = false;
    for (int i = 0; i < N_CH; ++i) setpoints[i] = 0;
  }

  void on_frame(uint8_t type, const uint8_t* p, uint8_t n) {
    switch (type) {
      case T_HELLO:
        if (n != 1) { bad(); return; }
        last_rx = now;
        send_hello_reply();
        return;
      case T_CONFIG: {
        if (n != 30) { bad(); return; }
        last_rx = now;
        uint16_t rate = get_u16(p + 2), wd = get_u16(p + 4);
        if (rate < MIN_RATE_HZ) rate = MIN_RATE_HZ;
        if (rate > MAX_RATE_HZ) rate = MAX_RATE_HZ;
        if (wd < MIN_WATCHDOG_MS) wd = MIN_WATCHDOG_MS;
        if (wd > MAX_WATCHDOG_MS) wd = MAX_WATCHDOG_MS;
        state_rate_hz = rate;
        state_period_us = 1000000u / rate;
        watchdog_us = wd * 1000u;
        for (int i = 0; i < N_CH; ++i) {
          uint32_t l = get_u32(p + 6 + 4 * i);
          limits[i] = l < fw_limits[i] ? l : fw_limits[i];   // lower, never raise
          if (setpoints[i] > limits[i]) setpoints[i] = limits[i];
        }
        seq = get_u16(p);
        send_state(true);
        return;
      }
      case T_COMMAND: {
        if (n != 26) { bad(); return; }
        last_rx = now;
        bool any = false;
        for (int i = 0; i < N_CH; ++i) {
          uint32_t v = get_u32(p + 2 + 4 * i);
          if (v > limits[i]) { v = limits[i]; any = true; }
          setpoints[i] = v;
        }
        clamped = any;
        seq = get_u16(p);
        vented = false;
        watchdog = false;
        armed = true;
        send_state(true);
        return;
      }
      case T_VENT:
        if (n != 2) { bad(); return; }
        last_rx = now;
        seq = get_u16(p);
        vent();
        send_state(true);
        return;
      case T_HEARTBEAT:
        if (n != 0) { bad(); return; }
        last_rx = now;
        return;
      default:
        bad();   // unknown type, or our own reply types echoed back
        return;
    }
  }

  // Parser errors count as receive errors, in order with the frames around them.
  uint32_t seen_bad = 0;
  void sync_bad() { while (seen_bad < parser.bad_crc) { ++seen_bad; bad(); } }
  void on_parsed(uint8_t type, const uint8_t* p, uint8_t n) { sync_bad(); on_frame(type, p, n); }

  // Bytes from the serial port, received at Due time t (microseconds).
  void receive(const uint8_t* data, size_t n, uint32_t t) {
    now = t;
    if (n) last_byte = t;
    for (size_t i = 0; i < n; ++i) {
      parser.feed(data[i], *this);
      sync_bad();
    }
  }

  // Watchdog and state stream; call every loop iteration.
  void tick(uint32_t t) {
    now = t;
    if (parser.len && elapsed(now, last_byte) > IDLE_FLUSH_US) {
      parser.flush(*this);
      sync_bad();
    }
    if (armed && elapsed(now, last_rx) > watchdog_us) {
      watchdog = true;
      vent();
    }
    if (due(now, next_state)) {
      send_state(false);
      next_state += state_period_us;
      if (due(now, next_state)) next_state = now + state_period_us;
    }
  }

  void set_measured(int ch, int32_t pa, bool in_range) {
    measured[ch] = pa;
    fault_bits = in_range ? (fault_bits & ~(1u << ch)) : (fault_bits | (1u << ch));
    fault = fault_bits != 0;
  }
  uint32_t fault_bits = 0;

  size_t take_tx(uint8_t* out, size_t cap) {
    size_t k = tx_len < cap ? tx_len : cap;
    memcpy(out, tx, k);
    memmove(tx, tx + k, tx_len - k);
    tx_len -= k;
    return k;
  }
};

}  // namespace ssb

#endif  // SOFTSHAPE_BRIDGE_CORE_H
