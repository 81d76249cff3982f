// File helpers every module that writes outputs or records provenance uses: atomic writes (a crash or a
// full disk never leaves a half-written output in place of a good one) and SHA-256 digests of inputs.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "core/printable_text.h"  // Utf16TextProblem, for the readers

namespace trackcal {

// Reads a whole file; throws std::invalid_argument naming the path if it cannot be read.
std::string ReadFileToString(const std::filesystem::path& path);

// Writes `contents` to `path` atomically: a temporary file in the same directory is written and
// fsync'ed, then renamed over `path` (overwrite) or hard-linked to it (no overwrite: link() fails
// if `path` exists, even if it appeared meanwhile, so nothing is ever replaced), then the directory
// is fsync'ed. Readers see either the old or the new file. A new file gets mode 0666 minus the
// umask; a regular file replaced (overwrite) passes its mode, and its group where the writer may
// set it, to the new one. A symbolic link replaced (overwrite) is written through and kept: the
// file it leads to (through a chain of links; made if it does not exist) is replaced. Throws
// std::runtime_error naming the path and the cause on failure (the temporary file is removed);
// without overwrite, "<path>: exists; refusing to overwrite it" for an existing file, and a message
// saying so on a file system without hard links (FAT): no fallback could guarantee that nothing is
// replaced.
void WriteFileAtomically(const std::filesystem::path& path, std::string_view contents,
                         bool overwrite = true);

// Creates a new, empty file "<folder of path>/.<file name of path>.tmp-XXXXXX" (X random) for
// writing, with mode 0666 minus the umask as open() gives any new file. Returns its descriptor and
// sets *temp_path, or returns -1 with errno set. (mkstemp's mode 0600 would have to be widened with
// the umask, which can only be read by changing it for every thread of the process.)
int CreateTemporaryFileBeside(const std::filesystem::path& path, std::string* temp_path);

// The same for a folder (mode 0777 minus the umask, as mkdir() gives any new folder; mkdtemp's
// 0700 has the same problem): false with errno set if it cannot be created.
bool CreateTemporaryFolderBeside(const std::filesystem::path& path, std::string* temp_path);

// Incremental SHA-256 (FIPS 180-4).
class Sha256 {
 public:
  Sha256();
  void Update(const void* data, size_t size);
  void Update(std::string_view data) { Update(data.data(), data.size()); }
  // The 32-byte digest; the object must not be updated afterwards.
  std::array<uint8_t, 32> Finish();
  // Lower-case hexadecimal digest (64 characters).
  std::string FinishHex();

 private:
  void ProcessBlock(const uint8_t* block);

  std::array<uint32_t, 8> state_;
  std::array<uint8_t, 64> buffer_{};
  size_t buffer_size_ = 0;
  uint64_t total_bytes_ = 0;
  bool finished_ = false;
};

// Lower-case hexadecimal SHA-256 of a byte string.
std::string Sha256Hex(std::string_view data);

// Lower-case hexadecimal SHA-256 of a file's contents, streamed; throws std::invalid_argument naming
// the path if it cannot be read.
std::string Sha256HexOfFile(const std::filesystem::path& path);

// True if `text` is 64 lower-case hexadecimal characters.
bool IsSha256Hex(std::string_view text);

// The system's reason for an errno value, for "<path>: cannot open ...: <reason>" ("No such file or
// directory", "Permission denied"); "unknown error" for 0 (a stream that failed without a system
// call failing). Callers save errno right after the failed call: any later call may change it.
std::string SystemErrorText(int error_number);

}  // namespace trackcal
