// libFuzzer target: arbitrary bytes as mll.v1 request messages through the
// service's handlers (see RunServiceInput in harness.h).
#include <cstddef>
#include <cstdint>

#include "harness.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  mll::fuzz::RunServiceInput(data, size);
  return 0;
}
