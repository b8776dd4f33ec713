// Declarations of the few Arduino calls the sketch uses, with the signatures of
// arduino/ArduinoCore-sam (SerialUSB is its Serial_ from USB/USBAPI.h, which has no
// availableForWrite()), so test_hardware_firmware.py can type-check due_pressure_bridge.ino
// with g++ on the host. Compile only, never linked: the real build is
// `arduino-cli compile --fqbn arduino:sam:arduino_due_x_dbg firmware/due_pressure_bridge`.
#pragma once
#include <stddef.h>
#include <stdint.h>
enum { A0 = 54, A1, A2, A3, A4, A5, DAC0 = 66, DAC1 = 67 };
void analogWrite(uint32_t pin, uint32_t value);
uint32_t analogRead(uint32_t pin);
void analogWriteResolution(int bits);
void analogReadResolution(int bits);
uint32_t micros();
struct SerialLike {
  void begin(uint32_t baud);
  int available();
  int read();
  size_t write(const uint8_t* p, size_t n);
};
extern SerialLike SerialUSB;
