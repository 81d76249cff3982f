// Incremental parser of the Fastrak's continuous binary records. Bytes are fed as they are read;
// records come out converted to trackcal conventions (metres, Eigen quaternion, 0-based sensor).
//
// Resynchronisation: a candidate record must pass every framing check of DecodeRecord and the
// plausibility checks below; when one fails, only its first byte is dropped and the search restarts
// at the next byte, so good records that follow garbage (or a truncated record) in the same read
// are kept. (The reference driver flushes the whole input buffer instead and loses them.)
//
// There is no checksum in the binary format, so a truncated record followed by a fresh one can
// pass every field check (the fresh record's header and status space absorbed into the last
// float). Such a merged window always contains the header of the real record that follows it.
// Hence the rule that makes a silently wrong pose impossible from truncation or a reconnect: a
// candidate is only emitted once every record header inside it has been ruled out, which may mean
// waiting for up to one more record's bytes (latency only when the float bytes of a record happen
// to contain "0<station>"). A candidate that a valid record inside it contradicts is dropped,
// unless the candidate is followed by a record header and the inner one is not. A header inside it
// that starts no checkable record (a station not configured, or a record damaged itself) is ruled
// out only by a record header right after the candidate. (Left: a truncated record completed by a
// fresh one that is cut exactly where a whole record would end, so that a header follows.)
// Plausibility (docs/fastrak-driver.md "What the driver rejects"): configured station, status
// space or letter, finite values, |q| within kMaxQuaternionNormError of 1, position within
// kMaxRangeM of the transmitter, and the record's bytes read within kMaxRecordSpread of each other.

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

  // `stylus[s]`: station s+1 has output item 16 (34-byte records). Records of stations above
  // `num_stations` (not configured) are rejected.
  // `baud`: the line's rate, which sets how far apart a record's bytes may be read
  // (MaxRecordSpread).
  RecordParser(std::array<bool, kMaxStations> stylus, Units units, int num_stations = kMaxStations,
               int baud = 115200);

  // A record whose first and last bytes were read further apart than this is rejected: at any
  // baud rate >= 9600 a record takes < 40 ms on the line, so a gap this long means the device (or
  // the cable) stopped in the middle of a record, and the rest is not the same record. Generous,
  // so that a reader thread descheduled on a loaded host does not drop records.
  static constexpr std::chrono::milliseconds kMaxRecordSpread{1000};
  // The limit at `baud`: kMaxRecordSpread, or three times the longest (34-byte) record's time on
  // the line if that is longer (300 baud: 1.13 s on the line, 3.4 s limit).
  static std::chrono::milliseconds MaxRecordSpread(int baud);
  // No Fastrak measures beyond 30 ft (9.14 m, long-range transmitter); |position| above this
  // (in metres, after unit conversion) is a mis-framed record.
  static constexpr double kMaxRangeM = 10.0;
  // A report stamped this much before the previous one is a step of the host clock (NTP), taken as
  // it is; a smaller step back (a chunk back-dated past the previous read) is moved after it.
  static constexpr std::chrono::milliseconds kClockStep{1000};

  // Appends bytes read at `read_time` and appends every complete valid record to *reports. A record
  // takes the stamp of its first byte: `read_time` less the line time of the bytes after it in the
  // chunk (10 bits per byte at the baud rate), so records that piled up and were read together get
  // their times on the line rather than one shared time. Reports' times strictly increase (by 1 us
  // at least) unless the clock stepped back more than kClockStep.
  void Feed(std::span<const uint8_t> bytes, TimePoint read_time, std::vector<FastrakReport>* reports);

  // Drops buffered bytes (after a flush of the port, a reset, or a port close/reopen: a record is
  // never assembled from bytes of two port openings).
  void Clear();

  void set_units(Units units) { units_ = units; }
  Units units() const { return units_; }

  // Bytes discarded while searching for record boundaries, since construction.
  uint64_t discarded_bytes() const { return discarded_bytes_; }
  // Valid records produced since construction.
  uint64_t records() const { return records_; }
  // Candidates that passed DecodeRecord but were rejected (implausible, or contradicted by a
  // record starting inside them), since construction.
  uint64_t rejected_candidates() const { return rejected_candidates_; }
  // Bytes waiting for the rest of their record.
  size_t buffered_bytes() const { return bytes_.size() - head_; }

 private:
  enum class Verdict { kAccept, kReject, kWait };
  void Compact();
  bool IsHeader(const uint8_t* p) const;  // '0' then a configured station digit
  static bool IsAnyStationHeader(const uint8_t* p);  // '0' then a station digit 1..4
  // DecodeRecord plus the parser's plausibility checks on the record at buffer offset `at`.
  std::optional<RawRecord> Plausible(size_t at, size_t size) const;
  Verdict Judge(size_t at, size_t size) const;

  std::array<bool, kMaxStations> stylus_;
  Units units_;
  int num_stations_;
  std::chrono::milliseconds max_record_spread_;
  std::chrono::nanoseconds byte_time_;  // one byte's time on the line
  std::optional<TimePoint> last_report_time_;
  std::vector<uint8_t> bytes_;
  std::vector<TimePoint> times_;  // read time of each buffered byte
  size_t head_ = 0;
  uint64_t discarded_bytes_ = 0;
  uint64_t records_ = 0;
  uint64_t rejected_candidates_ = 0;
};

}  // namespace trackcal::fastrak
