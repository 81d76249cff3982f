// Incremental parser of the Fastrak's continuous binary records. Bytes are fed as they are read;
// records come out converted to trackcal conventions (metres, Eigen quaternion, 0-based sensor).
//
// Resynchronisation: a candidate record must pass every framing check of DecodeRecord; when one
// fails, only its first byte is dropped and the search restarts at the next byte, so good records
// that follow garbage (or a truncated record) in the same read are kept. (The reference driver
// flushes the whole input buffer instead and loses them.) A candidate followed, in bytes already
// received, by something other than a record header loses to a valid record starting inside it.

#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <array>
#include <chrono>
#include <cstdint>
#include <optional>
#include <span>
#include <vector>

#include "vrpn_server/fastrak/protocol.h"

namespace trackcal::fastrak {

// One pose report of one sensor, in trackcal units and frames (the Fastrak transmitter frame).
struct FastrakReport {
  int sensor = 0;                                              // 0-based (station - 1)
  Eigen::Vector3d position_m = Eigen::Vector3d::Zero();        // receiver origin in the transmitter frame
  Eigen::Quaterniond rotation = Eigen::Quaterniond::Identity();  // transmitter_from_receiver
  std::chrono::system_clock::time_point time;                  // host time at the record's first byte
  char status = ' ';                                           // device status byte (' ' = OK)
  std::optional<bool> stylus_pressed;                          // if the station reports item 16
};

// Converts a decoded record: position x metres-per-unit, wire W,X,Y,Z -> Eigen (no normalisation,
// as the reference; the device's quaternion is unit to float precision).
FastrakReport ConvertRecord(const RawRecord& raw, Units units,
                            std::chrono::system_clock::time_point time);

class RecordParser {
 public:
  using TimePoint = std::chrono::system_clock::time_point;

  // `stylus[s]`: station s+1 has output item 16 (34-byte records).
  RecordParser(std::array<bool, kMaxStations> stylus, Units units);

  // Appends bytes read at `read_time` (every byte of the chunk is stamped with it; a record takes
  // the stamp of its first byte) and appends every complete valid record to *reports.
  void Feed(std::span<const uint8_t> bytes, TimePoint read_time, std::vector<FastrakReport>* reports);

  // Drops buffered bytes (after a flush of the port or a reset).
  void Clear();

  void set_units(Units units) { units_ = units; }
  Units units() const { return units_; }

  // Bytes discarded while searching for record boundaries, since construction.
  uint64_t discarded_bytes() const { return discarded_bytes_; }
  // Valid records produced since construction.
  uint64_t records() const { return records_; }
  // Bytes waiting for the rest of their record.
  size_t buffered_bytes() const { return bytes_.size() - head_; }

 private:
  void Compact();
  bool ConfirmedByWhatFollows(const uint8_t* p, size_t size, size_t available) const;

  std::array<bool, kMaxStations> stylus_;
  Units units_;
  std::vector<uint8_t> bytes_;
  std::vector<TimePoint> times_;  // read time of each buffered byte
  size_t head_ = 0;
  uint64_t discarded_bytes_ = 0;
  uint64_t records_ = 0;
};

}  // namespace trackcal::fastrak
