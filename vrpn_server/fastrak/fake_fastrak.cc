#include "vrpn_server/fastrak/fake_fastrak.h"

#include <fcntl.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <sstream>
#include <stdexcept>
#include <vector>

namespace trackcal::fastrak::testing {
namespace {

void AppendFloat32Le(float v, std::string* out) {
  uint32_t bits;
  std::memcpy(&bits, &v, sizeof(bits));
  for (int i = 0; i < 4; ++i) out->push_back(static_cast<char>((bits >> (8 * i)) & 0xff));
}

[[noreturn]] void Fail(const std::string& what) {
  throw std::runtime_error("FakeFastrak: " + what + ": " + std::strerror(errno));
}

}  // namespace

std::string MakeRecord(int station, const std::array<float, 3>& position,
                       const std::array<float, 4>& wxyz, char status, int stylus) {
  std::string r;
  r.push_back('0');
  r.push_back(static_cast<char>('0' + station));
  r.push_back(status);
  for (float v : position) AppendFloat32Le(v, &r);
  for (float v : wxyz) AppendFloat32Le(v, &r);
  if (stylus >= 0) {
    r.push_back(' ');
    r.push_back(stylus ? '1' : '0');
  }
  r.push_back(' ');
  return r;
}

std::string MakeStatusRecord() {
  std::string s = "21S0A0000";
  s += std::string(6, ' ');
  s += "  3.00";
  std::string id = "EMULATED POLHEMUS FASTRAK";
  id.resize(32, ' ');
  s += id;
  s += "\r\n";
  return s;
}

FakeFastrak::FakeFastrak(std::filesystem::path link, FakeFastrakOptions options)
    : link_(std::move(link)), options_(options) {
  if (::pipe2(wake_, O_CLOEXEC | O_NONBLOCK) != 0) Fail("pipe");
  PowerUp();
  OpenPty();
  thread_ = std::thread([this] { Loop(); });
}

FakeFastrak::~FakeFastrak() {
  stop_.store(true);
  const char b = 1;
  [[maybe_unused]] ssize_t n = ::write(wake_[1], &b, 1);
  thread_.join();
  std::error_code ec;
  std::filesystem::remove(link_, ec);  // (a stale link would name a reused pty number)
  ClosePty();
  ::close(wake_[0]);
  ::close(wake_[1]);
}

void FakeFastrak::PowerUp() {
  continuous_ = options_.start_streaming;
  binary_ = options_.start_streaming;
  metric_ = false;
  stylus_item_.fill(false);
  in_line_ = false;
  line_.clear();
}

void FakeFastrak::OpenPty() {
  master_ = ::posix_openpt(O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (master_ < 0) Fail("posix_openpt");
  if (::grantpt(master_) != 0 || ::unlockpt(master_) != 0) Fail("grantpt/unlockpt");
  const char* name = ::ptsname(master_);
  if (name == nullptr) Fail("ptsname");
  const std::string slave_path = name;
  // Keep a slave fd open in raw mode (a fresh pty echoes and translates CR until configured).
  slave_ = ::open(slave_path.c_str(), O_RDWR | O_NOCTTY | O_CLOEXEC);
  if (slave_ < 0) Fail("open slave");
  termios tio{};
  ::tcgetattr(slave_, &tio);
  ::cfmakeraw(&tio);
  ::tcsetattr(slave_, TCSANOW, &tio);
  // Atomic link replacement so the driver never sees a half-made link.
  const std::filesystem::path tmp = link_.string() + ".tmp";
  std::filesystem::remove(tmp);
  std::filesystem::create_symlink(slave_path, tmp);
  std::filesystem::rename(tmp, link_);
  next_record_ = std::chrono::steady_clock::now();
}

void FakeFastrak::ClosePty() {
  if (master_ >= 0) ::close(master_);
  if (slave_ >= 0) ::close(slave_);
  master_ = slave_ = -1;
}

std::string FakeFastrak::received() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return received_;
}

void FakeFastrak::ClearReceived() {
  std::lock_guard<std::mutex> lock(mutex_);
  received_.clear();
}

void FakeFastrak::SetMute(bool mute) {
  std::lock_guard<std::mutex> lock(mutex_);
  mute_ = mute;
}

void FakeFastrak::SetCorruptStatus(bool corrupt) {
  std::lock_guard<std::mutex> lock(mutex_);
  corrupt_status_ = corrupt;
}

void FakeFastrak::SetStylus(bool pressed) {
  std::lock_guard<std::mutex> lock(mutex_);
  stylus_pressed_ = pressed;
}

void FakeFastrak::SendGarbage(const std::string& bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  garbage_ += bytes;
}

void FakeFastrak::TruncateNextRecord(size_t keep_bytes) {
  std::lock_guard<std::mutex> lock(mutex_);
  truncate_next_ = keep_bytes;
}

void FakeFastrak::Unplug() {
  std::lock_guard<std::mutex> lock(mutex_);
  // Link first: once the pty is closed its number can go to another process's pty at once, and a
  // driver retrying the link must never reach that one.
  std::error_code ec;
  std::filesystem::remove(link_, ec);
  ClosePty();
}

void FakeFastrak::Plug(bool power_cycled) {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    if (power_cycled) PowerUp();
    OpenPty();
  }
  const char b = 0;
  [[maybe_unused]] ssize_t n = ::write(wake_[1], &b, 1);
}

bool FakeFastrak::continuous() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return continuous_;
}

bool FakeFastrak::metric() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return metric_;
}

int FakeFastrak::status_requests() const {
  std::lock_guard<std::mutex> lock(mutex_);
  return status_requests_;
}

void FakeFastrak::WriteOut(const std::string& bytes) {
  if (master_ < 0 || bytes.empty()) return;
  // Like a serial line, output nobody reads in time is lost rather than blocking the device.
  [[maybe_unused]] ssize_t n = ::write(master_, bytes.data(), bytes.size());
}

void FakeFastrak::HandleLine(const std::string& line, std::string* reply) {
  for (const auto& [query, answer] : options_.line_replies) {
    if (line == query) *reply += answer;
  }
  if (line.size() >= 2 && line[0] == 'O') {
    std::vector<int> items;
    std::stringstream in(line.substr(1));
    std::string field;
    while (std::getline(in, field, ',')) items.push_back(std::atoi(field.c_str()));
    if (!items.empty() && items[0] >= 1 && items[0] <= 4) {
      bool stylus = false;
      for (size_t i = 1; i < items.size(); ++i) stylus |= items[i] == 16;
      stylus_item_[items[0] - 1] = stylus;
    }
  }
  // x, v, e, H and anything else: accepted and ignored (the driver does not check them either).
}

void FakeFastrak::HandleInput(const char* data, size_t n, std::string* reply) {
  received_.append(data, n);
  if (mute_) return;
  for (size_t i = 0; i < n; ++i) {
    const char c = data[i];
    if (in_line_) {
      if (c == '\r' || c == '\n') {
        HandleLine(line_, reply);
        in_line_ = false;
        line_.clear();
      } else {
        line_.push_back(c);
      }
      continue;
    }
    switch (c) {
      case 'c':
        continuous_ = false;
        break;
      case 'C':
        continuous_ = true;
        next_record_ = std::chrono::steady_clock::now();
        break;
      case 'f':
        binary_ = true;
        break;
      case 'F':
        binary_ = false;
        break;
      case 'u':
        metric_ = true;
        break;
      case 'U':
        metric_ = false;
        break;
      case 'S': {
        ++status_requests_;
        if (options_.status_delay_s > 0.0) {
          WriteOut(*reply);  // the answers before `S` leave first
          reply->clear();
          std::this_thread::sleep_for(std::chrono::duration<double>(options_.status_delay_s));
        }
        const std::string status =
            options_.status_record.empty() ? MakeStatusRecord() : options_.status_record;
        const bool corrupt = corrupt_status_ || (options_.corrupt_status_from > 0 &&
                                                 status_requests_ >= options_.corrupt_status_from);
        *reply += corrupt ? status.substr(0, status.size() - 1) : status;  // LF missing
        break;
      }
      case 0x19:
        PowerUp();
        break;
      case '\r':
      case '\n':
      case 't':
      case 'Y':
        break;
      default:
        in_line_ = true;
        line_.assign(1, c);
    }
  }
}

void FakeFastrak::Loop() {
  std::vector<char> buffer(4096);
  while (!stop_.load()) {
    int master;
    int timeout_ms = 50;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      master = master_;
      if (continuous_ && binary_ && !mute_) {
        const auto wait = next_record_ - std::chrono::steady_clock::now();
        timeout_ms = static_cast<int>(
            std::max<int64_t>(0, std::chrono::ceil<std::chrono::milliseconds>(wait).count()));
      }
    }
    pollfd fds[2] = {{wake_[0], POLLIN, 0}, {master, POLLIN, 0}};
    ::poll(fds, master >= 0 ? 2 : 1, timeout_ms);
    if (fds[0].revents & POLLIN) {
      char drain[16];
      while (::read(wake_[0], drain, sizeof(drain)) > 0) {
      }
    }
    std::lock_guard<std::mutex> lock(mutex_);
    if (master_ < 0 || master_ != master) continue;
    if (fds[1].revents & POLLIN) {
      const ssize_t n = ::read(master_, buffer.data(), buffer.size());
      if (n > 0) {
        std::string reply;
        HandleInput(buffer.data(), static_cast<size_t>(n), &reply);
        WriteOut(reply);
      }
    }
    const auto now = std::chrono::steady_clock::now();
    if (continuous_ && binary_ && !mute_ && now >= next_record_) {
      next_record_ += std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(1.0 / options_.rate_hz));
      if (next_record_ < now) next_record_ = now;  // do not burst after a pause
      std::string out = garbage_;
      garbage_.clear();
      for (int s = 1; s <= options_.num_stations; ++s) {
        std::array<float, 3> p = options_.position_in[s - 1];
        if (metric_) {
          for (float& v : p) v *= 2.54f;
        }
        std::string record = MakeRecord(s, p, options_.wxyz[s - 1], ' ',
                                        stylus_item_[s - 1] ? (stylus_pressed_ ? 1 : 0) : -1);
        if (truncate_next_ > 0) {
          record.resize(std::min(truncate_next_, record.size()));
          truncate_next_ = 0;
        }
        out += record;
      }
      WriteOut(out);
    }
  }
}

}  // namespace trackcal::fastrak::testing
