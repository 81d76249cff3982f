#include "core/file_util.h"

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <fstream>
#include <thread>

#include "core/capture.h"
#include "tests/test_utils.h"

namespace trackcal {
namespace {

// FIPS 180-2 / NIST CAVP example vectors.
TEST(Utf16TextProblem, NamesAByteOrderMarkOfEitherOrder) {
  EXPECT_EQ(Utf16TextProblem(std::string("\xFF\xFE{\0", 4), "model file"),
            "UTF-16 text (a byte order mark FF FE or FE FF); save the model file as UTF-8");
  EXPECT_EQ(Utf16TextProblem(std::string("\xFE\xFF\0{", 4), "CSV file"),
            "UTF-16 text (a byte order mark FF FE or FE FF); save the CSV file as UTF-8");
  // UTF-32's marks (the little-endian one starts with UTF-16's) were called UTF-16's.
  const std::string utf32 =
      "UTF-32 text (a byte order mark FF FE 00 00 or 00 00 FE FF); save the CSV file as UTF-8";
  EXPECT_EQ(Utf16TextProblem(std::string("\xFF\xFE\0\0s\0\0\0", 8), "CSV file"), utf32);
  EXPECT_EQ(Utf16TextProblem(std::string("\0\0\xFE\xFF\0\0\0s", 8), "CSV file"), utf32);
  EXPECT_EQ(Utf16TextProblem("\xEF\xBB\xBF{}", "model file"), "");  // UTF-8's mark
  EXPECT_EQ(Utf16TextProblem("\xFF", "model file"), "");
  EXPECT_EQ(Utf16TextProblem("", "model file"), "");
}

TEST(Sha256, Nominal) {
  EXPECT_EQ(Sha256Hex("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
}

TEST(Sha256, StandardVectors) {
  EXPECT_EQ(Sha256Hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
  EXPECT_EQ(Sha256Hex("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
            "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
  EXPECT_EQ(Sha256Hex("abcdefghbcdefghicdefghijdefghijkefghijklfghijklmghijklmnhijklmnoijklmnopjklmnopqk"
                      "lmnopqrlmnopqrsmnopqrstnopqrstu"),
            "cf5b16a778af8380036ce59e7b0492370b249b11e8f07a51afac45037afee9d1");
  EXPECT_EQ(Sha256Hex(std::string(1000000, 'a')),
            "cdc76e5c9914fb9281a1c7e284d73e67f1809a48a497200e046d39ccc7112cd0");
}

TEST(Sha256, IncrementalEqualsOneShotAcrossBlockBoundaries) {
  std::string data;
  for (int i = 0; i < 1000; ++i) data.push_back(static_cast<char>(i * 37 + 11));
  for (size_t chunk : {1u, 3u, 55u, 56u, 63u, 64u, 65u, 127u}) {
    Sha256 sha;
    for (size_t pos = 0; pos < data.size(); pos += chunk) sha.Update(data.substr(pos, chunk));
    EXPECT_EQ(sha.FinishHex(), Sha256Hex(data)) << "chunk " << chunk;
  }
  // Lengths around the padding boundary (55/56 bytes need one or two final blocks).
  for (size_t n : {55u, 56u, 57u, 64u}) {
    Sha256 a;
    a.Update(data.substr(0, n));
    EXPECT_NE(a.FinishHex(), Sha256Hex(data.substr(0, n + 1)));
  }
}

TEST(Sha256, FileMatchesString) {
  const auto dir = testing::MakeTempDir("sha");
  const std::string contents(200000, 'x');
  WriteFileAtomically(dir / "f.bin", contents);
  EXPECT_EQ(Sha256HexOfFile(dir / "f.bin"), Sha256Hex(contents));
  EXPECT_THROW(Sha256HexOfFile(dir / "missing.bin"), std::invalid_argument);
}

TEST(IsSha256Hex, RejectsMalformed) {
  EXPECT_TRUE(IsSha256Hex(Sha256Hex("abc")));
  EXPECT_FALSE(IsSha256Hex("ABC"));
  std::string upper = Sha256Hex("abc");
  upper[0] = 'B';
  EXPECT_FALSE(IsSha256Hex(upper));
  EXPECT_FALSE(IsSha256Hex(Sha256Hex("abc").substr(1)));
}

TEST(WriteFileAtomically, Nominal) {
  const auto dir = testing::MakeTempDir("atomic");
  const auto path = dir / "out.txt";
  WriteFileAtomically(path, "first");
  EXPECT_EQ(ReadFileToString(path), "first");
  WriteFileAtomically(path, "second, longer");
  EXPECT_EQ(ReadFileToString(path), "second, longer");
  // No temporary file is left behind.
  int count = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    (void)entry;
    ++count;
  }
  EXPECT_EQ(count, 1);
  // Mode follows the umask like a plain open(), not mkstemp's 0600.
  struct stat st;
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  const mode_t mask = ::umask(0);
  ::umask(mask);
  EXPECT_EQ(st.st_mode & 0777, 0666 & ~mask);
}

TEST(CreateTemporaryFolderBeside, HiddenBesideThePathWithTheUmasksMode) {
  const auto dir = testing::MakeTempDir("temp_folder");
  const mode_t old_mask = ::umask(027);
  std::string a, b;
  ASSERT_TRUE(CreateTemporaryFolderBeside(dir / "capture", &a));
  ASSERT_TRUE(CreateTemporaryFolderBeside(dir / "capture", &b));
  ::umask(old_mask);
  EXPECT_NE(a, b);
  for (const std::string& folder : {a, b}) {
    EXPECT_EQ(std::filesystem::path(folder).parent_path(), dir);
    EXPECT_EQ(std::filesystem::path(folder).filename().string().rfind(".capture.tmp-", 0), 0u)
        << folder;
    // mkdir's 0777 minus the umask, as any new folder (mkdtemp would give 0700).
    EXPECT_EQ(std::filesystem::status(folder).permissions(),
              static_cast<std::filesystem::perms>(0750));
  }
  std::string missing;
  errno = 0;
  EXPECT_FALSE(CreateTemporaryFolderBeside(dir / "no" / "capture", &missing));
  EXPECT_EQ(errno, ENOENT);
}

TEST(WriteFileAtomically, LeavesTheUmaskAloneForOtherThreads) {
  // The umask is per process: clearing it even briefly to read it gives a file another thread
  // creates meanwhile mode 0666 (world-writable) instead of 0644. Measured before the fix: 5 of
  // 668427 files created during 3000 writes. On tmpfs (no fsync cost) the writes are fast enough
  // to make the window show within the test's time.
  std::string shm = "/dev/shm/file_util_test-XXXXXX";
  if (::mkdtemp(shm.data()) == nullptr) GTEST_SKIP() << "no /dev/shm";
  const std::filesystem::path dir = shm;
  const mode_t old_mask = ::umask(022);
  for (const bool replace : {true, false}) {
    std::atomic<bool> done{false};
    std::thread writer([&] {
      for (int i = 0; i < 20000; ++i) {
        if (replace) {
          WriteFileAtomically(dir / "out.txt", "x");
        } else {  // as the capture writers write: a new file, linked into place
          WriteFileAtomically(dir / "new.txt", "x", /*overwrite=*/false);
          std::filesystem::remove(dir / "new.txt");
        }
      }
      done = true;
    });
    int probes = 0, wrong = 0;
    const std::string probe = (dir / "probe").string();
    while (!done) {
      const int fd = ::open(probe.c_str(), O_CREAT | O_EXCL | O_WRONLY, 0666);
      if (fd < 0) continue;
      struct stat st;
      const bool ok = ::fstat(fd, &st) == 0;
      ::close(fd);
      ::unlink(probe.c_str());
      ++probes;
      if (ok && (st.st_mode & 0777) != 0644) ++wrong;
    }
    writer.join();
    EXPECT_EQ(wrong, 0) << "of " << probes << " files created while writing"
                        << (replace ? "" : " new files");
    EXPECT_EQ(std::filesystem::status(dir / "out.txt").permissions(),
              static_cast<std::filesystem::perms>(0644));
  }
  ::umask(old_mask);
  std::filesystem::remove_all(dir);
}

TEST(WriteFileAtomically, WithoutOverwriteNeverReplacesAndLeavesNoTemporary) {
  const auto dir = testing::MakeTempDir("atomic_new");
  const auto path = dir / "poses.csv";
  WriteFileAtomically(path, "mine", /*overwrite=*/false);
  EXPECT_EQ(ReadFileToString(path), "mine");
  try {
    WriteFileAtomically(path, "other", /*overwrite=*/false);
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_EQ(std::string(e.what()), path.string() + ": exists; refusing to overwrite it");
  }
  EXPECT_EQ(ReadFileToString(path), "mine");
  // A dangling symbolic link is a name in use too: writing through it could create its target.
  std::filesystem::create_symlink(dir / "elsewhere.csv", dir / "link.csv");
  EXPECT_THROW(WriteFileAtomically(dir / "link.csv", "x", /*overwrite=*/false), std::runtime_error);
  EXPECT_FALSE(std::filesystem::exists(dir / "elsewhere.csv"));
  int count = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) {
    EXPECT_EQ(entry.path().filename().string().find(".tmp-"), std::string::npos) << entry.path();
    ++count;
  }
  EXPECT_EQ(count, 2);
  // Linked, not renamed: the file got the umask's mode as the replacing writer's does.
  struct stat st;
  ASSERT_EQ(::stat(path.c_str(), &st), 0);
  const mode_t mask = ::umask(0);
  ::umask(mask);
  EXPECT_EQ(st.st_mode & 0777, 0666 & ~mask);
}

TEST(WriteFileAtomically, ReplacingKeepsTheModeAndGroup) {
  // A rename puts a new file in place: it had the umask's mode (0644 under 022) whatever the file
  // it replaced had, so a group-writable calibration a lab shares (0664) or a private one (0600)
  // changed on every refit.
  const auto dir = testing::MakeTempDir("atomic_mode");
  const auto path = dir / "calib.json";
  const mode_t old_mask = ::umask(022);
  for (const mode_t mode : {mode_t{0664}, mode_t{0600}, mode_t{0640}}) {
    WriteFileAtomically(path, "first");
    ASSERT_EQ(::chmod(path.c_str(), mode), 0);
    WriteFileAtomically(path, "second");
    EXPECT_EQ(ReadFileToString(path), "second");
    struct stat st;
    ASSERT_EQ(::stat(path.c_str(), &st), 0);
    EXPECT_EQ(st.st_mode & 07777, mode);
  }
  ::umask(old_mask);
  // The group, where the writer may set it (root may set any).
  if (::geteuid() == 0) {
    ASSERT_EQ(::chown(path.c_str(), static_cast<uid_t>(-1), 4242), 0);
    WriteFileAtomically(path, "third");
    struct stat st;
    ASSERT_EQ(::stat(path.c_str(), &st), 0);
    EXPECT_EQ(st.st_gid, 4242u);
    EXPECT_EQ(st.st_mode & 07777, 0640u);
  }
}

// A calibration a server reads through a link (calib.json -> calibrations/2026-12-01.json) was
// replaced by a regular file: the rename put the new file in place of the link, so the dated file
// kept the old calibration and the link was gone. Written through the link, as any editor does.
TEST(WriteFileAtomically, ReplacingWritesThroughASymlinkAndKeepsIt) {
  const auto dir = testing::MakeTempDir("atomic_link");
  std::filesystem::create_directory(dir / "calibrations");
  const auto target = dir / "calibrations" / "dated.json";
  WriteFileAtomically(target, "old");
  ASSERT_EQ(::chmod(target.c_str(), 0640), 0);
  std::filesystem::create_symlink("calibrations/dated.json", dir / "calib.json");  // relative
  std::filesystem::create_symlink(dir / "calib.json", dir / "current.json");       // a chain
  for (const char* link : {"calib.json", "current.json"}) {
    WriteFileAtomically(dir / link, std::string("new through ") + link);
    EXPECT_TRUE(std::filesystem::is_symlink(dir / link)) << link;
    EXPECT_EQ(ReadFileToString(target), std::string("new through ") + link);
    struct stat st;
    ASSERT_EQ(::stat(target.c_str(), &st), 0);
    EXPECT_EQ(st.st_mode & 07777, 0640u);  // the target's mode, kept
  }
  EXPECT_EQ(std::filesystem::read_symlink(dir / "calib.json"), "calibrations/dated.json");
  // A link to a file not written yet creates it, as writing through a link does.
  std::filesystem::create_symlink("calibrations/next.json", dir / "next.json");
  WriteFileAtomically(dir / "next.json", "first");
  EXPECT_TRUE(std::filesystem::is_symlink(dir / "next.json"));
  EXPECT_EQ(ReadFileToString(dir / "calibrations" / "next.json"), "first");
  // No temporary file is left in either folder.
  for (const auto& folder : {dir, dir / "calibrations"}) {
    for (const auto& entry : std::filesystem::directory_iterator(folder)) {
      EXPECT_EQ(entry.path().filename().string().find(".tmp-"), std::string::npos) << entry.path();
    }
  }
  // Without overwrite a link is an existing file, refused as before.
  EXPECT_THROW(WriteFileAtomically(dir / "calib.json", "x", /*overwrite=*/false),
               std::runtime_error);
  EXPECT_EQ(ReadFileToString(target), "new through current.json");
  // A loop of links is an error naming the path, not a hang.
  std::filesystem::create_symlink("loop_b", dir / "loop_a");
  std::filesystem::create_symlink("loop_a", dir / "loop_b");
  try {
    WriteFileAtomically(dir / "loop_a", "x");
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find((dir / "loop_a").string()), std::string::npos) << e.what();
  }
  EXPECT_TRUE(std::filesystem::is_symlink(dir / "loop_a"));
}

TEST(WriteFileAtomically, MissingDirectoryThrowsNamingPath) {
  const auto dir = testing::MakeTempDir("atomic");
  const auto path = dir / "no" / "such" / "out.txt";
  try {
    WriteFileAtomically(path, "x");
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find(path.string()), std::string::npos) << e.what();
  }
}

TEST(ReadFileToString, DirectoryIsAnError) {
  const auto dir = testing::MakeTempDir("read");
  EXPECT_THROW(ReadFileToString(dir), std::invalid_argument);
}

TEST(ReadFileToString, MissingFileNamesPath) {
  try {
    ReadFileToString("/nonexistent/trackcal/file.json");
    FAIL() << "expected an exception";
  } catch (const std::invalid_argument& e) {
    EXPECT_NE(std::string(e.what()).find("/nonexistent/trackcal/file.json"), std::string::npos);
  }
}

}  // namespace
}  // namespace trackcal
