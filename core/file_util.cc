#include "core/file_util.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <fstream>
#include <random>
#include <stdexcept>
#include <vector>

namespace trackcal {

namespace {

std::string ErrnoText() { return std::strerror(errno); }

// Closes a descriptor and removes a temporary file unless released.
class TempFileGuard {
 public:
  TempFileGuard(int fd, std::string path) : fd_(fd), path_(std::move(path)) {}
  ~TempFileGuard() {
    if (fd_ >= 0) ::close(fd_);
    if (!released_) ::unlink(path_.c_str());
  }
  int fd() const { return fd_; }
  int ReleaseFd() {
    const int fd = fd_;
    fd_ = -1;
    return fd;
  }
  void Release() { released_ = true; }

 private:
  int fd_;
  std::string path_;
  bool released_ = false;
};

constexpr std::array<uint32_t, 64> kRoundConstants = {
    0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4, 0xab1c5ed5,
    0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe, 0x9bdc06a7, 0xc19bf174,
    0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f, 0x4a7484aa, 0x5cb0a9dc, 0x76f988da,
    0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7, 0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967,
    0x27b70a85, 0x2e1b2138, 0x4d2c6dfc, 0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85,
    0xa2bfe8a1, 0xa81a664b, 0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070,
    0x19a4c116, 0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
    0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7, 0xc67178f2};

inline uint32_t RotateRight(uint32_t x, int n) { return (x >> n) | (x << (32 - n)); }

}  // namespace

std::string ReadFileToString(const std::filesystem::path& path) {
  std::error_code ec;
  if (std::filesystem::is_directory(path, ec)) {
    throw std::invalid_argument(path.string() + ": cannot read: is a directory");
  }
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::invalid_argument(path.string() + ": cannot open for reading: " + ErrnoText());
  std::string contents((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw std::invalid_argument(path.string() + ": read error: " + ErrnoText());
  return contents;
}

std::string SystemErrorText(int error_number) {
  return error_number != 0 ? std::strerror(error_number) : "unknown error";
}

namespace {

// Creates "<folder of path>/.<file name of path>.tmp-XXXXXX" (X random) with `create(name)`, which
// returns >= 0 on success or -1 with errno set; retries a name that exists.
template <typename Create>
int CreateBeside(const std::filesystem::path& path, std::string* temp_path, Create create) {
  static constexpr char kChars[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789";
  const std::filesystem::path dir =
      path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  std::string hidden_name = ".";
  hidden_name += path.filename().string();
  hidden_name += ".tmp-";
  const std::string prefix = (dir / hidden_name).string();
  std::random_device random;
  for (int attempt = 0; attempt < 100; ++attempt) {
    std::string name = prefix;
    for (int i = 0; i < 6; ++i) name += kChars[random() % (sizeof(kChars) - 1)];
    const int result = create(name);
    if (result >= 0) {
      *temp_path = std::move(name);
      return result;
    }
    if (errno != EEXIST) return -1;
  }
  return -1;  // errno is EEXIST
}

}  // namespace

int CreateTemporaryFileBeside(const std::filesystem::path& path, std::string* temp_path) {
  return CreateBeside(path, temp_path, [](const std::string& name) {
    return ::open(name.c_str(), O_CREAT | O_EXCL | O_WRONLY | O_CLOEXEC, 0666);
  });
}

bool CreateTemporaryFolderBeside(const std::filesystem::path& path, std::string* temp_path) {
  return CreateBeside(path, temp_path,
                      [](const std::string& name) { return ::mkdir(name.c_str(), 0777); }) >= 0;
}

namespace {

// The file a write to `path` lands in: `path`, or where the symbolic link(s) it names lead (a link
// to a file not made yet leads to where it will be). Throws naming `path` for a loop of links.
std::filesystem::path FollowSymlinks(const std::filesystem::path& path) {
  std::filesystem::path at = path;
  for (int hops = 0; hops < 40; ++hops) {  // Linux's own limit (ELOOP)
    struct stat st {};
    if (::lstat(at.c_str(), &st) != 0 || !S_ISLNK(st.st_mode)) return at;
    std::error_code ec;
    const std::filesystem::path next = std::filesystem::read_symlink(at, ec);
    if (ec) {
      throw std::runtime_error(path.string() + ": cannot read the symbolic link " + at.string() +
                               ": " + ec.message());
    }
    at = next.is_absolute() ? next : at.parent_path() / next;
  }
  throw std::runtime_error(path.string() + ": " + std::strerror(ELOOP));
}

}  // namespace

void WriteFileAtomically(const std::filesystem::path& given, std::string_view contents,
                         bool overwrite) {
  static constexpr char kExists[] = ": exists; refusing to overwrite it";
  std::error_code ec;
  if (!overwrite && std::filesystem::exists(std::filesystem::symlink_status(given, ec))) {
    throw std::runtime_error(given.string() + kExists);  // before the work of writing it
  }
  // Replacing a symbolic link writes through it and keeps it (calib.json -> a dated file a server
  // reads through the link): renamed over the link, the new file replaced the link itself and the
  // file it led to kept the old contents. Messages still name the path given.
  const std::filesystem::path path = overwrite ? FollowSymlinks(given) : given;
  const std::string name = given.string();
  const std::filesystem::path dir =
      path.has_parent_path() ? path.parent_path() : std::filesystem::path(".");
  // A file replaced keeps its mode and group: a lab's group-writable 0664 calibration became 0644
  // (the umask's), and a colleague could no longer refit it.
  struct stat replaced {};
  const bool replacing =
      overwrite && ::stat(path.c_str(), &replaced) == 0 && S_ISREG(replaced.st_mode);
  std::string temp;
  const int fd = CreateTemporaryFileBeside(path, &temp);
  if (fd < 0) {
    throw std::runtime_error(name + ": cannot create a temporary file in " + dir.string() + ": " +
                             ErrnoText());
  }
  TempFileGuard guard(fd, temp);
  size_t written = 0;
  while (written < contents.size()) {
    const ssize_t n = ::write(fd, contents.data() + written, contents.size() - written);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw std::runtime_error(name + ": write failed: " + ErrnoText());
    }
    written += static_cast<size_t>(n);
  }
  if (replacing) {
    // The group first: it fails unless the writer is in that group (or root), and the writer's
    // group then stays, as for a new file. Then the mode, which fchown may have cleared bits of.
    // A mode that cannot be set is an error: the file would be more open than the user's.
    [[maybe_unused]] const int group_kept = ::fchown(fd, static_cast<uid_t>(-1), replaced.st_gid);
    if (::fchmod(fd, replaced.st_mode & 07777) != 0) {
      throw std::runtime_error(name + ": cannot give the new file the mode of the one " +
                               "it replaces: " + ErrnoText());
    }
  }
  if (::fsync(fd) != 0) throw std::runtime_error(name + ": fsync failed: " + ErrnoText());
  if (::close(guard.ReleaseFd()) != 0) {
    throw std::runtime_error(name + ": close failed: " + ErrnoText());
  }
  if (overwrite) {
    if (::rename(temp.c_str(), path.c_str()) != 0) {
      throw std::runtime_error(name +
                               ": cannot rename the temporary file into place: " + ErrnoText());
    }
    guard.Release();
  } else if (::link(temp.c_str(), path.c_str()) != 0) {  // the guard removes the temporary
    const int error = errno;
    if (error == EEXIST) throw std::runtime_error(name + kExists);
    if (error == EPERM || error == EOPNOTSUPP || error == ENOSYS || error == EMLINK) {
      throw std::runtime_error(name + ": not written: the file system of " + dir.string() +
                               " has no hard links (" + std::strerror(error) +
                               "), which trackcal needs to write a file without risking replacing "
                               "another; write it to another folder");
    }
    throw std::runtime_error(
        name + ": cannot link the temporary file into place: " + std::strerror(error));
  }
  // The link made: the guard unlinks the temporary name, the file stays under `path`.
  // Persist the rename or link itself; failure here does not lose data, so it is not an error.
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (dir_fd >= 0) {
    ::fsync(dir_fd);
    ::close(dir_fd);
  }
}

Sha256::Sha256()
    : state_{0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a, 0x510e527f, 0x9b05688c, 0x1f83d9ab,
             0x5be0cd19} {}

void Sha256::ProcessBlock(const uint8_t* block) {
  uint32_t w[64];
  for (int i = 0; i < 16; ++i) {
    w[i] = (uint32_t{block[4 * i]} << 24) | (uint32_t{block[4 * i + 1]} << 16) |
           (uint32_t{block[4 * i + 2]} << 8) | uint32_t{block[4 * i + 3]};
  }
  for (int i = 16; i < 64; ++i) {
    const uint32_t s0 = RotateRight(w[i - 15], 7) ^ RotateRight(w[i - 15], 18) ^ (w[i - 15] >> 3);
    const uint32_t s1 = RotateRight(w[i - 2], 17) ^ RotateRight(w[i - 2], 19) ^ (w[i - 2] >> 10);
    w[i] = w[i - 16] + s0 + w[i - 7] + s1;
  }
  uint32_t a = state_[0], b = state_[1], c = state_[2], d = state_[3];
  uint32_t e = state_[4], f = state_[5], g = state_[6], h = state_[7];
  for (int i = 0; i < 64; ++i) {
    const uint32_t s1 = RotateRight(e, 6) ^ RotateRight(e, 11) ^ RotateRight(e, 25);
    const uint32_t ch = (e & f) ^ (~e & g);
    const uint32_t t1 = h + s1 + ch + kRoundConstants[i] + w[i];
    const uint32_t s0 = RotateRight(a, 2) ^ RotateRight(a, 13) ^ RotateRight(a, 22);
    const uint32_t maj = (a & b) ^ (a & c) ^ (b & c);
    const uint32_t t2 = s0 + maj;
    h = g;
    g = f;
    f = e;
    e = d + t1;
    d = c;
    c = b;
    b = a;
    a = t1 + t2;
  }
  state_[0] += a;
  state_[1] += b;
  state_[2] += c;
  state_[3] += d;
  state_[4] += e;
  state_[5] += f;
  state_[6] += g;
  state_[7] += h;
}

void Sha256::Update(const void* data, size_t size) {
  if (finished_) throw std::logic_error("Sha256::Update after Finish");
  const auto* bytes = static_cast<const uint8_t*>(data);
  total_bytes_ += size;
  if (buffer_size_ > 0) {
    const size_t take = std::min(size, buffer_.size() - buffer_size_);
    std::memcpy(buffer_.data() + buffer_size_, bytes, take);
    buffer_size_ += take;
    bytes += take;
    size -= take;
    if (buffer_size_ < buffer_.size()) return;
    ProcessBlock(buffer_.data());
    buffer_size_ = 0;
  }
  while (size >= 64) {
    ProcessBlock(bytes);
    bytes += 64;
    size -= 64;
  }
  std::memcpy(buffer_.data(), bytes, size);
  buffer_size_ = size;
}

std::array<uint8_t, 32> Sha256::Finish() {
  if (finished_) throw std::logic_error("Sha256::Finish called twice");
  const uint64_t bit_length = total_bytes_ * 8;
  uint8_t pad[72] = {0x80};
  // Pad to 56 mod 64, then the 64-bit big-endian message length.
  const size_t pad_size = (buffer_size_ < 56 ? 56 - buffer_size_ : 120 - buffer_size_);
  Update(pad, pad_size);
  uint8_t length[8];
  for (int i = 0; i < 8; ++i) length[i] = static_cast<uint8_t>(bit_length >> (56 - 8 * i));
  Update(length, 8);
  finished_ = true;
  std::array<uint8_t, 32> digest;
  for (int i = 0; i < 8; ++i) {
    for (int j = 0; j < 4; ++j) digest[4 * i + j] = static_cast<uint8_t>(state_[i] >> (24 - 8 * j));
  }
  return digest;
}

std::string Sha256::FinishHex() {
  static constexpr char kHex[] = "0123456789abcdef";
  const std::array<uint8_t, 32> digest = Finish();
  std::string hex;
  hex.reserve(64);
  for (uint8_t byte : digest) {
    hex.push_back(kHex[byte >> 4]);
    hex.push_back(kHex[byte & 15]);
  }
  return hex;
}

std::string Sha256Hex(std::string_view data) {
  Sha256 sha;
  sha.Update(data);
  return sha.FinishHex();
}

std::string Sha256HexOfFile(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::invalid_argument(path.string() + ": cannot open for reading: " + ErrnoText());
  Sha256 sha;
  std::vector<char> chunk(1 << 16);
  while (in) {
    in.read(chunk.data(), static_cast<std::streamsize>(chunk.size()));
    sha.Update(chunk.data(), static_cast<size_t>(in.gcount()));
  }
  if (in.bad()) throw std::invalid_argument(path.string() + ": read error: " + ErrnoText());
  return sha.FinishHex();
}

bool IsSha256Hex(std::string_view text) {
  if (text.size() != 64) return false;
  for (char c : text) {
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
  }
  return true;
}

}  // namespace trackcal
