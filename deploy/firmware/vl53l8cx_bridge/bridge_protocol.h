// The bridge's side of the serial protocol of docs/vl53l8cx-serial.md (version 1): the frame encoder, the
// receiver of host commands, and what the device does with each command.
//
// Plain C++11 with no Arduino header, no heap, no exceptions: the sketch beside this file and the host
// build in deploy/firmware/host/ compile the same source (tests/test_firmware_host.py runs the host build
// against the cell's Python driver). Names carry a k prefix or live in namespace bridge so that the
// macros of board cores (STM32's CRC, POSIX's R_OK, ...) cannot clash with them.

#ifndef VL53L8CX_BRIDGE_PROTOCOL_H
#define VL53L8CX_BRIDGE_PROTOCOL_H

#include <stddef.h>
#include <stdint.h>

namespace bridge {

const uint8_t kMagic0 = 0xA5, kMagic1 = 0x5C, kVersion = 1;
const uint8_t kRanging = 0x01, kStatus = 0x02, kText = 0x03;
const uint8_t kStart = 0x81, kStop = 0x82, kSetResolution = 0x83, kSetFrequency = 0x84, kQuery = 0x85;
const uint8_t kResultOk = 0, kResultInvalidParameter = 1, kResultSensorError = 2;
const uint16_t kHeaderSize = 14, kCrcSize = 2, kMaxPayload = 1024;
const uint8_t kMaxZones = 64;
const uint16_t kZoneSize = 7;
// The longest frame the bridge sends: an 8x8 RANGING frame (466 bytes).
const uint16_t kMaxFrame = kHeaderSize + 2 + kZoneSize * kMaxZones + kCrcSize;
// The longest payload the receiver buffers: a header announcing more cannot be a command (they carry at
// most one byte), so it is treated as a bad header.
const uint16_t kMaxCommandPayload = 16;
const uint8_t kDefaultResolution = 8, kDefaultFrequencyHz = 15;

// CRC-16/CCITT-FALSE: polynomial 0x1021, initial value 0xFFFF, not reflected, no final XOR.
uint16_t crc16(const uint8_t *data, size_t n);

// Highest ranging frequency [Hz] the VL53L8CX allows at a resolution (zones per side).
uint8_t max_frequency_hz(uint8_t resolution);

// One zone of a RANGING frame, the first target's values (docs/vl53l8cx-serial.md, "0x01 RANGING").
struct Zone {
  int16_t distance_mm;
  uint16_t range_sigma_mm;
  uint8_t target_status;
  uint8_t reflectance_pct;
  uint8_t nb_target_detected;
};

// The arrays of ST's VL53L8CX_ResultsData that a RANGING frame carries: per zone nb_target_detected, per
// target (targets_per_zone entries per zone, the library's VL53L8CX_NB_TARGET_PER_ZONE) the others.
struct UldResults {
  const uint8_t *nb_target_detected;
  const int16_t *distance_mm;
  const uint16_t *range_sigma_mm;
  const uint8_t *target_status;
  const uint8_t *reflectance;
  uint8_t targets_per_zone;
};

// The resolution^2 zones of one ULD measurement in protocol order, row-major from the top-left as seen in
// the sensor frame (ST numbers the zones mirrored left to right: protocol zone i * res + j is ULD zone
// i * res + (res - 1 - j)), with each zone's first target; a zone without a target is sent as distance 0,
// sigma 0, status 255, reflectance 0 whatever the ULD left in its arrays.
void zones_from_uld(Zone *out, uint8_t resolution, const UldResults &results);

// Writes the RANGING payload of resolution x resolution zones (protocol order) at out, which must hold
// 2 + 7 resolution^2 bytes; returns its size.
uint16_t put_ranging_payload(uint8_t *out, uint8_t resolution, const Zone *zones);

// Completes the frame whose len-byte payload is already at out + kHeaderSize: the header goes in front,
// the CRC behind (out must hold kHeaderSize + len + kCrcSize bytes). Returns the frame's size.
uint16_t seal_frame(uint8_t *out, uint8_t type, uint32_t seq, uint32_t timestamp_us, uint16_t len);

// A host command: type (kStart .. kQuery) and, for kSetResolution and kSetFrequency, its value.
struct Command {
  uint8_t type;
  uint8_t value;
};

// What the receiver has seen: commands decoded; crc_errors, frames failing the CRC; bad_headers, magics
// followed by another version or a longer payload than any command; malformed, frames with a good CRC
// that are not a command (another type, a payload of the wrong length); bytes_discarded while searching.
struct ReceiverStats {
  uint32_t commands;
  uint32_t crc_errors;
  uint32_t bad_headers;
  uint32_t malformed;
  uint32_t bytes_discarded;
};

// Host-to-device frames from a byte stream, by the rules of "Receiving" in the protocol document.
class CommandReceiver {
 public:
  CommandReceiver();
  void push(uint8_t byte);
  // The next command the bytes pushed so far complete, if any (call until it returns false: one byte can
  // complete several commands, when it settles a corrupted header that was hiding them).
  bool next(Command *out);
  const ReceiverStats &stats() const { return stats_; }

 private:
  void discard(uint16_t n);
  void consume(uint16_t n);

  uint8_t buf_[kHeaderSize + kMaxCommandPayload + kCrcSize];
  uint16_t len_;
  ReceiverStats stats_;
};

// What the device logic needs from the board: the link to the host (one call per whole frame, so that
// frames are never interleaved), a microsecond clock, and the sensor. The sensor calls return true on
// success (the ULD's status 0).
class Board {
 public:
  virtual void write(const uint8_t *data, uint16_t n) = 0;
  virtual uint32_t now_us() = 0;
  virtual bool sensor_start() = 0;
  virtual bool sensor_stop() = 0;
  virtual bool sensor_configure(uint8_t resolution, uint8_t frequency_hz) = 0;

 protected:
  ~Board() {}
};

// The device side of the protocol: numbers and sends every frame, answers every command with a STATUS,
// keeps the ranging state. Not ranging after begin, 8x8 at 15 Hz.
class Bridge {
 public:
  explicit Bridge(Board &board);
  // Applies the default configuration when the sensor was found and initialised, then sends the
  // unsolicited STATUS (command 0); without a sensor every command but QUERY fails with a sensor error.
  void begin(bool sensor_found);
  // A byte from the host: answers each command it completes.
  void receive(uint8_t byte);
  // Sends one measurement of resolution()^2 zones in protocol order.
  void send_ranging(const Zone *zones);
  void send_text(const char *text);

  bool ranging() const { return ranging_; }
  uint8_t resolution() const { return resolution_; }
  uint8_t frequency_hz() const { return frequency_hz_; }
  // The sequence number the next frame will carry.
  uint32_t next_seq() const { return seq_; }
  const ReceiverStats &receiver_stats() const { return rx_.stats(); }

 private:
  void send(uint8_t type, uint16_t len);
  void send_status(uint8_t command, uint8_t result);
  uint8_t execute(const Command &command);
  bool reconfigure();

  Board &board_;
  CommandReceiver rx_;
  uint32_t seq_;
  bool sensor_ok_;
  bool ranging_;
  uint8_t resolution_;
  uint8_t frequency_hz_;
  uint8_t tx_[kMaxFrame];
};

}  // namespace bridge

#endif  // VL53L8CX_BRIDGE_PROTOCOL_H
