// libFuzzer target: arbitrary configs and action sequences through the
// simulation core (see RunCoreInput in harness.h).
#include <cstddef>
#include <cstdint>

#include "harness.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  mll::fuzz::RunCoreInput(data, size);
  return 0;
}
