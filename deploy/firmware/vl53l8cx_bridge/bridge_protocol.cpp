// See bridge_protocol.h; docs/vl53l8cx-serial.md is normative.

#include "bridge_protocol.h"

#include <string.h>

namespace bridge {

namespace {

void put_u16(uint8_t *p, uint16_t v) {
  p[0] = (uint8_t)(v & 0xFF);
  p[1] = (uint8_t)(v >> 8);
}

void put_u32(uint8_t *p, uint32_t v) {
  for (int i = 0; i < 4; i++) p[i] = (uint8_t)(v >> (8 * i));
}

uint16_t get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }

bool takes_value(uint8_t type) { return type == kSetResolution || type == kSetFrequency; }

bool is_command(uint8_t type) { return type >= kStart && type <= kQuery; }

}  // namespace

uint16_t crc16(const uint8_t *data, size_t n) {
  uint16_t crc = 0xFFFF;
  for (size_t i = 0; i < n; i++) {
    crc ^= (uint16_t)(data[i] << 8);
    for (int b = 0; b < 8; b++) crc = (crc & 0x8000) ? (uint16_t)((crc << 1) ^ 0x1021) : (uint16_t)(crc << 1);
  }
  return crc;
}

uint8_t max_frequency_hz(uint8_t resolution) { return resolution == 8 ? 15 : 60; }

void zones_from_uld(Zone *out, uint8_t resolution, const UldResults &results) {
  for (uint8_t i = 0; i < resolution; i++) {
    for (uint8_t j = 0; j < resolution; j++) {
      const uint16_t uld = (uint16_t)(i * resolution + (resolution - 1 - j));
      const uint16_t t = (uint16_t)(results.targets_per_zone * uld);
      Zone &z = out[i * resolution + j];
      z.nb_target_detected = results.nb_target_detected[uld];
      if (z.nb_target_detected > 0) {
        z.distance_mm = results.distance_mm[t];
        z.range_sigma_mm = results.range_sigma_mm[t];
        z.target_status = results.target_status[t];
        z.reflectance_pct = results.reflectance[t];
      } else {
        z.distance_mm = 0;
        z.range_sigma_mm = 0;
        z.target_status = 255;
        z.reflectance_pct = 0;
      }
    }
  }
}

uint16_t put_ranging_payload(uint8_t *out, uint8_t resolution, const Zone *zones) {
  const uint16_t n = (uint16_t)(resolution * resolution);
  out[0] = resolution;
  out[1] = 1;  // targets per zone sent: the first one
  for (uint16_t k = 0; k < n; k++) {
    uint8_t *z = out + 2 + kZoneSize * k;
    put_u16(z, (uint16_t)zones[k].distance_mm);
    put_u16(z + 2, zones[k].range_sigma_mm);
    z[4] = zones[k].target_status;
    z[5] = zones[k].reflectance_pct;
    z[6] = zones[k].nb_target_detected;
  }
  return (uint16_t)(2 + kZoneSize * n);
}

uint16_t seal_frame(uint8_t *out, uint8_t type, uint32_t seq, uint32_t timestamp_us, uint16_t len) {
  out[0] = kMagic0;
  out[1] = kMagic1;
  out[2] = kVersion;
  out[3] = type;
  put_u16(out + 4, len);
  put_u32(out + 6, seq);
  put_u32(out + 10, timestamp_us);
  put_u16(out + kHeaderSize + len, crc16(out, kHeaderSize + len));
  return (uint16_t)(kHeaderSize + len + kCrcSize);
}

// ---- receiver ------------------------------------------------------------------------------------------

CommandReceiver::CommandReceiver() : len_(0) { memset(&stats_, 0, sizeof stats_); }

void CommandReceiver::push(uint8_t byte) {
  if (len_ == sizeof buf_) discard(1);  // only when next() was not called: it never leaves a full buffer
  buf_[len_++] = byte;
}

void CommandReceiver::consume(uint16_t n) {
  memmove(buf_, buf_ + n, len_ - n);
  len_ = (uint16_t)(len_ - n);
}

void CommandReceiver::discard(uint16_t n) {
  consume(n);
  stats_.bytes_discarded += n;
}

bool CommandReceiver::next(Command *out) {
  for (;;) {
    // Up to the next magic; a last byte that may begin one stays (its second byte has not come yet).
    uint16_t start = 0;
    while (start < len_ && !(buf_[start] == kMagic0 && (start + 1 == len_ || buf_[start + 1] == kMagic1))) start++;
    if (start) discard(start);
    if (len_ < kHeaderSize) return false;
    const uint16_t len = get_u16(buf_ + 4);
    if (buf_[2] != kVersion || len > kMaxCommandPayload) {
      stats_.bad_headers++;
      discard(1);
      continue;
    }
    if (len_ < kHeaderSize + len + kCrcSize) return false;
    if (get_u16(buf_ + kHeaderSize + len) != crc16(buf_, kHeaderSize + len)) {
      // The length field of a corrupted frame cannot be trusted: the next frame may begin inside it.
      stats_.crc_errors++;
      discard(1);
      continue;
    }
    const uint8_t type = buf_[3];
    const bool ok = is_command(type) && len == (takes_value(type) ? 1 : 0);
    out->type = type;
    out->value = len ? buf_[kHeaderSize] : 0;
    consume((uint16_t)(kHeaderSize + len + kCrcSize));
    if (ok) {
      stats_.commands++;
      return true;
    }
    stats_.malformed++;
  }
}

// ---- device --------------------------------------------------------------------------------------------

Bridge::Bridge(Board &board)
    : board_(board), seq_(0), sensor_ok_(false), ranging_(false), resolution_(kDefaultResolution),
      frequency_hz_(kDefaultFrequencyHz) {}

void Bridge::send(uint8_t type, uint16_t len) {
  board_.write(tx_, seal_frame(tx_, type, seq_++, board_.now_us(), len));
}

void Bridge::send_text(const char *text) {
  size_t n = strlen(text);
  if (n > kMaxFrame - kHeaderSize - kCrcSize) n = kMaxFrame - kHeaderSize - kCrcSize;
  memcpy(tx_ + kHeaderSize, text, n);
  send(kText, (uint16_t)n);
}

void Bridge::send_status(uint8_t command, uint8_t result) {
  uint8_t *p = tx_ + kHeaderSize;
  p[0] = command;
  p[1] = result;
  p[2] = ranging_ ? 1 : 0;
  p[3] = resolution_;
  p[4] = frequency_hz_;
  send(kStatus, 5);
}

void Bridge::send_ranging(const Zone *zones) {
  send(kRanging, put_ranging_payload(tx_ + kHeaderSize, resolution_, zones));
}

// The ULD refuses changes while it ranges: stop, apply, restart. Every step runs even after a failure,
// so that the sensor is left ranging if it was.
bool Bridge::reconfigure() {
  bool ok = true;
  if (ranging_) ok = board_.sensor_stop() && ok;
  ok = board_.sensor_configure(resolution_, frequency_hz_) && ok;
  if (ranging_) ok = board_.sensor_start() && ok;
  return ok;
}

void Bridge::begin(bool sensor_found) {
  sensor_ok_ = sensor_found && reconfigure();
  if (!sensor_ok_) send_text("VL53L8CX not found or its initialisation failed");
  send_status(0, sensor_ok_ ? kResultOk : kResultSensorError);
}

uint8_t Bridge::execute(const Command &command) {
  switch (command.type) {
    case kStart:
      if (!ranging_) {
        if (!board_.sensor_start()) return kResultSensorError;
        ranging_ = true;
      }
      return kResultOk;
    case kStop: {
      const bool ok = !ranging_ || board_.sensor_stop();
      ranging_ = false;
      return ok ? kResultOk : kResultSensorError;
    }
    case kSetResolution:
      if (command.value != 4 && command.value != 8) return kResultInvalidParameter;
      resolution_ = command.value;
      if (frequency_hz_ > max_frequency_hz(resolution_)) frequency_hz_ = max_frequency_hz(resolution_);
      return reconfigure() ? kResultOk : kResultSensorError;
    case kSetFrequency:
      if (command.value < 1 || command.value > max_frequency_hz(resolution_)) return kResultInvalidParameter;
      frequency_hz_ = command.value;
      return reconfigure() ? kResultOk : kResultSensorError;
    default:  // kQuery
      return kResultOk;
  }
}

void Bridge::receive(uint8_t byte) {
  rx_.push(byte);
  Command command;
  while (rx_.next(&command)) {
    if (!sensor_ok_ && command.type != kQuery) {
      send_text("VL53L8CX not initialised; check wiring and power, then reset the board");
      send_status(command.type, kResultSensorError);
      continue;
    }
    const uint8_t result = execute(command);
    if (result == kResultSensorError) send_text("the VL53L8CX ULD returned an error");
    send_status(command.type, result);
  }
}

}  // namespace bridge
