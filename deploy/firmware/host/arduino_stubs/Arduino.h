// Declarations only: the few names of an Arduino core that vl53l8cx_bridge.ino uses, so that g++ can
// type-check the sketch on a PC (tests/test_firmware_host.py). Nothing here runs; a board build uses the
// board's real core.
#ifndef CELL_ARDUINO_STUB_H
#define CELL_ARDUINO_STUB_H

#include <stddef.h>
#include <stdint.h>
#include <string.h>

unsigned long micros();

const uint8_t A1 = 15, A3 = 17;

class HardwareSerial {
 public:
  void begin(unsigned long baud);
  int available();
  int read();
  size_t write(const uint8_t *data, size_t n);
};

extern HardwareSerial Serial;

#endif
