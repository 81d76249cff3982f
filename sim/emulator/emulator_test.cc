// The emulator over a real pseudo-terminal: a test client behaves like VRPN's vrpn_Tracker_Fastrak
// (port settings of FASTRAK.md section 2, reset sequence of section 4 without its sleeps) and
// checks records byte by byte; each fault is injected through the control socket and observed on
// the line.

#include "sim/emulator/emulator.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/resource.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <termios.h>
#include <unistd.h>

#include <chrono>
#include <fstream>
#include <iterator>
#include <set>
#include <thread>

#include "tests/test_utils.h"

namespace trackcal::emulator {
namespace {

using Clock = std::chrono::steady_clock;

double SecondsSince(Clock::time_point t0) {
  return std::chrono::duration<double>(Clock::now() - t0).count();
}

std::string ReadFile(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  EXPECT_TRUE(in) << path;
  return std::string(std::istreambuf_iterator<char>(in), {});
}

std::filesystem::path Transcript07() {
  return testing::SourceDir() / "tests/data/fastrak/07_fastrak_emulated_tcp";
}

// The two stations of transcripts 07/08 (FASTRAK.md section 11), in metres.
std::vector<Rigid3d> TranscriptPoses() {
  return {
      Rigid3d(QuaternionFromWxyz(4.0, 1.0, 2.0, 3.0).normalized(),
              Eigen::Vector3d(10, -5, 20) * kMetresPerInch),
      Rigid3d(Eigen::Quaterniond::Identity(), Eigen::Vector3d(1.5, 2.5, -3.5) * kMetresPerInch)};
}

// A serial port opened and configured the way the reference driver does it.
class SerialClient {
 public:
  explicit SerialClient(const std::string& path) {
    fd_ = open(path.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK);
    if (fd_ < 0) return;
    termios tio{};
    tcgetattr(fd_, &tio);
    tio.c_iflag = IGNBRK | IGNPAR;
    tio.c_oflag = 0;
    tio.c_lflag = 0;
    tio.c_cflag = CS8 | CREAD | CLOCAL;
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    cfsetispeed(&tio, B115200);
    cfsetospeed(&tio, B115200);
    tcsetattr(fd_, TCSANOW, &tio);
  }
  ~SerialClient() {
    if (fd_ >= 0) close(fd_);
  }
  bool ok() const { return fd_ >= 0; }
  bool hung_up() const { return hung_up_; }

  void Write(std::string_view bytes) {
    ASSERT_EQ(write(fd_, bytes.data(), bytes.size()), static_cast<ssize_t>(bytes.size()));
  }
  void FlushInput() { tcflush(fd_, TCIFLUSH); }

  // Reads until `n` bytes arrived or `timeout_s` passed.
  std::string ReadExactly(size_t n, double timeout_s) {
    std::string out;
    const auto t0 = Clock::now();
    while (out.size() < n && !hung_up_) {
      const double left = timeout_s - SecondsSince(t0);
      if (left <= 0) break;
      ReadSome(n - out.size(), left, &out);
    }
    return out;
  }

  // Reads what arrives during `duration_s`; `arrivals` gets (time, bytes so far) per chunk.
  std::string ReadFor(double duration_s,
                      std::vector<std::pair<double, size_t>>* arrivals = nullptr) {
    std::string out;
    const auto t0 = Clock::now();
    while (!hung_up_) {
      const double left = duration_s - SecondsSince(t0);
      if (left <= 0) break;
      if (ReadSome(1 << 16, left, &out) && arrivals)
        arrivals->push_back({SecondsSince(t0), out.size()});
    }
    return out;
  }

 private:
  bool ReadSome(size_t max, double timeout_s, std::string* out) {
    pollfd p{fd_, POLLIN, 0};
    const int r = poll(&p, 1, std::max(1, static_cast<int>(timeout_s * 1000)));
    if (r <= 0) return false;
    char buffer[4096];
    const ssize_t n = read(fd_, buffer, std::min(max, sizeof(buffer)));
    if (n > 0) {
      out->append(buffer, n);
      return true;
    }
    // The emulator closed the pty: EIO (or an end of file) with POLLHUP.
    if ((n < 0 && errno == EIO) || (p.revents & POLLHUP)) hung_up_ = true;
    return false;
  }

  int fd_ = -1;
  bool hung_up_ = false;
};

// One line in, one line out on the control socket.
std::string Control(const std::string& socket_path, const std::string& line) {
  const int fd = socket(AF_UNIX, SOCK_STREAM, 0);
  sockaddr_un addr{};
  addr.sun_family = AF_UNIX;
  std::strncpy(addr.sun_path, socket_path.c_str(), sizeof(addr.sun_path) - 1);
  if (connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) != 0) {
    close(fd);
    return "connect failed";
  }
  const std::string request = line + "\n";
  send(fd, request.data(), request.size(), MSG_NOSIGNAL);
  std::string reply;
  char c;
  pollfd p{fd, POLLIN, 0};
  while (poll(&p, 1, 2000) > 0 && read(fd, &c, 1) == 1 && c != '\n') reply += c;
  close(fd);
  return reply;
}

// Splits a record stream into the expected records and everything else. Returns the blocks of
// unexpected bytes (adjacent bytes merged); a trailing prefix of a record is left in `stream`.
// `records_after_last_block` (optional) counts the whole records after the last block.
std::vector<std::string> StripRecords(std::string* stream, const std::vector<std::string>& records,
                                      int* num_records, int* records_after_last_block = nullptr) {
  std::vector<std::string> blocks;
  size_t pos = 0;
  bool in_block = false;
  int after = 0;
  while (pos < stream->size()) {
    bool matched = false;
    bool partial = false;
    for (const std::string& r : records) {
      const size_t n = std::min(r.size(), stream->size() - pos);
      if (stream->compare(pos, n, r, 0, n) == 0) {
        if (n == r.size()) {
          matched = true;
          pos += n;
          ++*num_records;
          ++after;
        } else {
          partial = true;
        }
        break;
      }
    }
    if (partial) break;
    if (matched) {
      in_block = false;
      continue;
    }
    if (!in_block) blocks.emplace_back();
    in_block = true;
    after = 0;
    blocks.back() += (*stream)[pos++];
  }
  stream->erase(0, pos);
  if (records_after_last_block) *records_after_last_block = after;
  return blocks;
}

// Reads a record stream, starting with the record prefix left in *pending by an earlier read (a
// read may end anywhere in a record, as on a serial line), until `count` blocks of unexpected bytes
// have been seen and followed by 3 whole records (so the last block is complete), or 3 s passed (a
// loaded machine may delay the fault by far more than its record period). Returns the blocks and
// leaves the trailing record prefix in *pending.
std::vector<std::string> ReadBlocks(SerialClient* client, const std::vector<std::string>& records,
                                    size_t count, std::string* pending) {
  std::string all = *pending;
  std::string copy;
  std::vector<std::string> blocks;
  const auto t0 = Clock::now();
  while (SecondsSince(t0) < 3.0) {
    all += client->ReadFor(0.05);
    copy = all;
    int n = 0, after = 0;
    blocks = StripRecords(&copy, records, &n, &after);
    if (blocks.size() >= count && after >= 3) break;
  }
  *pending = copy;
  return blocks;
}

class EmulatorTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = testing::MakeTempDir("emulator");
    options_.link_path = (dir_ / "fastrak").string();
    options_.control_socket_path = (dir_ / "control.sock").string();
    options_.device.num_stations = 2;
    // Power-up state chosen to exercise the driver's `c` + flush: ASCII records stream at once.
    options_.device.continuous = true;
    source_ = std::make_unique<ControlledPoseSource>(
        std::make_unique<StaticPoseSource>(TranscriptPoses()));
  }
  void TearDown() override { Stop(); }

  void Start() {
    emulator_ = std::make_unique<Emulator>(options_, source_.get(), &model_);
    emulator_->Start();
    thread_ = std::thread([this] { emulator_->Run(); });
  }
  void Stop() {
    if (!emulator_) return;
    emulator_->RequestStop();
    thread_.join();
    emulator_.reset();
  }
  std::string Control(const std::string& line) {
    return emulator::Control(options_.control_socket_path, line);
  }
  // Moves station 1 to a new pose; returns the record the device reports for it from then on.
  std::string MoveStation1() {
    EXPECT_EQ(Control("move 1 0.1 0.2 0.3 1 0 0 0"), "ok");
    const Rigid3d moved(QuaternionFromWxyz(1.0, 0.0, 0.0, 0.0), Eigen::Vector3d(0.1, 0.2, 0.3));
    return FastrakDevice(options_.device).FormatRecord(1, StationMeasurement{moved, false});
  }

  // The reset sequence of transcript 07 with the driver's flushes but none of its sleeps. Leaves
  // the client with a record-aligned binary stream started.
  void Handshake(SerialClient* client, const std::string& host_lines) {
    const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
    client->Write("c");
    // The driver sleeps 2 s, flushes, sleeps 2 s, flushes; 50 ms covers the emulator's reaction.
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    client->FlushInput();
    EXPECT_EQ(client->ReadFor(0.05), "") << "the device kept streaming after 'c'";
    client->FlushInput();
    const auto t_status = Clock::now();
    client->Write("S");
    const std::string status = client->ReadExactly(55, 1.0);  // deadline of the driver
    EXPECT_LT(SecondsSince(t_status), 1.0);
    EXPECT_EQ(status, device_bytes.substr(0, 55));
    client->Write(host_lines);
    EXPECT_EQ(client->ReadFor(0.05), "") << "output before 'C'";
    const auto t_start = Clock::now();
    client->Write("fC");
    const std::string first = client->ReadExactly(1, 2.0);
    EXPECT_LT(SecondsSince(t_start), 2.0);  // the driver's watchdog
    stream_ = first;
  }

  std::filesystem::path dir_;
  EmulatorOptions options_;
  std::unique_ptr<ControlledPoseSource> source_;
  PerfectMeasurement model_;
  std::unique_ptr<Emulator> emulator_;
  std::thread thread_;
  std::string stream_;  // bytes read since 'C' and not yet analysed
};

// The host bytes of transcript 07 between 'S' and "fC": four output lists and the two filters.
std::string Transcript07Lines() {
  const std::string host = ReadFile(Transcript07() / "serial_host_to_device.bin");
  EXPECT_EQ(host.substr(0, 2), "cS");
  EXPECT_EQ(host.substr(host.size() - 2), "fC");
  return host.substr(2, host.size() - 4);
}

TEST_F(EmulatorTest, Nominal) {
  Start();
  ASSERT_TRUE(std::filesystem::is_symlink(options_.link_path));
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  Handshake(&client, Transcript07Lines());
  // 30 records alternate station 1, 2 exactly as in the transcript.
  const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
  stream_ += client.ReadExactly(960 - stream_.size(), 2.0);
  EXPECT_EQ(stream_, device_bytes.substr(55, 960));
  // Rate: 120 Hz shared by 2 stations; 0.5 s gives 60 records. The margin covers the records in
  // flight at both ends and a loaded machine (the schedule restarts after a 0.1 s lag); a burst or
  // a wrong rate (60 or 240 Hz) falls outside.
  stream_.clear();
  int n = 0;
  std::string more = client.ReadFor(0.5);
  const std::vector<std::string> records = {device_bytes.substr(55, 32),
                                            device_bytes.substr(87, 32)};
  EXPECT_TRUE(StripRecords(&more, records, &n).empty());
  EXPECT_GE(n, 40);
  EXPECT_LE(n, 70);
  EXPECT_NE(Control("status").find("continuous=1 format=binary units=inches active=1,2"),
            std::string::npos);
}

TEST_F(EmulatorTest, PolledAsciiAndBinary) {
  options_.device.continuous = false;  // Fastrak power-up: polled, ASCII, list 2,4,1
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  EXPECT_EQ(client.ReadFor(0.1), "") << "a polled device must stay silent";
  client.Write("P");
  const std::string ascii = client.ReadExactly(2 * 47, 1.0);
  ASSERT_EQ(ascii.size(), 2 * 47u);
  // Station 1 at (10, -5, 20) in; Euler angles of (4, 1, 2, 3)/sqrt(30) are checked in the device
  // test.
  EXPECT_EQ(ascii.substr(0, 24), "01   10.00  -5.00  20.00");
  EXPECT_EQ(ascii.substr(45, 5), "\r\n02 ");
  EXPECT_EQ(ascii.substr(47, 24), "02    1.50   2.50  -3.50");
  client.Write("fO1,2,11,0\rO2,2,11,0\rP");
  const std::string binary = client.ReadExactly(64, 1.0);
  const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
  EXPECT_EQ(binary, device_bytes.substr(55, 64));
  EXPECT_EQ(client.ReadFor(0.1), "");
}

TEST_F(EmulatorTest, LineSpeedLimitsThroughput) {
  // At 9600 baud (960 bytes/s with 8N1) 32-byte records leave at most 30 per second although the
  // device measures 120 times per second; the rest are lost whole, the framing stays intact.
  options_.baud = 9600;
  options_.device.num_stations = 1;
  options_.device.continuous = false;
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.Write("O1,2,11,0\rfC");
  std::string bytes = client.ReadFor(1.0);
  const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
  int n = 0;
  EXPECT_TRUE(StripRecords(&bytes, {device_bytes.substr(55, 32)}, &n).empty());
  // 30 records/s at most by the line (+2 for the records already on their way when reading
  // started); 120 Hz unpaced would give ~120. The lower bound only shows the stream flows: a
  // heavily loaded machine restarts the schedule after 0.1 s lags and loses records.
  EXPECT_GE(n, 15);
  EXPECT_LE(n, 32);
}

// Counts the complete ASCII records of `stream` equal to `record` and all complete records.
void CountRecords(const std::string& stream, const std::string& record, int* equal, int* total) {
  *equal = *total = 0;
  size_t start = stream.find("\r\n");  // skip a record cut by the start of reading
  while (start != std::string::npos) {
    const size_t end = stream.find("\r\n", start + 2);
    if (end == std::string::npos) break;
    ++*total;
    if (stream.compare(start + 2, end + 2 - (start + 2), record) == 0) ++*equal;
    start = end;
  }
}

TEST_F(EmulatorTest, RecordsStayFreshOnASlowLine) {
  // At 9600 baud the line carries ~20 ASCII records per second of the 120 the device could
  // measure. The host must get fresh ones at that lower rate, not every record seconds late from
  // a queue (4 KB was 4.3 s at this speed).
  options_.baud = 9600;
  options_.device.num_stations = 1;
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.ReadFor(0.5);  // the line is saturated from here on
  const std::string moved_record = MoveStation1();
  const std::string after = client.ReadFor(1.0);
  int fresh = 0, total = 0;
  CountRecords(after, moved_record, &fresh, &total);
  // Old records after the move: the one on the wire, one measured for the next free slot, and
  // what the kernel buffered while this reader was descheduled (~2 records per 0.1 s of lag).
  EXPECT_GE(fresh, total - 4) << total << " records";
  EXPECT_GE(total, 10);  // 20 per second fit the line; a loaded machine loses a few
}

TEST_F(EmulatorTest, AHostThatReopensThePortGetsNoBacklog) {
  // Bytes nobody reads are lost on a serial line. A host that closes the port, reopens it and
  // flushes its input must then read records measured after it reopened, as VRPN-style drivers
  // assume when they resume a stream without a reset. Unpaced at 1000 Hz the kernel's pty
  // buffer fills within 0.5 s, so the emulator's own queue is what gets tested.
  options_.baud = 0;
  options_.update_rate_hz = 1000;
  options_.device.num_stations = 1;
  Start();
  {
    SerialClient first(options_.link_path);
    ASSERT_TRUE(first.ok());
    ASSERT_FALSE(first.ReadFor(0.1).empty());
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  const std::string moved_record = MoveStation1();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.FlushInput();
  const std::string after = client.ReadFor(0.3);
  int fresh = 0, total = 0;
  CountRecords(after, moved_record, &fresh, &total);
  // At most the record being written when the host flushed is old (2 for margin).
  EXPECT_GE(fresh, total - 2) << total << " records";
  EXPECT_GE(total, 50);  // 1000 per second; a loaded machine restarts the schedule after lags
  EXPECT_EQ(Control("status").find("lost=0 "), std::string::npos) << "the buffer never filled";
}

TEST_F(EmulatorTest, FollowsTrajectory) {
  // Station 1 moves along x from 0.10 m to 0.30 m in 1 s, then holds.
  std::vector<std::vector<TrajectoryKeyframe>> frames(1, std::vector<TrajectoryKeyframe>(2));
  frames[0][0].transmitter_from_receiver.translation = {0.10, 0, 0};
  frames[0][1].t_s = 1.0;
  frames[0][1].transmitter_from_receiver.translation = {0.30, 0, 0};
  source_ =
      std::make_unique<ControlledPoseSource>(std::make_unique<TrajectoryPoseSource>(frames, false));
  options_.device.num_stations = 1;
  options_.device.continuous = false;
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.Write("O1,2,11,0\rfC");
  const std::string bytes = client.ReadExactly(32 * 150, 3.0);  // 120 Hz: 1.25 s
  ASSERT_EQ(bytes.size(), 32u * 150);
  double previous = 0;
  for (size_t i = 0; i < bytes.size(); i += 32) {
    ASSERT_EQ(bytes.substr(i, 3), "01 ");
    const double x_m = ReadFloat32Le(&bytes[i + 3]) * kMetresPerInch;
    // float32 inches: ~1e-7 relative; 1e-6 m absolute covers it.
    EXPECT_GE(x_m, previous - 1e-6) << i / 32;
    EXPECT_LE(x_m, 0.30 + 1e-6);
    previous = x_m;
  }
  // Started near the first keyframe (the host's commands came a few ms after t = 0; 0.5 s of
  // margin for a loaded machine), ended held at the last keyframe.
  EXPECT_LT(ReadFloat32Le(&bytes[3]) * kMetresPerInch, 0.20);
  EXPECT_NEAR(previous, 0.30, 1e-6);
}

TEST_F(EmulatorTest, MoveAndStylusButton) {
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  // Transcript 08's station-1 output list (stylus), inches.
  Handshake(&client, "O1,2,11,16,0\rO2,2,11,0\re1,0\r");
  const Rigid3d moved(QuaternionFromWxyz(0.0, 0.0, 1.0, 0.0), Eigen::Vector3d(0.1, 0.2, 0.3));
  EXPECT_EQ(Control("move 1 0.1 0.2 0.3 0 0 1 0"), "ok");
  EXPECT_EQ(Control("button 1 1"), "ok");
  FastrakDevice reference(FastrakDeviceOptions{});
  reference.Receive("fO1,2,11,16,0\r", [](int) { return StationMeasurement{}; });
  const std::string expected = reference.FormatRecord(1, StationMeasurement{moved, true});
  ASSERT_EQ(expected.size(), 34u);
  EXPECT_EQ(expected.substr(31), " 1 ");
  const std::string got = client.ReadFor(0.3);
  EXPECT_NE(got.find(expected), std::string::npos);
  EXPECT_EQ(Control("move 9 0 0 0 1 0 0 0").rfind("error: field 'station'", 0), 0u);
  EXPECT_EQ(Control("fault nonsense").rfind("error:", 0), 0u);
}

// CPU seconds this process has used (all threads).
double ProcessCpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
         1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

TEST_F(EmulatorTest, ContinuousWithNoActiveStationIdles) {
  // `l` can switch every station off while output stays continuous: nothing to send, and the
  // emulator must wait for the host instead of polling with a zero timeout (a busy loop).
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.Write("l1,0\rl2,0\r");
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  ASSERT_NE(Control("status").find(" continuous=1 "), std::string::npos);
  ASSERT_NE(Control("status").find(" active= "), std::string::npos);
  client.FlushInput();
  const double cpu_before = ProcessCpuSeconds();
  std::this_thread::sleep_for(std::chrono::seconds(1));
  EXPECT_LT(ProcessCpuSeconds() - cpu_before, 0.2);
  EXPECT_EQ(client.ReadFor(0.1), "");
}

// A byte reaches the host when its last bit has: at 1200 baud the 55-byte status record takes
// 55 x 10 / 1200 = 0.458 s on the line. The emulator wrote each reply or record whole at the start
// of its line time, so the status arrived complete within a few ms of `S` at any baud rate, and a
// driver whose status timeout or poll interval is shorter than the reply (the reference's 1 s at
// 300 baud) passed against the emulator and failed on a real unit.
TEST_F(EmulatorTest, BytesArriveAtTheLineRate) {
  options_.baud = 1200;
  options_.device.num_stations = 1;
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.Write("c");  // the fixture's power-up state streams
  client.ReadFor(0.3);
  client.FlushInput();
  const auto t0 = Clock::now();
  client.Write("S");
  std::vector<std::pair<double, size_t>> arrivals;
  const std::string reply = client.ReadFor(1.5, &arrivals);
  ASSERT_EQ(reply.size(), 55u) << reply;
  EXPECT_EQ(reply.substr(0, 3), "21S");
  EXPECT_EQ(reply.substr(53), "\r\n");
  const double line_s = 55 * 10.0 / 1200;
  // The last byte cannot come earlier than the reply's line time after `S` (10 ms allow for the
  // clock reads around the write); a loaded host may only make it later.
  EXPECT_GE(SecondsSince(t0), line_s - 0.01);
  ASSERT_FALSE(arrivals.empty());
  EXPECT_GE(arrivals.back().first, line_s - 0.01);
  // And not all at once: bytes are released as they complete, in chunks of a few ms.
  EXPECT_GT(arrivals.size(), 2u);
}

TEST_F(EmulatorTest, StopStreamingKeepsARequestedStatusRecord) {
  // At 9600 baud the line is always busy with ASCII records, so the reply to `S` waits for it.
  // A `c` arriving meanwhile stops the records, not the answer the host already asked for.
  options_.baud = 9600;
  options_.device.num_stations = 1;
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  client.ReadFor(0.2);  // the line is saturated from here on
  client.Write("S");
  std::this_thread::sleep_for(std::chrono::milliseconds(2));
  client.Write("c");
  const std::string after = client.ReadFor(0.5);
  const std::string status = FastrakDevice(options_.device).StatusRecord();
  EXPECT_NE(after.find(status.substr(0, 3)), std::string::npos) << after;
}

TEST_F(EmulatorTest, StylusSwitchTogglesOutputUnlessStylusModeIsSet) {
  // A Fastrak powers up in point/track stylus mode (e1,1): in continuous mode each press of the
  // station-1 switch toggles the record stream, in polled mode it outputs a record. Drivers send
  // `e1,0` for exactly this reason; one that forgets must see the stream stop, as on hardware.
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  Handshake(&client, "O1,2,11,16,0\rO2,2,11,0\r");
  ASSERT_FALSE(client.ReadFor(0.1).empty());
  EXPECT_EQ(Control("button 1 1"), "ok");
  client.ReadFor(0.1);  // the record on the wire
  EXPECT_EQ(client.ReadFor(0.3), "") << "a press in continuous mode stops the output";
  EXPECT_EQ(Control("button 1 0"), "ok");
  EXPECT_EQ(client.ReadFor(0.1), "");
  EXPECT_EQ(Control("button 1 1"), "ok");
  EXPECT_FALSE(client.ReadFor(0.3).empty()) << "the next press starts it again";
  // Polled: a press outputs one record per active station (34 + 32 bytes).
  client.Write("c");
  EXPECT_EQ(Control("button 1 0"), "ok");
  client.ReadFor(0.1);
  EXPECT_EQ(client.ReadFor(0.2), "");
  EXPECT_EQ(Control("button 1 1"), "ok");
  EXPECT_EQ(client.ReadFor(0.3).size(), 66u);
  // `e1,0`: the switch is only reported.
  client.Write("e1,0\rC");
  EXPECT_EQ(Control("button 1 0"), "ok");
  EXPECT_EQ(Control("button 1 1"), "ok");
  client.ReadFor(0.1);
  EXPECT_GT(client.ReadFor(0.3).size(), 66u);
}

TEST_F(EmulatorTest, GarbageAndTruncatedRecord) {
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  Handshake(&client, Transcript07Lines());
  const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
  const std::vector<std::string> records = {device_bytes.substr(55, 32),
                                            device_bytes.substr(87, 32)};
  int n = 0;
  stream_ += client.ReadFor(0.1);
  ASSERT_TRUE(StripRecords(&stream_, records, &n).empty());

  ASSERT_EQ(Control("fault garbage 7"), "ok");
  std::vector<std::string> blocks = ReadBlocks(&client, records, 1, &stream_);
  ASSERT_EQ(blocks.size(), 1u);
  EXPECT_EQ(blocks[0].size(), 7u);

  ASSERT_EQ(Control("fault truncate 10"), "ok");
  blocks = ReadBlocks(&client, records, 1, &stream_);
  ASSERT_EQ(blocks.size(), 1u);
  ASSERT_EQ(blocks[0].size(), 10u);
  EXPECT_TRUE(blocks[0] == records[0].substr(0, 10) || blocks[0] == records[1].substr(0, 10));

  ASSERT_EQ(Control("fault truncate"), "ok");  // half a record
  blocks = ReadBlocks(&client, records, 1, &stream_);
  ASSERT_EQ(blocks.size(), 1u);
  EXPECT_EQ(blocks[0].size(), 16u);
}

TEST_F(EmulatorTest, Stall) {
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  Handshake(&client, Transcript07Lines());
  client.ReadFor(0.1);
  ASSERT_EQ(Control("fault stall 0.5"), "ok");
  std::vector<std::pair<double, size_t>> arrivals;
  client.ReadFor(1.0, &arrivals);
  ASSERT_GE(arrivals.size(), 2u);
  // The silence may start before the first read (counted from the start of reading).
  double longest = arrivals[0].first;
  for (size_t i = 1; i < arrivals.size(); ++i)
    longest = std::max(longest, arrivals[i].first - arrivals[i - 1].first);
  // The gap spans the stall minus the control round trip, at most one record period (8.3 ms)
  // already on the way, and poll's millisecond rounding; 0.45 s leaves margin for all.
  EXPECT_GE(longest, 0.45);
  EXPECT_LT(longest, 1.0);
  EXPECT_GT(arrivals.back().first, 0.5) << "streaming did not resume";
}

TEST_F(EmulatorTest, PowerCycle) {
  options_.device.continuous = false;  // the Fastrak's power-up state
  Start();
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  Handshake(&client, Transcript07Lines());
  client.ReadFor(0.05);
  ASSERT_EQ(Control("fault powercycle 0.3"), "ok");
  const std::string off = Control("status");
  EXPECT_NE(off.find("power=off"), std::string::npos) << off;
  client.FlushInput();  // what had reached the host before the power went
  client.Write("S");    // lost: the device is off
  // Off, then back in its power-up state: polled, so silent.
  EXPECT_EQ(client.ReadFor(0.6), "");
  EXPECT_NE(Control("status").find("power=on continuous=0 format=ascii"), std::string::npos);
  client.Write("S");
  const std::string status = client.ReadExactly(55, 1.0);
  EXPECT_EQ(status, ReadFile(Transcript07() / "serial_device_to_host.bin").substr(0, 55));
  client.Write("P");
  EXPECT_EQ(client.ReadExactly(2 * 47, 1.0).size(), 2 * 47u);  // ASCII, output list 2,4,1
}

TEST_F(EmulatorTest, DisconnectAndReconnect) {
  Start();
  {
    SerialClient client(options_.link_path);
    ASSERT_TRUE(client.ok());
    Handshake(&client, Transcript07Lines());
    client.ReadFor(0.05);
    ASSERT_EQ(Control("fault disconnect 0.3"), "ok");
    // Unplugged: the open port hangs up and the device path disappears.
    client.ReadFor(0.2);
    EXPECT_TRUE(client.hung_up());
    EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(options_.link_path)));
    EXPECT_NE(Control("status").find("connected=0"), std::string::npos);
  }
  const auto t0 = Clock::now();
  while (!std::filesystem::exists(options_.link_path) && SecondsSince(t0) < 2.0) {
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(std::filesystem::exists(options_.link_path));
  // The tracker kept its configuration (only the cable was unplugged): binary records at once.
  SerialClient client(options_.link_path);
  ASSERT_TRUE(client.ok());
  std::string got = client.ReadExactly(320, 1.0);
  const std::string device_bytes = ReadFile(Transcript07() / "serial_device_to_host.bin");
  int n = 0;
  EXPECT_TRUE(
      StripRecords(&got, {device_bytes.substr(55, 32), device_bytes.substr(87, 32)}, &n).empty());
  EXPECT_EQ(n, 10);
  EXPECT_NE(Control("status").find("reconnects=1"), std::string::npos);
}

TEST_F(EmulatorTest, StopRemovesLinkAndSocket) {
  Start();
  ASSERT_TRUE(std::filesystem::is_symlink(options_.link_path));
  ASSERT_TRUE(std::filesystem::exists(options_.control_socket_path));
  Stop();
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(options_.link_path)));
  EXPECT_FALSE(std::filesystem::exists(options_.control_socket_path));
}

TEST_F(EmulatorTest, RefusesToReplaceRegularFile) {
  std::ofstream(options_.link_path) << "user data";
  EXPECT_THROW(Start(), std::runtime_error);
  emulator_.reset();
  EXPECT_EQ(ReadFile(options_.link_path), "user data");
}

TEST(ParseControlCommand, Nominal) {
  const ControlCommand move = ParseControlCommand("move 2 0.1 -0.2 0.3 2 0 0 0");
  ASSERT_TRUE(std::holds_alternative<MoveCommand>(move));
  EXPECT_EQ(std::get<MoveCommand>(move).station, 2);
  EXPECT_DOUBLE_EQ(std::get<MoveCommand>(move).transmitter_from_receiver.rotation.w(), 1.0);
  EXPECT_EQ(std::get<StallFault>(ParseControlCommand("fault stall 1.5")).seconds, 1.5);
  EXPECT_EQ(std::get<TruncateFault>(ParseControlCommand("fault truncate")).keep_bytes, -1);
  EXPECT_EQ(std::get<GarbageFault>(ParseControlCommand("  fault   garbage 3 ")).num_bytes, 3);
  EXPECT_THROW(ParseControlCommand("move 1 0 0 0 0 0 0 0"),
               std::invalid_argument);  // zero quaternion
  EXPECT_THROW(ParseControlCommand("fault garbage 1.5"), std::invalid_argument);
  EXPECT_THROW(ParseControlCommand("fault stall -1"), std::invalid_argument);
  EXPECT_THROW(ParseControlCommand("button 1 2"), std::invalid_argument);
  EXPECT_THROW(ParseControlCommand("jump"), std::invalid_argument);
}

// The installed command: prints the device path, serves, and on SIGTERM removes its link.
TEST(TrackcalEmulate, SigtermRemovesLink) {
  // Built next to this test (CMake adds the dependency).
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::filesystem::path dir = testing::MakeTempDir("emulate_cli");
  const std::string link = (dir / "fastrak").string();
  int out[2];
  ASSERT_EQ(pipe(out), 0);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_adddup2(&actions, out[1], 1);
  posix_spawn_file_actions_addclose(&actions, out[0]);
  std::vector<std::string> args = {exe,      "--link",           link, "--stations", "1",
                                   "--pose", "1=0.2,0,0,1,0,0,0"};
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  pid_t pid = 0;
  ASSERT_EQ(posix_spawn(&pid, exe.c_str(), &actions, nullptr, argv.data(), environ), 0);
  posix_spawn_file_actions_destroy(&actions);
  close(out[1]);
  std::string line;
  char c;
  pollfd p{out[0], POLLIN, 0};
  while (poll(&p, 1, 5000) > 0 && read(out[0], &c, 1) == 1 && c != '\n') line += c;
  close(out[0]);
  EXPECT_EQ(line.rfind("/dev/pts/", 0), 0u) << line;
  EXPECT_EQ(std::filesystem::read_symlink(link).string(), line);
  {
    SerialClient client(link);
    ASSERT_TRUE(client.ok());
    client.Write("S");
    EXPECT_EQ(client.ReadExactly(55, 1.0).substr(0, 3), "21S");
  }
  kill(pid, SIGTERM);
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(link)));
}

// Whole-number options are read as such: a fraction, an exponent or a sign is refused by name, not
// truncated (--stations 2.5 was 2) or wrapped (--seed -1 was 2^64 - 1).
TEST(TrackcalEmulate, WholeNumberOptionsRefuseFractionsAndSigns) {
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"--stations 2.5", "--stations: expected a whole number from 1 to 4, got '2.5'"},
      {"--seed -1", "--seed: expected a whole number from 0 to 18446744073709551615, got '-1'"},
      {"--seed 1e3", "--seed: expected a whole number"},
      {"--seed 99999999999999999999", "--seed: expected a whole number"},
      {"--baud 9600.5", "--baud: expected a whole number"},
      {"--pose 5=0.3,0,0,1,0,0,0", "--pose station: expected a whole number from 1 to 4, got '5'"},
      // A trailing comma is a missing number, not nothing (std::getline dropped it).
      {"--pose 1=0.3,0,0,1,0,0,0,", "--pose: expected 7 numbers after '=', got 8 fields"},
      {"--pose 1=0.3,0,0,1,0,0,", "--pose: not a number: ''"}};
  for (const auto& [args, message] : cases) {
    FILE* f = popen((exe + " " + args + " --duration 0.05 2>&1").c_str(), "r");
    ASSERT_NE(f, nullptr);
    std::string out;
    char buf[256];
    while (fgets(buf, sizeof(buf), f) != nullptr) out += buf;
    const int status = pclose(f);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) != 0) << args;
    EXPECT_NE(out.find(message), std::string::npos) << args << ": " << out;
  }
}

// Number options must be finite numbers and --duration positive: `--pose 1=nan,...` streamed NaN
// records and `--duration 0` (or -1) served forever instead of exiting.
TEST(TrackcalEmulate, NumberOptionsRefuseNonFiniteAndDurationNotPositive) {
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"--scene none --pose 1=nan,0,0,1,0,0,0 --duration 0.05",
       "--pose: not a finite number: 'nan'"},
      {"--scene none --duration 0", "--duration: must be more than 0 seconds"},
      {"--scene none --duration -1", "--duration: must be more than 0 seconds"}};
  for (const auto& [args, message] : cases) {
    // `timeout` so that an emulator that does not exit fails the case instead of the test run.
    FILE* f = popen(("timeout 5 " + exe + " " + args + " 2>&1").c_str(), "r");
    ASSERT_NE(f, nullptr);
    std::string out;
    char buf[256];
    while (fgets(buf, sizeof(buf), f) != nullptr) out += buf;
    const int status = pclose(f);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 2) << args << ": " << status;
    EXPECT_NE(out.find(message), std::string::npos) << args << ": " << out;
  }
}

// --trajectory with the example file, --duration: the command exits by itself and cleans up.
TEST(TrackcalEmulate, TrajectoryAndDuration) {
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::filesystem::path dir = testing::MakeTempDir("emulate_cli");
  const std::string link = (dir / "fastrak").string();
  const std::string trajectory =
      (testing::SourceDir() / "tests/data/fastrak/example_trajectory.csv").string();
  std::vector<std::string> args = {exe,          "--link", link,       "--trajectory", trajectory,
                                   "--duration", "0.5",    "--binary", "--continuous"};
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  pid_t pid = 0;
  ASSERT_EQ(posix_spawn(&pid, exe.c_str(), &actions, nullptr, argv.data(), environ), 0);
  posix_spawn_file_actions_destroy(&actions);
  const auto t0 = Clock::now();
  while (!std::filesystem::exists(link) && SecondsSince(t0) < 2.0) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  {
    SerialClient client(link);
    ASSERT_TRUE(client.ok());
    // Default output list 2,4,1 in binary: 3 + 12 + 12 + 2 bytes, stations 1 and 2 alternating.
    const std::string bytes = client.ReadExactly(4 * 29, 1.0);
    ASSERT_EQ(bytes.size(), 4 * 29u);
    std::set<std::string> stations;
    for (size_t i = 0; i < bytes.size(); i += 29) stations.insert(bytes.substr(i, 2));
    EXPECT_EQ(stations, (std::set<std::string>{"01", "02"}));
  }
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(link)));
}

// The default: the paper scene's physics and trajectories, in the scene's hemisphere (-z).
TEST(TrackcalEmulate, DefaultIsPaperScene) {
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::filesystem::path dir = testing::MakeTempDir("emulate_cli");
  const std::string link = (dir / "fastrak").string();
  std::vector<std::string> args = {exe, "--link", link, "--stations", "1", "--duration", "1.5"};
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 1, "/dev/null", O_WRONLY, 0);
  pid_t pid = 0;
  ASSERT_EQ(posix_spawn(&pid, exe.c_str(), &actions, nullptr, argv.data(), environ), 0);
  posix_spawn_file_actions_destroy(&actions);
  const auto t0 = Clock::now();
  while (!std::filesystem::exists(link) && SecondsSince(t0) < 5.0) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  {
    SerialClient client(link);
    ASSERT_TRUE(client.ok());
    client.Write("O1,2,11,0\rfC");
    const std::string bytes = client.ReadExactly(32 * 30, 1.0);
    ASSERT_EQ(bytes.size(), 32u * 30);
    const float z_first = ReadFloat32Le(&bytes[11]);
    bool moved = false;
    for (size_t i = 0; i < bytes.size(); i += 32) {
      ASSERT_EQ(bytes.substr(i, 3), "01 ");
      EXPECT_LE(ReadFloat32Le(&bytes[i + 11]), 0.0f);  // hemisphere H1,0,0,-1 of the scene
      moved = moved || ReadFloat32Le(&bytes[i + 11]) != z_first;
    }
    EXPECT_TRUE(moved) << "the scene trajectory should move the receiver";
  }
  int status = 0;
  ASSERT_EQ(waitpid(pid, &status, 0), pid);
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
}

// Bad input: exit code 2 and a message naming file, line and field.
TEST(TrackcalEmulate, BadTrajectoryIsAUserError) {
  const std::string exe =
      (std::filesystem::read_symlink("/proc/self/exe").parent_path() / "trackcal-emulate").string();
  const std::filesystem::path dir = testing::MakeTempDir("emulate_cli");
  std::ofstream(dir / "bad.csv")
      << "t,station,x,y,z,qw,qx,qy,qz\n0,1,0.3,0,0,1,0,0,0\n1,1,0.3,oops,0,1,0,0,0\n";
  const std::string command =
      exe + " --trajectory " + (dir / "bad.csv").string() + " 2>" + (dir / "err.txt").string();
  const int status = std::system(command.c_str());
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 2) << status;
  const std::string err = ReadFile(dir / "err.txt");
  EXPECT_NE(err.find("bad.csv:3: field 'y'"), std::string::npos) << err;
}

}  // namespace
}  // namespace trackcal::emulator

namespace trackcal::emulator {
namespace {

TEST(BackgroundEmulator, Nominal) {
  EmulatorOptions options;
  options.device.num_stations = 1;
  const std::filesystem::path link = testing::MakeTempDir("background") / "fastrak";
  options.link_path = link.string();
  std::string path;
  {
    BackgroundEmulator emulator(options, std::make_unique<StaticPoseSource>(TranscriptPoses()));
    path = emulator.initial_device_path();
    ASSERT_EQ(path.rfind("/dev/pts/", 0), 0u) << path;
    EXPECT_NE(emulator.Control("status").find("connected=1"), std::string::npos);
    EXPECT_EQ(emulator.Control("move 1 0.0254 0 0 1 0 0 0"), "ok");
    EXPECT_EQ(emulator.Control("move 0 0 0 0 1 0 0 0").rfind("error:", 0), 0u);
    SerialClient client(path);
    ASSERT_TRUE(client.ok());
    client.Write("fO1,2\rP");
    const std::string record = client.ReadExactly(15, 1.0);
    ASSERT_EQ(record.size(), 15u);
    EXPECT_EQ(ReadFloat32Le(&record[3]), 1.0f);  // 0.0254 m = 1 inch
  }
  // The destructor closed the pty and removed the link. (The /dev/pts path itself is not probed:
  // its number may already belong to another process's pty.)
  EXPECT_FALSE(std::filesystem::exists(std::filesystem::symlink_status(link)));
}

}  // namespace
}  // namespace trackcal::emulator
