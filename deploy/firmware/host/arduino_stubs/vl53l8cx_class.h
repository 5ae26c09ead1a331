// Declarations only: the part of ST's "STM32duino VL53L8CX" library (1.x method names) that
// vl53l8cx_bridge.ino calls, with the library's types, so that g++ can type-check the sketch on a PC (see
// Arduino.h). A board build uses the real library.
#ifndef CELL_VL53L8CX_CLASS_STUB_H
#define CELL_VL53L8CX_CLASS_STUB_H

#include <stdint.h>

#include "Wire.h"

#define VL53L8CX_NB_TARGET_PER_ZONE 1U
#define VL53L8CX_RESOLUTION_4X4 ((uint8_t)16U)
#define VL53L8CX_RESOLUTION_8X8 ((uint8_t)64U)

typedef struct {
  uint8_t nb_target_detected[VL53L8CX_RESOLUTION_8X8];
  uint16_t range_sigma_mm[VL53L8CX_RESOLUTION_8X8 * VL53L8CX_NB_TARGET_PER_ZONE];
  int16_t distance_mm[VL53L8CX_RESOLUTION_8X8 * VL53L8CX_NB_TARGET_PER_ZONE];
  uint8_t reflectance[VL53L8CX_RESOLUTION_8X8 * VL53L8CX_NB_TARGET_PER_ZONE];
  uint8_t target_status[VL53L8CX_RESOLUTION_8X8 * VL53L8CX_NB_TARGET_PER_ZONE];
} VL53L8CX_ResultsData;

class VL53L8CX {
 public:
  VL53L8CX(TwoWire *i2c, int lpn_pin, int i2c_rst_pin = -1);
  int begin();
  int init_sensor(uint8_t addr = 0x52);
  uint8_t vl53l8cx_set_resolution(uint8_t resolution);
  uint8_t vl53l8cx_set_ranging_frequency_hz(uint8_t frequency_hz);
  uint8_t vl53l8cx_start_ranging();
  uint8_t vl53l8cx_stop_ranging();
  uint8_t vl53l8cx_check_data_ready(uint8_t *p_is_ready);
  uint8_t vl53l8cx_get_ranging_data(VL53L8CX_ResultsData *p_results);
};

#endif
