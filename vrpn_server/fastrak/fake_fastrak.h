// Test support: Fastrak record bytes and a small scripted Fastrak on a pseudo-terminal, so the
// driver's tests need neither hardware nor the full emulator (sim/emulator).
//
// FakeFastrak answers `S` with a 55-byte status record, honours `c` `C` `f` `F` `u` `U` ^Y and `O`
// output lists (item 16 = stylus), streams binary records at a fixed rate per station after `C`, and
// logs every byte the host wrote. Faults: mute (no answers, no records), garbage bytes, truncated
// records, unplug/plug (the pty is closed and a new one is linked at the same path) and power cycle.

#pragma once

#include <array>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <mutex>
#include <string>
#include <thread>
#include <utility>
#include <vector>

namespace trackcal::fastrak::testing {

// Binary record (output list 2,11[,16],0) as the Fastrak sends it: '0', station digit, status,
// x y z (float32 LE, device units), w x y z, [' ' + '0'/'1'], ' '.
std::string MakeRecord(int station, const std::array<float, 3>& position,
                       const std::array<float, 4>& wxyz, char status = ' ', int stylus = -1);
// The status record as the reference emulator sends it (transcript 07 offset 0).
std::string MakeStatusRecord();

struct FakeFastrakOptions {
  int num_stations = 2;  // receivers plugged in (stations 1..n stream)
  double rate_hz = 60.0;  // records per second per station
  bool start_streaming = false;  // power up continuous + binary (as transcript 08's emulator)
  // Reply to `S`; empty: MakeStatusRecord(). Another unit's reply (a 54-byte IS-900 status) or
  // firmware whose fields differ from the Fastrak's layout.
  std::string status_record;
  // From the n-th `S` on (1-based; 0 = never) the reply loses its final LF, as SetCorruptStatus:
  // replies that go wrong at a given step of the reset (3: the round trip after the extras).
  int corrupt_status_from = 0;
  // The unit is busy this long before it answers `S` (and reads nothing meanwhile): a driver that
  // goes on before the reply finds the reply's bytes in its record stream.
  double status_delay_s = 0.0;
  // Replies to line commands (without their CR), e.g. {"H1", "21H  1.00  0.00  0.00\r\n"}: a
  // query among the extra commands.
  std::vector<std::pair<std::string, std::string>> line_replies;
  // Pose of each station in inches and wire order w, x, y, z (transcript 07's values).
  std::array<std::array<float, 3>, 4> position_in = {{{10, -5, 20}, {1.5f, 2.5f, -3.5f}, {0, 0, 1}, {0, 0, 2}}};
  std::array<std::array<float, 4>, 4> wxyz = {{{0.73029674f, 0.18257418f, 0.36514837f, 0.54772256f},
                                               {1, 0, 0, 0},
                                               {1, 0, 0, 0},
                                               {1, 0, 0, 0}}};
};

class FakeFastrak {
 public:
  // Creates the pty and a symbolic link `link` to its slave; starts the device thread.
  FakeFastrak(std::filesystem::path link, FakeFastrakOptions options);
  ~FakeFastrak();

  // Every byte the host wrote so far (across unplugs).
  std::string received() const;
  void ClearReceived();

  void SetMute(bool mute);              // ignore input, send nothing (a dead or disconnected unit)
  void SetCorruptStatus(bool corrupt);  // answer `S` with a 54-byte record (LF missing)
  void SetStylus(bool pressed);    // stylus switch of every station with item 16
  void SendGarbage(const std::string& bytes);  // written before the next record
  void TruncateNextRecord(size_t keep_bytes);  // next record is cut after keep_bytes
  void Unplug();                   // close the pty (hang-up for the host) and remove the link
  void Plug(bool power_cycled);    // new pty at the same link; power_cycled = back to power-up state

  bool continuous() const;
  bool metric() const;
  int status_requests() const;

 private:
  void OpenPty();
  void ClosePty();
  void Loop();
  void HandleInput(const char* data, size_t n, std::string* reply);
  void HandleLine(const std::string& line, std::string* reply);
  void PowerUp();
  void WriteOut(const std::string& bytes);

  std::filesystem::path link_;
  FakeFastrakOptions options_;
  mutable std::mutex mutex_;
  int master_ = -1;
  int slave_ = -1;
  int wake_[2] = {-1, -1};
  std::thread thread_;
  std::atomic<bool> stop_{false};
  // Device state (guarded by mutex_).
  std::string received_;
  bool mute_ = false;
  bool corrupt_status_ = false;
  bool continuous_ = false;
  bool binary_ = false;
  bool metric_ = false;
  bool stylus_pressed_ = false;
  std::array<bool, 4> stylus_item_{};
  std::string line_;
  bool in_line_ = false;
  std::string garbage_;
  size_t truncate_next_ = 0;
  int status_requests_ = 0;
  std::chrono::steady_clock::time_point next_record_;
};

}  // namespace trackcal::fastrak::testing
