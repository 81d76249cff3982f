// LogToStderr with a stderr nobody reads: the network thread logs every connection, so a blocking
// write there stalled every client.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <future>
#include <string>
#include <thread>

#include "vrpn_server/server/server.h"

namespace trackcal::vrpn {
namespace {

// fd 2 replaced by the write end of a pipe for the life of the object; Drain() reads it.
class CapturedStderr {
 public:
  CapturedStderr() {
    EXPECT_EQ(::pipe2(fds_, O_CLOEXEC), 0);
    saved_ = ::dup(STDERR_FILENO);
    ::dup2(fds_[1], STDERR_FILENO);
  }
  ~CapturedStderr() {
    StopDraining();
    ::dup2(saved_, STDERR_FILENO);
    ::close(saved_);
    ::close(fds_[1]);
    ::close(fds_[0]);
  }
  // Reads everything written, on a thread of its own, until StopDraining.
  void StartDraining() {
    reader_ = std::thread([this] {
      char buf[65536];
      for (;;) {
        // Once told to stop, reads what is left in the pipe and ends.
        const bool stopping = stop_;
        pollfd p{fds_[0], POLLIN, 0};
        if (::poll(&p, 1, stopping ? 0 : 20) <= 0) {
          if (stopping) break;
          continue;
        }
        const ssize_t n = ::read(fds_[0], buf, sizeof(buf));
        if (n > 0) text_.append(buf, static_cast<std::size_t>(n));
      }
    });
  }
  int Capacity() const { return ::fcntl(fds_[1], F_GETPIPE_SZ); }
  // Reads (and keeps) what is written until the first line has ended; before StartDraining.
  void ReadFirstLine() {
    char buf[4096];
    while (text_.find('\n') == std::string::npos) {
      const ssize_t n = ::read(fds_[0], buf, sizeof(buf));
      ASSERT_GT(n, 0);
      text_.append(buf, static_cast<std::size_t>(n));
    }
  }
  // Bytes waiting in the pipe.
  int Pending() const {
    int n = 0;
    ::ioctl(fds_[0], FIONREAD, &n);
    return n;
  }
  std::string StopDraining() {
    if (reader_.joinable()) {
      stop_ = true;
      reader_.join();
    }
    return text_;
  }

 private:
  int fds_[2] = {-1, -1};
  int saved_ = -1;
  std::thread reader_;
  std::atomic<bool> stop_{false};
  std::string text_;
};

// Polls `done` every millisecond for at most 10 s.
template <typename Predicate>
void WaitFor(Predicate done) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!done() && std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
}

// What a flood of "<prefix>N ..." lines left on stderr, N counting from 0.
struct FloodTally {
  int kept = 0;                // lines written
  std::size_t kept_bytes = 0;  // their bytes, stamp and line end included
  int dropped = 0;             // the sum of the drop notices
  int notices = 0;             // drop notices
  int last_kept = -1;          // N of the last line written
  bool ok = true;              // every notice counts the lines missing where it stands
  std::string error;           // the first notice (or line) that did not
};

FloodTally TallyFlood(const std::string& text,
                      const std::string& prefix = " trackcal-server: flood ") {
  static const std::string kNotice = " log line(s) dropped: stderr was not read fast enough";
  FloodTally tally;
  int expected_next = 0;  // N of the next line if none went missing
  std::size_t line_start = 0;
  while (line_start < text.size()) {
    std::size_t line_end = text.find('\n', line_start);
    if (line_end == std::string::npos) line_end = text.size();
    const std::string line = text.substr(line_start, line_end - line_start);
    line_start = line_end + 1;
    const std::size_t flood = line.find(prefix);
    const std::size_t notice = line.find(kNotice);
    if (flood != std::string::npos) {
      const int n = std::stoi(line.substr(flood + prefix.size()));
      if (n != expected_next && tally.ok) {
        tally.ok = false;
        tally.error = "line " + std::to_string(n) + " follows " + std::to_string(expected_next - 1);
      }
      ++tally.kept;
      tally.kept_bytes += line.size() + 1;
      tally.last_kept = n;
      expected_next = n + 1;
    } else if (notice != std::string::npos) {
      const std::size_t count_start = line.rfind(' ', notice - 1) + 1;  // "...: N log line(s)"
      const int dropped = std::stoi(line.substr(count_start, notice - count_start));
      ++tally.notices;
      tally.dropped += dropped;
      expected_next += dropped;
    }
  }
  return tally;
}

TEST(LogToStderr, NeverBlocksWhileStderrIsNotRead) {
  CapturedStderr err;
  // 3000 lines of about 150 bytes: several times a pipe's 64 KiB, well under the 1 MiB queue.
  const std::string filler(100, 'x');
  constexpr int kLines = 3000;
  auto logging = std::async(std::launch::async, [&] {
    for (int i = 0; i < kLines; ++i) LogToStderr("line " + std::to_string(i) + " " + filler);
  });
  // Generous against a loaded machine: queuing 3000 lines takes milliseconds.
  const bool returned = logging.wait_for(std::chrono::seconds(10)) == std::future_status::ready;
  EXPECT_TRUE(returned) << "LogToStderr blocked on a full stderr pipe";
  err.StartDraining();  // unblocks a blocked writer in either case
  logging.wait();
  EXPECT_TRUE(FlushStderrLog(std::chrono::seconds(10)));
  const std::string text = err.StopDraining();
  // Every line arrived, in order, stamped and with its line end.
  std::size_t at = 0;
  for (int i = 0; i < kLines; ++i) {
    const std::string expected =
        " trackcal-server: line " + std::to_string(i) + " " + filler + "\n";
    const std::size_t found = text.find(expected, at);
    ASSERT_NE(found, std::string::npos) << "line " << i;
    at = found + expected.size();
  }
  EXPECT_EQ(text.find("dropped"), std::string::npos);
}

TEST(LogToStderr, DropsBeyondItsQueueAndSaysHowMany) {
  CapturedStderr err;
  // 20000 lines of about 160 bytes (3 MiB) while nobody reads: the queue keeps 1 MiB of them.
  const std::string filler(110, 'y');
  constexpr int kLines = 20000;
  auto logging = std::async(std::launch::async, [&] {
    for (int i = 0; i < kLines; ++i) LogToStderr("flood " + std::to_string(i) + " " + filler);
  });
  EXPECT_EQ(logging.wait_for(std::chrono::seconds(10)), std::future_status::ready)
      << "LogToStderr blocked on a full stderr pipe";
  err.StartDraining();
  logging.wait();
  // Flushed once stderr takes lines again: the queued lines, then the count of the others.
  EXPECT_TRUE(FlushStderrLog(std::chrono::seconds(10)));
  LogToStderr("after the flood");
  EXPECT_TRUE(FlushStderrLog(std::chrono::seconds(10)));
  const std::string text = err.StopDraining();
  const std::size_t notice = text.rfind(" log line(s) dropped: stderr was not read fast enough\n");
  ASSERT_NE(notice, std::string::npos);
  // The (last) notice stands where the lines went missing: after the last kept flood line (the
  // first ones, which were queued) and before the next line.
  const std::size_t last_kept = text.rfind(" trackcal-server: flood ");
  ASSERT_NE(last_kept, std::string::npos);
  EXPECT_LT(last_kept, notice);
  const std::size_t after = text.find("after the flood");
  ASSERT_NE(after, std::string::npos);
  EXPECT_GT(after, notice);
  EXPECT_NE(text.find(" trackcal-server: flood 0 "), std::string::npos);
  // Every notice counts the lines missing where it stands, and kept + dropped = logged. There is
  // one notice when the writer is blocked throughout; a writer that finished a short batch into
  // the pipe while the flood went on makes room for a few more lines and a second notice.
  const FloodTally tally = TallyFlood(text);
  EXPECT_TRUE(tally.ok) << tally.error;
  EXPECT_GT(tally.dropped, 0);
  EXPECT_EQ(tally.kept + tally.dropped, kLines);
  // Memory stays bounded: what was written is what the pipe took before it was read plus the
  // 1 MiB the queue (and the batch being written) held.
  EXPECT_LE(tally.kept_bytes, std::size_t{1 << 20} + static_cast<std::size_t>(err.Capacity()));
}

TEST(LogToStderr, TheBatchBeingWrittenCountsAgainstTheQueue) {
  // The writer takes every queued line at once and writes them while stderr is blocked; those
  // lines used to leave the count at once, so another MiB was queued behind them: up to 2 MiB
  // held (under load, when the writer woke only after the queue was full, the flood test below saw
  // two drop notices). Made deterministic here: the writer is blocked in a line larger than the
  // pipe while the queue fills, then that line is read so the writer takes the whole queue.
  CapturedStderr err;
  const int capacity = err.Capacity();
  ASSERT_GT(capacity, 0);
  const std::string big(static_cast<std::size_t>(capacity) + 16384, 'b');
  LogToStderr(big);
  // A full pipe shows the writer blocked in `big`, the only line logged. Generous against a
  // loaded machine: the writer needs microseconds.
  WaitFor([&] { return err.Pending() == capacity; });
  ASSERT_EQ(err.Pending(), capacity) << "the writer did not block in the first line";
  // 1 MiB / ~160 bytes = about 6600 lines: 8000 overflow the queue.
  const std::string filler(110, 'w');
  int logged = 0;
  for (; logged < 8000; ++logged) LogToStderr("held " + std::to_string(logged) + " " + filler);
  err.ReadFirstLine();
  // The writer ends `big`, then takes the whole queue and writes it until the pipe is full: once
  // the pipe holds anything, the queue is in the writer's hands.
  WaitFor([&] { return err.Pending() > 0; });
  ASSERT_GT(err.Pending(), 0) << "the writer did not take the queued lines";
  // Still nobody reads: 2000 lines (about 320 kB) find at most the room `big` left.
  for (int i = 0; i < 2000; ++i, ++logged) {
    LogToStderr("held " + std::to_string(logged) + " " + filler);
  }
  err.StartDraining();
  EXPECT_TRUE(FlushStderrLog(std::chrono::seconds(10)));
  const std::string text = err.StopDraining();
  const FloodTally tally = TallyFlood(text, " trackcal-server: held ");
  EXPECT_TRUE(tally.ok) << tally.error;
  EXPECT_EQ(tally.kept + tally.dropped, logged);
  // At most 1 MiB of lines was held: kept = what the pipe took before it was read (`big`, not
  // counted here, then one pipe of queued lines) + what was held when the reading started.
  EXPECT_LE(tally.kept_bytes, std::size_t{1 << 20} + static_cast<std::size_t>(capacity))
      << tally.kept << " lines kept";
}

TEST(LogToStderr, ALineLargerThanTheQueueIsCountedAndSaidAtOnce) {
  // A line over the queue's 1 MiB is dropped when it comes. The count used to wait for the next
  // line: with none (the last line before exit), the writer slept, FlushStderrLog ran into its
  // timeout and the count was never written.
  CapturedStderr err;
  err.StartDraining();
  LogToStderr("before");
  LogToStderr(std::string(std::size_t{2} << 20, 'z'));
  // Generous against a loaded machine: writing two lines takes microseconds.
  EXPECT_TRUE(FlushStderrLog(std::chrono::seconds(5)));
  const std::string text = err.StopDraining();
  EXPECT_NE(text.find(" trackcal-server: before\n"), std::string::npos) << text.size();
  EXPECT_NE(text.find(" trackcal-server: 1 log line(s) dropped: stderr was not read fast enough\n"),
            std::string::npos)
      << text.size();
  EXPECT_EQ(text.find('z'), std::string::npos);
}

}  // namespace
}  // namespace trackcal::vrpn
