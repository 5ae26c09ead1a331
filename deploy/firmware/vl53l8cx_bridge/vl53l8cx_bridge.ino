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

#include <Arduino.h>
#include <Wire.h>
#include <vl53l8cx_class.h>

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

// ---- protocol constants (docs/vl53l8cx-serial.md) ------------------------------------------------
static const uint8_t MAGIC0 = 0xA5, MAGIC1 = 0x5C, VERSION = 1;
static const uint8_t T_RANGING = 0x01, T_STATUS = 0x02, T_TEXT = 0x03;
static const uint8_t C_START = 0x81, C_STOP = 0x82, C_SET_RESOLUTION = 0x83, C_SET_FREQUENCY = 0x84,
                     C_QUERY = 0x85;
static const uint8_t R_OK = 0, R_INVALID = 1, R_SENSOR_ERROR = 2;
static const uint16_t HEADER_SIZE = 14, MAX_PAYLOAD = 1024;

VL53L8CX sensor(&Wire, LPN_PIN, I2C_RST_PIN);
VL53L8CX_ResultsData results;

static uint32_t tx_seq = 0;
static bool ranging = false;
static bool sensor_ok = false;
static uint8_t resolution = 8;   // zones per side
static uint8_t frequency_hz = 15;

// ---- CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, no final XOR --------------------
static uint16_t crc16_update(uint16_t crc, const uint8_t *data, size_t n) {
  for (size_t i = 0; i < n; i++) {
    crc ^= (uint16_t)data[i] << 8;
    for (uint8_t b = 0; b < 8; b++) crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
  }
  return crc;
}

static void put_u16(uint8_t *p, uint16_t v) { p[0] = v & 0xFF; p[1] = v >> 8; }
static void put_u32(uint8_t *p, uint32_t v) { for (int i = 0; i < 4; i++) p[i] = (v >> (8 * i)) & 0xFF; }

// Header, payload and CRC go out as one write so that a frame is never interleaved with another.
static uint8_t tx_buf[HEADER_SIZE + 2 + 7 * 64 + 2];

static void send_frame(uint8_t type, const uint8_t *payload, uint16_t len) {
  uint8_t *h = tx_buf;
  h[0] = MAGIC0; h[1] = MAGIC1; h[2] = VERSION; h[3] = type;
  put_u16(h + 4, len);
  put_u32(h + 6, tx_seq++);
  put_u32(h + 10, micros());
  if (len) memcpy(h + HEADER_SIZE, payload, len);
  put_u16(h + HEADER_SIZE + len, crc16_update(0xFFFF, h, HEADER_SIZE + len));
  LINK.write(h, HEADER_SIZE + len + 2);
}

static void send_text(const char *text) {
  send_frame(T_TEXT, (const uint8_t *)text, (uint16_t)strlen(text));
}

static void send_status(uint8_t command, uint8_t result) {
  uint8_t p[5] = {command, result, (uint8_t)(ranging ? 1 : 0), resolution, frequency_hz};
  send_frame(T_STATUS, p, sizeof p);
}

// ---- sensor ---------------------------------------------------------------------------------------
static uint8_t max_frequency(uint8_t res) { return res == 8 ? 15 : 60; }

// Applies resolution and frequency, restarting ranging if it was on. Returns the ULD status (0 = ok).
static uint8_t configure_sensor() {
  uint8_t st = 0;
  if (ranging) st |= ULD_STOP(sensor);
  st |= ULD_SET_RESOLUTION(sensor, resolution == 8 ? VL53L8CX_RESOLUTION_8X8 : VL53L8CX_RESOLUTION_4X4);
  st |= ULD_SET_FREQUENCY(sensor, frequency_hz);
  if (ranging) st |= ULD_START(sensor);
  return st;
}

static void send_ranging() {
  static uint8_t payload[2 + 7 * 64];
  const uint8_t n = resolution;
  payload[0] = n;
  payload[1] = 1;  // targets per zone sent: the first one
  for (uint8_t i = 0; i < n; i++) {
    for (uint8_t j = 0; j < n; j++) {
      const uint16_t uld = i * n + (n - 1 - j);   // ST's order is mirrored left to right
      const uint16_t t = VL53L8CX_NB_TARGET_PER_ZONE * uld;
      uint8_t *z = payload + 2 + 7 * (i * n + j);
      const bool target = results.nb_target_detected[uld] > 0;
      put_u16(z, target ? (uint16_t)results.distance_mm[t] : 0);
      put_u16(z + 2, target ? results.range_sigma_mm[t] : 0);
      z[4] = target ? results.target_status[t] : 255;
      z[5] = target ? results.reflectance[t] : 0;
      z[6] = results.nb_target_detected[uld];
    }
  }
  send_frame(T_RANGING, payload, 2 + 7 * n * n);
}

// ---- commands from the host -----------------------------------------------------------------------
static void handle_command(uint8_t type, const uint8_t *payload, uint16_t len) {
  uint8_t result = R_OK;
  const bool needs_value = (type == C_SET_RESOLUTION || type == C_SET_FREQUENCY);
  if (type < C_START || type > C_QUERY || len != (needs_value ? 1 : 0)) return;  // not a command: ignore
  if (!sensor_ok && type != C_QUERY) {
    send_text("VL53L8CX not initialised; check wiring and power, then reset the board");
    send_status(type, R_SENSOR_ERROR);
    return;
  }
  switch (type) {
    case C_START:
      if (!ranging) result = ULD_START(sensor) ? R_SENSOR_ERROR : R_OK;
      ranging = ranging || result == R_OK;
      break;
    case C_STOP:
      if (ranging) result = ULD_STOP(sensor) ? R_SENSOR_ERROR : R_OK;
      ranging = false;
      break;
    case C_SET_RESOLUTION:
      if (payload[0] != 4 && payload[0] != 8) { result = R_INVALID; break; }
      resolution = payload[0];
      if (frequency_hz > max_frequency(resolution)) frequency_hz = max_frequency(resolution);
      result = configure_sensor() ? R_SENSOR_ERROR : R_OK;
      break;
    case C_SET_FREQUENCY:
      if (payload[0] < 1 || payload[0] > max_frequency(resolution)) { result = R_INVALID; break; }
      frequency_hz = payload[0];
      result = configure_sensor() ? R_SENSOR_ERROR : R_OK;
      break;
    default:  // QUERY
      break;
  }
  if (result == R_SENSOR_ERROR) send_text("the VL53L8CX ULD returned an error");
  send_status(type, result);
}

// Receiver (docs/vl53l8cx-serial.md, "Receiving"): resynchronise on the magic, check version, length
// and CRC; after a CRC error drop one byte only.
static uint8_t rx_buf[HEADER_SIZE + 16 + 2];   // commands carry at most 1 payload byte
static uint16_t rx_len = 0;

static void drop_rx(uint16_t n) {
  memmove(rx_buf, rx_buf + n, rx_len - n);
  rx_len -= n;
}

static void poll_link() {
  while (LINK.available() > 0) {
    if (rx_len == sizeof rx_buf) drop_rx(1);
    rx_buf[rx_len++] = (uint8_t)LINK.read();
    for (;;) {
      uint16_t start = 0;
      while (start < rx_len && !(rx_buf[start] == MAGIC0 && (start + 1 == rx_len || rx_buf[start + 1] == MAGIC1))) start++;
      if (start) drop_rx(start);
      if (rx_len < HEADER_SIZE) break;
      const uint16_t len = rx_buf[4] | (rx_buf[5] << 8);
      if (rx_buf[2] != VERSION || len > MAX_PAYLOAD) { drop_rx(1); continue; }
      if (len > sizeof rx_buf - HEADER_SIZE - 2) { drop_rx(1); continue; }  // longer than any command
      if (rx_len < HEADER_SIZE + len + 2) break;
      const uint16_t crc = rx_buf[HEADER_SIZE + len] | (rx_buf[HEADER_SIZE + len + 1] << 8);
      if (crc != crc16_update(0xFFFF, rx_buf, HEADER_SIZE + len)) { drop_rx(1); continue; }
      handle_command(rx_buf[3], rx_buf + HEADER_SIZE, len);
      drop_rx(HEADER_SIZE + len + 2);
    }
  }
}

// ---- Arduino entry points -------------------------------------------------------------------------
void setup() {
  LINK.begin(LINK_BAUD);
  Wire.begin();
  Wire.setClock(I2C_CLOCK_HZ);
  send_text("cell VL53L8CX bridge, protocol 1");
  sensor.begin();
  sensor_ok = ULD_INIT(sensor) == 0 && configure_sensor() == 0;   // firmware upload: about 1 s
  if (!sensor_ok) send_text("VL53L8CX not found or its initialisation failed");
  send_status(0, sensor_ok ? R_OK : R_SENSOR_ERROR);
}

void loop() {
  poll_link();
  if (!ranging) return;
  uint8_t ready = 0;
  if (ULD_DATA_READY(sensor, &ready) != 0) {
    send_text("VL53L8CX: reading the data-ready flag failed");
    return;
  }
  if (ready && ULD_GET_DATA(sensor, &results) == 0) send_ranging();
}
