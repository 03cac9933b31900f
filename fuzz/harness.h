// Fuzz harnesses shared by the libFuzzer targets (fuzz/*_fuzzer.cc) and the
// regression test that replays their corpora and crash inputs
// (tests/reliability/fuzz_regression_test.cc), so that a crash found by the
// fuzzer is replayed through exactly the same code.
//
// A harness returns normally for every input the code under test handles
// correctly (an OK result or a clean error with the documented code) and
// aborts with a message on anything else: a wrong status code, a non-finite
// result, a response that does not match its request.
#ifndef MLL_FUZZ_HARNESS_H_
#define MLL_FUZZ_HARNESS_H_

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "mll/service/metrics.h"

namespace mll::fuzz {

// The service's request handlers (mll::service::Operations over a real Registry
// and WorkerPool). The input is a sequence of operations, each
//   [kind: 1 byte][length: 2 bytes little-endian][length bytes of proto]
// where kind mod kMethodCount is an mll::service::Method (metrics.h: the RPCs
// in the proto's order) and picks the request message the bytes are parsed as;
// for Method::kSession they are a SessionRequest whose operation runs as a
// Session stream runs it (a created env is session-bound unless detached).
// Names of the form "@<digit>" are replaced by the name of the env created n-th
// by this input (mod the count), so that the fuzzer reaches live environments.
// Every env the input created is deleted at its end, so each input runs from
// the same empty state.
void RunServiceInput(const uint8_t* data, size_t size);

// The simulation core (Env, AecEnv, RenderEnv/EncodePng): a config decoded
// field by field from the bytes (out-of-range values included), then
// episodes of parallel or AEC steps with arbitrary (NaN, infinite,
// out-of-range) actions, resets and renders.
void RunCoreInput(const uint8_t* data, size_t size);

// Reports a broken contract and aborts (so libFuzzer and the regression test
// both see a crash with the reason on stderr).
[[noreturn]] void HarnessFailure(const std::string& harness,
                                 const std::string& what);

// Appends one framed operation to `input` (for seed corpora and tests).
void AppendServiceOp(service::Method method, const std::string& proto_bytes,
                     std::vector<uint8_t>* input);

}  // namespace mll::fuzz

#endif  // MLL_FUZZ_HARNESS_H_
