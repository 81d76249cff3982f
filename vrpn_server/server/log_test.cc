// LogToStderr with a stderr nobody reads: the network thread logs every connection, so a blocking
// write there stalled every client.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <poll.h>
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
  const std::size_t notice = text.find(" log line(s) dropped: stderr was not read fast enough\n");
  ASSERT_NE(notice, std::string::npos);
  // The notice stands where the lines went missing: after the last kept flood line (the first
  // ones, which were queued) and before the next line.
  const std::size_t last_kept = text.rfind(" trackcal-server: flood ");
  ASSERT_NE(last_kept, std::string::npos);
  EXPECT_LT(last_kept, notice);
  const std::size_t after = text.find("after the flood");
  ASSERT_NE(after, std::string::npos);
  EXPECT_GT(after, notice);
  EXPECT_NE(text.find(" trackcal-server: flood 0 "), std::string::npos);
  // The count is what was not written: kept + dropped = logged.
  std::size_t kept = 0;
  for (std::size_t p = text.find(" trackcal-server: flood "); p != std::string::npos;
       p = text.find(" trackcal-server: flood ", p + 1)) {
    ++kept;
  }
  const std::size_t count_start = text.rfind(' ', notice - 1) + 1;  // "...: N log line(s)"
  const int dropped = std::stoi(text.substr(count_start, notice - count_start));
  EXPECT_GT(dropped, 0);
  EXPECT_EQ(kept + static_cast<std::size_t>(dropped), static_cast<std::size_t>(kLines));
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
