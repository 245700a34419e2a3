// Seeds a fuzz target makes itself (valid inputs built by lifemap's own writers, rather than
// binary files kept in the repository): `LIFEMAP_FUZZ_SEEDS=DIR target` writes them into DIR
// and exits; scripts/fuzz does this before each run.
#pragma once

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

namespace lifemap::fuzz {

inline void WriteFile(const std::string& path, const std::string& bytes) {
  std::ofstream(path, std::ios::binary | std::ios::trunc) << bytes;
}

// Call from LLVMFuzzerInitialize: when LIFEMAP_FUZZ_SEEDS names a folder, `write(folder)`
// fills it and the process exits.
template <typename Writer>
void WriteSeedsIfAsked(Writer write) {
  const char* dir = std::getenv("LIFEMAP_FUZZ_SEEDS");
  if (dir == nullptr) return;
  std::filesystem::create_directories(dir);
  write(std::string(dir));
  std::exit(0);
}

}  // namespace lifemap::fuzz
