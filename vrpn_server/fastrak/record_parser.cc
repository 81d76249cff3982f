#include "vrpn_server/fastrak/record_parser.h"

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

RecordParser::RecordParser(std::array<bool, kMaxStations> stylus, Units units)
    : stylus_(stylus), units_(units) {}

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

bool RecordParser::ConfirmedByWhatFollows(const uint8_t* p, size_t size, size_t available) const {
  // Without a checksum a truncated record plus the start of the next one can pass every check
  // (e.g. a record cut 3 bytes short, an identity quaternion whose last float absorbs "0N", and the
  // next record's status space as the final byte). When the bytes after the candidate are already
  // here and are not a record header, prefer a valid record starting inside the candidate.
  // Waiting for bytes that have not arrived would add latency, so a lone candidate is accepted.
  if (available < size + 2) return true;
  const uint8_t* next = p + size;
  if (next[0] == '0' && next[1] >= '1' && next[1] <= '0' + kMaxStations) return true;
  for (size_t j = 1; j + 1 < size; ++j) {
    if (p[j] != '0' || p[j + 1] < '1' || p[j + 1] > '0' + kMaxStations) continue;
    const size_t inner_size = RecordSize(stylus_[p[j + 1] - '1']);
    if (j + inner_size <= available && DecodeRecord(p + j, inner_size)) return false;
  }
  return true;
}

void RecordParser::Feed(std::span<const uint8_t> bytes, TimePoint read_time,
                        std::vector<FastrakReport>* reports) {
  bytes_.insert(bytes_.end(), bytes.begin(), bytes.end());
  times_.insert(times_.end(), bytes.size(), read_time);
  while (head_ < bytes_.size()) {
    const size_t available = bytes_.size() - head_;
    const uint8_t* p = bytes_.data() + head_;
    if (p[0] != '0') {  // not the start of a record
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    if (available < 2) break;
    if (p[1] < '1' || p[1] > '0' + kMaxStations) {
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    const size_t size = RecordSize(stylus_[p[1] - '1']);
    if (available < size) break;
    std::optional<RawRecord> raw = DecodeRecord(p, size);
    if (raw && !ConfirmedByWhatFollows(p, size, available)) raw.reset();
    if (!raw) {
      // Drop only the false start: the next record may begin inside this window.
      ++head_;
      ++discarded_bytes_;
      continue;
    }
    reports->push_back(ConvertRecord(*raw, units_, times_[head_]));
    ++records_;
    head_ += size;
  }
  if (head_ > 4096 || head_ == bytes_.size()) Compact();
}

}  // namespace trackcal::fastrak
