// Shared by the load and soak tools (bench/load): client construction over
// either transport, the operation mix's pieces, and latency percentiles.
#ifndef MLL_BENCH_LOAD_LOAD_COMMON_H_
#define MLL_BENCH_LOAD_LOAD_COMMON_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "mll/client.h"

namespace mll::client::load {

// Client `index` of a run: even ones make unary calls on their own channel,
// odd ones carry every environment call on their own Session stream, so a
// run exercises both transports.
absl::StatusOr<Client> ConnectClient(const std::string& address, int index);

// Records the first few unexpected errors (thread-safe) for the report.
void NoteError(const std::string& operation, const absl::Status& status);
// The errors noted so far, one per line.
std::string NotedErrors();

// Latencies of one operation kind, in microseconds.
struct Latencies {
  std::vector<double> micros;
  int64_t errors = 0;
  void Merge(const Latencies& other);
  // The q-quantile (0..1) by nearest rank; 0 when empty. Sorts.
  double Quantile(double q);
};

// Resident set size (VmRSS, KiB) and open descriptors of process `pid`;
// -1 when unreadable.
int64_t ResidentKib(int pid);
int OpenFds(int pid);

}  // namespace mll::client::load

#endif  // MLL_BENCH_LOAD_LOAD_COMMON_H_
