// libFuzzer target: arbitrary bytes as a forest model file (what UploadModel receives and the
// store keeps) must give a Status, never a crash, hang or out-of-bounds access; a model that
// loads must describe itself consistently.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/forest/forest.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string bytes(reinterpret_cast<const char*>(data), size);
  lifemap::forest::ModelDescription description;
  auto forest = lifemap::forest::Forest::Deserialize(bytes, &description);
  if (forest.ok()) {
    // What a server does with a loaded model's metadata.
    (void)forest->tree_count();
    (void)forest->node_count();
    (void)forest->Serialize(description);
  }
  return 0;
}
