// Host-side driver of bridge_core.h for test/test_hardware_firmware.py.
//
// Reads one command per line on stdin and answers with exactly one line, so the Python
// test can run the golden vectors (test/data/protocol_vectors.json) through the very code
// the Due runs:
//   crc <hex>                 -> <crc32 decimal>
//   parse <hex>               -> <before_flush> <frames_ok> <bad_crc> <skipped> [type:payloadhex ...]
//   core <6 limits Pa>        -> ok            (a fresh firmware core)
//   measured <ch> <pa> <0|1>  -> ok
//   rx <t_us> <hex>           -> <tx hex or -> <6 set-points> <flags>
//   tick <t_us>               -> <tx hex or -> <6 set-points> <flags>
#include <cstdio>
#include <cstdlib>
#include <iostream>
#include <sstream>
#include <string>
#include <vector>

#include "../due_pressure_bridge/bridge_core.h"

static std::vector<uint8_t> unhex(const std::string& h) {
  std::vector<uint8_t> out;
  if (h == "-") return out;
  for (size_t i = 0; i + 1 < h.size(); i += 2) out.push_back((uint8_t)strtoul(h.substr(i, 2).c_str(), nullptr, 16));
  return out;
}

static std::string hex(const uint8_t* p, size_t n) {
  if (n == 0) return "-";
  std::string s;
  char b[3];
  for (size_t i = 0; i < n; ++i) { snprintf(b, sizeof(b), "%02x", p[i]); s += b; }
  return s;
}

struct Collect {
  std::vector<std::string> frames;
  void on_parsed(uint8_t type, const uint8_t* p, uint8_t n) {
    char t[8];
    snprintf(t, sizeof(t), "%u:", type);
    frames.push_back(std::string(t) + hex(p, n));
  }
};

static void report(ssb::Core& core) {
  uint8_t out[1024];
  size_t n = core.take_tx(out, sizeof(out));
  std::cout << hex(out, n);
  for (int i = 0; i < ssb::N_CH; ++i) std::cout << ' ' << core.setpoints[i];
  std::cout << ' ' << (unsigned)core.flags() << '\n';
}

int main() {
  std::string line;
  ssb::Core* core = nullptr;
  while (std::getline(std::cin, line)) {
    std::istringstream in(line);
    std::string cmd;
    in >> cmd;
    if (cmd == "crc") {
      std::string h; in >> h;
      std::vector<uint8_t> d = unhex(h);
      std::cout << ssb::crc32(d.data(), d.size()) << '\n';
    } else if (cmd == "parse") {
      std::string h; in >> h;
      std::vector<uint8_t> d = unhex(h);
      ssb::Parser p;
      Collect c;
      for (uint8_t b : d) p.feed(b, c);
      size_t before_flush = c.frames.size();
      p.flush(c);
      std::cout << before_flush << ' ' << p.frames_ok << ' ' << p.bad_crc << ' ' << p.skipped;
      for (auto& f : c.frames) std::cout << ' ' << f;
      std::cout << '\n';
    } else if (cmd == "core") {
      uint32_t lim[ssb::N_CH];
      for (int i = 0; i < ssb::N_CH; ++i) in >> lim[i];
      delete core;
      core = new ssb::Core(lim);
      std::cout << "ok\n";
    } else if (cmd == "measured") {
      int ch, ok; long pa;
      in >> ch >> pa >> ok;
      core->set_measured(ch, (int32_t)pa, ok != 0);
      std::cout << "ok\n";
    } else if (cmd == "rx") {
      unsigned long t; std::string h;
      in >> t >> h;
      std::vector<uint8_t> d = unhex(h);
      core->receive(d.data(), d.size(), (uint32_t)t);
      report(*core);
    } else if (cmd == "tick") {
      unsigned long t;
      in >> t;
      core->tick((uint32_t)t);
      report(*core);
    } else {
      std::cout << "error unknown command " << cmd << '\n';
    }
    std::cout.flush();
  }
  delete core;
  return 0;
}
