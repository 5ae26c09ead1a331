// VL53L8CX serial bridge for the cell: reads ST's VL53L8CX through its ULD driver and sends every
// measurement to the host in the frame format of docs/vl53l8cx-serial.md (protocol version 1).
//
// Board: any Arduino-compatible board with I2C at 1 MHz and a USB serial port (tested layout: a
// Nucleo-F401RE or an RP2040 board with the SATEL-VL53L8 breakout). Library: "STM32duino VL53L8CX"
// (ST's ULD wrapped for Arduino; it builds on non-STM32 cores too). See README.md beside this file.
//
// Behaviour (the protocol document is normative):
// - after start: a TEXT banner and an unsolicited STATUS (command 0); not ranging, 8x8 at 15 Hz;
// - START / STOP / SET_RESOLUTION / SET_FREQUENCY / QUERY from the host, each answered with a STATUS;
//   changes while ranging stop the sensor, apply, and restart it (the ULD refuses them while ranging);
// - every measurement becomes one RANGING frame, zones re-ordered from ST's order (mirrored left to
//   right) to row-major from the top-left as seen in the sensor frame (x right, y down).
// All of it but the sensor and the link lives in bridge_protocol.h/.cpp beside this file, which the
// Arduino IDE compiles with the sketch and which deploy/firmware/host/ builds and tests on a PC.

#include <Arduino.h>
#include <Wire.h>
#include <vl53l8cx_class.h>

#include "bridge_protocol.h"   // the frame encoder, the command receiver and the device logic

// ---- wiring and link ----------------------------------------------------------------------------
#ifndef LPN_PIN
#define LPN_PIN A3          // sensor LPn (low power enable); the breakout's "LPn"
#endif
#ifndef I2C_RST_PIN
#define I2C_RST_PIN A1      // sensor I2C reset; -1 when not wired
#endif
#define LINK Serial         // USB CDC: the baud rate is ignored; on a UART use 921600 8N1
#define LINK_BAUD 921600
#define I2C_CLOCK_HZ 1000000

// ---- ULD calls (library 1.x names; library 2.x drops the "vl53l8cx_" prefix of these methods) -----
#define ULD_INIT(s) (s).init_sensor()
#define ULD_SET_RESOLUTION(s, r) (s).vl53l8cx_set_resolution(r)
#define ULD_SET_FREQUENCY(s, f) (s).vl53l8cx_set_ranging_frequency_hz(f)
#define ULD_START(s) (s).vl53l8cx_start_ranging()
#define ULD_STOP(s) (s).vl53l8cx_stop_ranging()
#define ULD_DATA_READY(s, p) (s).vl53l8cx_check_data_ready(p)
#define ULD_GET_DATA(s, p) (s).vl53l8cx_get_ranging_data(p)

// ---- the board: link and sensor -------------------------------------------------------------------
VL53L8CX sensor(&Wire, LPN_PIN, I2C_RST_PIN);
VL53L8CX_ResultsData results;

class UldBoard : public bridge::Board {
 public:
  void write(const uint8_t *data, uint16_t n) override { LINK.write(data, n); }
  uint32_t now_us() override { return micros(); }
  bool sensor_start() override { return ULD_START(sensor) == 0; }
  bool sensor_stop() override { return ULD_STOP(sensor) == 0; }
  bool sensor_configure(uint8_t resolution, uint8_t frequency_hz) override {
    const uint8_t r = resolution == 8 ? VL53L8CX_RESOLUTION_8X8 : VL53L8CX_RESOLUTION_4X4;
    const bool resolution_ok = ULD_SET_RESOLUTION(sensor, r) == 0;
    return ULD_SET_FREQUENCY(sensor, frequency_hz) == 0 && resolution_ok;
  }
};

UldBoard uld_board;
bridge::Bridge device(uld_board);

static void send_ranging() {
  static bridge::Zone zones[bridge::kMaxZones];
  const bridge::UldResults uld = {results.nb_target_detected, results.distance_mm, results.range_sigma_mm,
                                  results.target_status, results.reflectance, VL53L8CX_NB_TARGET_PER_ZONE};
  bridge::zones_from_uld(zones, device.resolution(), uld);
  device.send_ranging(zones);
}

// ---- Arduino entry points -------------------------------------------------------------------------
void setup() {
  LINK.begin(LINK_BAUD);
  Wire.begin();
  Wire.setClock(I2C_CLOCK_HZ);
  device.send_text("cell VL53L8CX bridge, protocol 1");
  sensor.begin();
  device.begin(ULD_INIT(sensor) == 0);   // firmware upload to the sensor: about 1 s
}

void loop() {
  while (LINK.available() > 0) device.receive((uint8_t)LINK.read());
  if (!device.ranging()) return;
  uint8_t ready = 0;
  if (ULD_DATA_READY(sensor, &ready) != 0) {
    device.send_text("VL53L8CX: reading the data-ready flag failed");
    return;
  }
  if (ready && ULD_GET_DATA(sensor, &results) == 0) send_ranging();
}
