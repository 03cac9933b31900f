#include "load_common.h"

#include <dirent.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <mutex>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/strip.h"

namespace mll::client::load {
namespace {

constexpr int kMaxNotedErrors = 20;

std::mutex& ErrorsMutex() {
  static std::mutex* const mutex = new std::mutex;
  return *mutex;
}

std::string& ErrorLog() {
  static std::string* const log = new std::string;
  return *log;
}

}  // namespace

absl::StatusOr<Client> ConnectClient(const std::string& address, int index) {
  absl::StatusOr<Client> client = Client::Create(address);
  if (!client.ok() || index % 2 == 0) return client;
  return client->OpenSession();
}

void NoteError(const std::string& operation, const absl::Status& status) {
  static int noted = 0;
  std::lock_guard<std::mutex> lock(ErrorsMutex());
  if (noted++ < kMaxNotedErrors) {
    absl::StrAppend(&ErrorLog(), operation, ": ", status.ToString(), "\n");
  }
}

std::string NotedErrors() {
  std::lock_guard<std::mutex> lock(ErrorsMutex());
  return ErrorLog();
}

void Latencies::Merge(const Latencies& other) {
  micros.insert(micros.end(), other.micros.begin(), other.micros.end());
  errors += other.errors;
}

double Latencies::Quantile(double q) {
  if (micros.empty()) return 0;
  std::sort(micros.begin(), micros.end());
  const size_t rank = static_cast<size_t>(std::ceil(q * micros.size()));
  return micros[std::clamp<size_t>(rank, 1, micros.size()) - 1];
}

int64_t ResidentKib(int pid) {
  std::ifstream status(absl::StrCat("/proc/", pid, "/status"));
  std::string line;
  while (std::getline(status, line)) {
    absl::string_view rest = line;
    if (absl::ConsumePrefix(&rest, "VmRSS:")) {
      rest = absl::StripAsciiWhitespace(rest);
      int64_t kib = 0;
      return absl::SimpleAtoi(rest.substr(0, rest.find(' ')), &kib) ? kib : -1;
    }
  }
  return -1;
}

int OpenFds(int pid) {
  DIR* dir = opendir(absl::StrCat("/proc/", pid, "/fd").c_str());
  if (dir == nullptr) return -1;
  int count = 0;
  while (dirent* entry = readdir(dir)) {
    if (entry->d_name[0] != '.') ++count;
  }
  closedir(dir);
  return count;
}

}  // namespace mll::client::load
