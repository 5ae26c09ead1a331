// The VL53L8CX bridge's protocol code (../vl53l8cx_bridge/bridge_protocol.cpp) on a Linux host: acts as
// the bridge board on an open file descriptor, e.g. the master side of a pseudo-terminal whose slave the
// cell's driver opens as its serial port. It runs the sketch's own receiver, command handling and frame
// encoder; only the sensor is synthetic (every ULD call succeeds, or, with --sensor-missing, the sensor is
// never found) and each measurement is the UldMeasurement below, sent at the commanded frequency through
// the sketch's own conversion from ST's zone order.
//
//   cd deploy/firmware && g++ -std=c++17 -Wall -Wextra -Werror -I vl53l8cx_bridge
//       host/bridge_host.cpp vl53l8cx_bridge/bridge_protocol.cpp -o bridge_host   (one command line)
//   bridge_host [--sensor-missing] FD
//
// It prints "ready" once the banner and the first STATUS are written, serves until SIGTERM / SIGINT or
// until the descriptor reports end of file or fails, then prints its receiver's counters on one line:
//   commands=N crc_errors=N bad_headers=N malformed=N bytes_discarded=N
// (tests/test_firmware_host.py runs it against the Python driver.)

#include <errno.h>
#include <poll.h>
#include <signal.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>

#include "bridge_protocol.h"

namespace {

volatile sig_atomic_t g_stop = 0;

void on_signal(int) { g_stop = 1; }

using Clock = std::chrono::steady_clock;

class FdBoard : public bridge::Board {
 public:
  FdBoard(int fd, bool sensor_present) : fd_(fd), sensor_present_(sensor_present), t0_(Clock::now()) {}

  // Blocking, like a UART's transmit: a reader that falls behind slows the bridge down, nothing is lost.
  void write(const uint8_t *data, uint16_t n) override {
    while (n > 0 && !failed_ && !g_stop) {
      const ssize_t k = ::write(fd_, data, n);
      if (k < 0) {
        failed_ = errno != EINTR;
        continue;
      }
      data += k;
      n = static_cast<uint16_t>(n - k);
    }
  }
  uint32_t now_us() override {
    const auto us = std::chrono::duration_cast<std::chrono::microseconds>(Clock::now() - t0_).count();
    return static_cast<uint32_t>(us);  // wraps after 71.6 min, like Arduino's micros()
  }
  bool sensor_start() override { return sensor_present_; }
  bool sensor_stop() override { return sensor_present_; }
  bool sensor_configure(uint8_t, uint8_t) override { return sensor_present_; }

  bool failed() const { return failed_; }

 private:
  int fd_;
  bool sensor_present_;
  bool failed_ = false;
  Clock::time_point t0_;
};

// A measurement as ST's ULD reports it, in its zone order and with two targets per zone (of which the
// bridge sends the first). ULD zone u of the frame numbered seq has no target when u % 7 == 6, with
// values left over in the arrays that the bridge must not send; else a first target 200 + 10 u + seq % 50
// mm away, sigma 1 + u % 4 mm, reflectance 10 + u % 80 %, status 9 for every 5th zone, 4 (not a valid
// range) for the zone after it, 5 otherwise; and a second target 4 m away with status 5.
const uint8_t kTargets = 2;

struct UldMeasurement {
  uint8_t nb_target_detected[bridge::kMaxZones];
  int16_t distance_mm[bridge::kMaxZones * kTargets];
  uint16_t range_sigma_mm[bridge::kMaxZones * kTargets];
  uint8_t target_status[bridge::kMaxZones * kTargets];
  uint8_t reflectance[bridge::kMaxZones * kTargets];

  void synthesise(uint32_t seq, uint8_t resolution) {
    for (uint16_t u = 0; u < resolution * resolution; u++) {
      const bool empty = u % 7 == 6;
      const uint16_t t = kTargets * u;
      nb_target_detected[u] = empty ? 0 : 2;
      distance_mm[t] = static_cast<int16_t>(empty ? 1234 : 200 + 10 * u + seq % 50);
      range_sigma_mm[t] = static_cast<uint16_t>(empty ? 77 : 1 + u % 4);
      target_status[t] = empty ? 13 : (u % 5 == 4 ? 9 : (u % 5 == 0 && u > 0 ? 4 : 5));
      reflectance[t] = static_cast<uint8_t>(empty ? 66 : 10 + u % 80);
      distance_mm[t + 1] = 4000;
      range_sigma_mm[t + 1] = 9;
      target_status[t + 1] = 5;
      reflectance[t + 1] = 1;
    }
  }

  bridge::UldResults results() const {
    return bridge::UldResults{nb_target_detected, distance_mm, range_sigma_mm, target_status, reflectance,
                              kTargets};
  }
};

int usage(const char *program) {
  std::fprintf(stderr, "usage: %s [--sensor-missing] FD\n", program);
  return 2;
}

}  // namespace

int main(int argc, char **argv) {
  bool sensor_present = true;
  int fd = -1;
  for (int i = 1; i < argc; i++) {
    if (std::strcmp(argv[i], "--sensor-missing") == 0) {
      sensor_present = false;
      continue;
    }
    char *end = nullptr;
    const long value = std::strtol(argv[i], &end, 10);
    if (fd >= 0 || end == argv[i] || *end != '\0' || value < 0) return usage(argv[0]);
    fd = static_cast<int>(value);
  }
  if (fd < 0) return usage(argv[0]);

  struct sigaction action;
  std::memset(&action, 0, sizeof action);
  action.sa_handler = on_signal;  // no SA_RESTART: a blocked poll or write returns so that the loop ends
  sigaction(SIGTERM, &action, nullptr);
  sigaction(SIGINT, &action, nullptr);

  FdBoard board(fd, sensor_present);
  bridge::Bridge device(board);
  device.send_text("cell VL53L8CX bridge, host build, protocol 1");
  device.begin(sensor_present);
  std::printf("ready\n");
  std::fflush(stdout);

  UldMeasurement measurement;
  bridge::Zone zones[bridge::kMaxZones];
  Clock::time_point next_frame = Clock::now();
  bool was_ranging = false;
  while (!g_stop && !board.failed()) {
    const Clock::time_point now = Clock::now();
    if (device.ranging() && !was_ranging) next_frame = now;
    was_ranging = device.ranging();
    if (device.ranging() && now >= next_frame) {
      measurement.synthesise(device.next_seq(), device.resolution());
      bridge::zones_from_uld(zones, device.resolution(), measurement.results());
      device.send_ranging(zones);
      const auto period = std::chrono::microseconds(1000000 / device.frequency_hz());
      next_frame = next_frame + period > now ? next_frame + period : now + period;  // no burst to catch up
    }
    int timeout_ms = 100;
    if (device.ranging()) {
      const auto wait = std::chrono::ceil<std::chrono::milliseconds>(next_frame - Clock::now());
      timeout_ms = wait.count() < 0 ? 0 : static_cast<int>(wait.count());
    }
    pollfd p = {fd, POLLIN, 0};
    if (poll(&p, 1, timeout_ms) <= 0) continue;
    uint8_t buf[256];
    const ssize_t k = read(fd, buf, sizeof buf);
    if (k == 0 || (k < 0 && errno != EINTR && errno != EAGAIN)) break;  // end of file, or the link failed
    for (ssize_t i = 0; i < k; i++) device.receive(buf[i]);
  }

  const bridge::ReceiverStats &s = device.receiver_stats();
  std::printf("commands=%lu crc_errors=%lu bad_headers=%lu malformed=%lu bytes_discarded=%lu\n",
              static_cast<unsigned long>(s.commands), static_cast<unsigned long>(s.crc_errors),
              static_cast<unsigned long>(s.bad_headers), static_cast<unsigned long>(s.malformed),
              static_cast<unsigned long>(s.bytes_discarded));
  return 0;
}
