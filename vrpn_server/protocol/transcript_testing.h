// Test helpers: loading the captured reference sessions copied to tests/data/vrpn/ (see its
// README.md) and decoding them. Used by the protocol and server replay tests only.
#pragma once

#include <filesystem>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

#include "tests/test_utils.h"
#include "vrpn_server/protocol/stream_parser.h"

namespace trackcal::vrpn::testing {

inline std::filesystem::path TranscriptDir() {
  return trackcal::testing::SourceDir() / "tests" / "data" / "vrpn";
}

inline std::vector<std::filesystem::path> TranscriptScenarios() {
  std::vector<std::filesystem::path> dirs;
  for (const auto& e : std::filesystem::directory_iterator(TranscriptDir())) {
    if (e.is_directory()) dirs.push_back(e.path());
  }
  std::sort(dirs.begin(), dirs.end());
  return dirs;
}

inline std::vector<std::uint8_t> ReadBytes(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error(path.string() + ": cannot open");
  return std::vector<std::uint8_t>(std::istreambuf_iterator<char>(in), {});
}

// One row of client.csv: sensor,x,y,z,qx,qy,qz,qw,msg_time_sec,msg_time_usec.
struct CsvPose {
  int sensor = 0;
  double v[7] = {};  // x, y, z, qx, qy, qz, qw
  std::uint32_t sec = 0;
  std::uint32_t usec = 0;
};

inline std::vector<CsvPose> ReadClientCsv(const std::filesystem::path& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error(path.string() + ": cannot open");
  std::vector<CsvPose> rows;
  std::string line;
  int line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (line.empty()) continue;
    std::stringstream ss(line);
    std::string field;
    std::vector<std::string> f;
    while (std::getline(ss, field, ',')) f.push_back(field);
    if (f.size() != 10) {
      throw std::runtime_error(path.string() + ":" + std::to_string(line_no) + ": expected 10 fields");
    }
    CsvPose p;
    p.sensor = std::stoi(f[0]);
    for (int i = 0; i < 7; ++i) p.v[i] = std::stod(f[1 + i]);
    p.sec = static_cast<std::uint32_t>(std::stoul(f[8]));
    p.usec = static_cast<std::uint32_t>(std::stoul(f[9]));
    rows.push_back(p);
  }
  return rows;
}

}  // namespace trackcal::vrpn::testing
