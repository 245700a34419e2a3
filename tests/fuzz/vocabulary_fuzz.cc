// libFuzzer target: arbitrary bytes as a stored appearance vocabulary (paper 000) must give a
// Status, never a crash or an out-of-bounds access.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/appearance/vocabulary.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  (void)lifemap::appearance::Vocabulary::Deserialize(bytes);
  return 0;
}
