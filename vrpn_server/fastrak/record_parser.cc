#include "vrpn_server/fastrak/record_parser.h"

#include <algorithm>
#include <cmath>

#include "core/pose.h"

namespace trackcal::fastrak {

FastrakReport ConvertRecord(const RawRecord& raw, Units units,
                            std::chrono::system_clock::time_point time) {
  FastrakReport report;
  report.sensor = raw.station - 1;
  const double scale = MetresPerUnit(units);
  report.position_m = Eigen::Vector3d(raw.position[0], raw.position[1], raw.position[2]) * scale;
  report.rotation = QuaternionFromWxyz<double>(raw.wxyz[0], raw.wxyz[1], raw.wxyz[2], raw.wxyz[3]);
  report.time = time;
  report.status = raw.status;
  report.stylus_pressed = raw.stylus;
  return report;
}

RecordParser::RecordParser(std::array<bool, kMaxStations> stylus, Units units, int num_stations,
                           int baud)
    : stylus_(stylus),
      units_(units),
      num_stations_(std::clamp(num_stations, 1, kMaxStations)),
      max_record_spread_(MaxRecordSpread(baud)),
      byte_time_(static_cast<int64_t>(std::llround(10.0 * 1e9 / std::max(baud, 1)))) {}

std::chrono::milliseconds RecordParser::MaxRecordSpread(int baud) {
  // 10 bits per byte on the line (start, 8 data, stop), the longest record 34 bytes.
  const double line_ms = 34.0 * 10.0 * 1000.0 / std::max(baud, 1);
  return std::max(kMaxRecordSpread, std::chrono::milliseconds(static_cast<int64_t>(3.0 * line_ms)));
}

void RecordParser::Clear() {
  bytes_.clear();
  times_.clear();
  head_ = 0;
}

void RecordParser::Compact() {
  if (head_ == 0) return;
  bytes_.erase(bytes_.begin(), bytes_.begin() + static_cast<std::ptrdiff_t>(head_));
  times_.erase(times_.begin(), times_.begin() + static_cast<std::ptrdiff_t>(head_));
  head_ = 0;
}

bool RecordParser::IsHeader(const uint8_t* p) const {
  return p[0] == '0' && p[1] >= '1' && p[1] <= '0' + num_stations_;
}

bool RecordParser::IsAnyStationHeader(const uint8_t* p) {
  return p[0] == '0' && p[1] >= '1' && p[1] <= '0' + kMaxStations;
}

std::optional<RawRecord> RecordParser::Plausible(size_t at, size_t size) const {
  const uint8_t* p = bytes_.data() + at;
  if (!IsHeader(p)) return std::nullopt;
  std::optional<RawRecord> raw = DecodeRecord(p, size);
  if (!raw) return std::nullopt;
  const double scale = MetresPerUnit(units_);
  const double range_m =
      std::sqrt(static_cast<double>(raw->position[0]) * raw->position[0] +
                static_cast<double>(raw->position[1]) * raw->position[1] +
                static_cast<double>(raw->position[2]) * raw->position[2]) * scale;
  if (!(range_m <= kMaxRangeM)) return std::nullopt;
  if (times_[at + size - 1] - times_[at] > max_record_spread_) return std::nullopt;
  return raw;
}

RecordParser::Verdict RecordParser::Judge(size_t at, size_t size) const {
  const uint8_t* p = bytes_.data() + at;
  const size_t available = bytes_.size() - at;
  // Stations that are not configured still stream (in a layout we did not set): their records
  // follow and are followed by ours.
  const bool followed_by_header = available >= size + 2 && IsAnyStationHeader(p + size);
  // Every record header inside the candidate must be ruled out: a truncated record followed by a
  // fresh one looks like this, and can pass every field check (no checksum).
  for (size_t j = 1; j < size; ++j) {
    if (p[j] != '0') continue;
    if (j + 1 >= available) return Verdict::kWait;  // a '0' at the very end: header or not?
    if (!IsAnyStationHeader(p + j)) continue;
    if (IsHeader(p + j)) {
      const size_t inner_size = RecordSize(stylus_[p[j + 1] - '1']);
      if (j + inner_size > available) return Verdict::kWait;
      if (Plausible(at + j, inner_size)) {
        // Both are plausible; at most one is real. The candidate wins only if it is followed by a
        // header and the inner record is known not to be.
        if (available < size + 2) return Verdict::kWait;
        if (!followed_by_header) return Verdict::kReject;
        if (j + inner_size + 2 > available) return Verdict::kWait;
        if (IsAnyStationHeader(p + j + inner_size)) return Verdict::kReject;
        continue;
      }
    }
    // A record may start here that cannot be checked: one of a station we did not configure
    // (layout unknown), or one damaged itself (a second truncation, a byte lost on the line). Only
    // a record header right after the candidate shows that the candidate is whole.
    if (available < size + 2) return Verdict::kWait;
    if (!followed_by_header) return Verdict::kReject;
  }
  return Verdict::kAccept;
}

void RecordParser::Feed(std::span<const uint8_t> bytes, TimePoint read_time,
                        std::vector<FastrakReport>* reports) {
  bytes_.insert(bytes_.end(), bytes.begin(), bytes.end());
  for (size_t j = 0; j < bytes.size(); ++j) {
    const auto after = static_cast<int64_t>(bytes.size() - 1 - j);  // bytes on the line after it
    times_.push_back(read_time -
                     std::chrono::duration_cast<TimePoint::duration>(byte_time_ * after));
  }
  while (head_ < bytes_.size()) {
    const size_t available = bytes_.size() - head_;
    const uint8_t* p = bytes_.data() + head_;
    if (p[0] != '0') {  // not the start of a record
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    if (available < 2) break;
    if (!IsHeader(p)) {
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    const size_t size = RecordSize(stylus_[p[1] - '1']);
    if (available < size) break;
    std::optional<RawRecord> raw = Plausible(head_, size);
    if (raw) {
      const Verdict verdict = Judge(head_, size);
      if (verdict == Verdict::kWait) break;
      if (verdict == Verdict::kReject) {
        raw.reset();
        ++rejected_candidates_;
      }
    } else if (DecodeRecord(p, size)) {
      ++rejected_candidates_;  // well framed but implausible
    }
    if (!raw) {
      // Drop only the false start: the next record may begin inside this window.
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    TimePoint time = times_[head_];
    if (last_report_time_ && time <= *last_report_time_ && *last_report_time_ - time < kClockStep) {
      time = *last_report_time_ + std::chrono::microseconds(1);
    }
    last_report_time_ = time;
    reports->push_back(ConvertRecord(*raw, units_, time));
    ++records_;
    head_ += size;
  }
  if (head_ > 4096 || head_ == bytes_.size()) Compact();
}

}  // namespace trackcal::fastrak
