// Declarations only: the I2C bus object of an Arduino core as vl53l8cx_bridge.ino uses it (see Arduino.h).
#ifndef CELL_WIRE_STUB_H
#define CELL_WIRE_STUB_H

#include <stdint.h>

class TwoWire {
 public:
  void begin();
  void setClock(uint32_t hz);
};

extern TwoWire Wire;

#endif
