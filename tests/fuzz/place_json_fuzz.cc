// libFuzzer target: arbitrary text as a stored floor plan or architecture descriptor (JSON,
// paper 004) must give a Status, never a crash; what parses is written back and read again.
#include <cstddef>
#include <cstdint>
#include <string>

#include "core/place/descriptor.h"
#include "core/place/serialize.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const std::string json(reinterpret_cast<const char*>(data), size);
  if (auto d = lifemap::place::DescriptorFromJson(json); d.ok()) {
    (void)lifemap::place::DescriptorText(*d);
    (void)lifemap::place::DescriptorFromJson(lifemap::place::DescriptorToJson(*d));
  }
  if (auto plan = lifemap::place::FloorPlanFromJson(json); plan.ok()) {
    (void)lifemap::place::FloorPlanFromJson(lifemap::place::FloorPlanToJson(*plan));
  }
  return 0;
}
