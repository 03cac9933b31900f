// delay_proxy: a loopback TCP proxy that holds every byte for a fixed time,
// the slow link of bench/latency/bench_latency.py (the kernel here has no
// netem).
//
//   delay_proxy --listen=127.0.0.1:0 --target=127.0.0.1:PORT --delay_us=N
//               [--port_file=F] [--spin_us=100] [--max_buffer_mib=64]
//
// Each accepted connection gets its own connection to --target; bytes flow
// both ways, each chunk written N microseconds after the read that returned
// it (one-way delay: a round trip through the proxy gains 2N), in order, with
// no bandwidth limit. One thread, epoll. The wait is a timerfd on the
// monotonic clock armed a margin before the earliest deadline, then a spin
// that keeps polling the sockets (so reads are still stamped on time) until
// the deadline itself: the wake-up latency of the timer does not add to the
// delay. The margin follows the timer's observed wake-up latency (plus 10 us),
// at most --spin_us. A direction buffers at most --max_buffer_mib and then
// stops reading until its queue drains. A peer's EOF is forwarded (shutdown)
// after the delay too; a reset or error closes both sides at once.
//
// With --realtime it runs under SCHED_FIFO: on a busy machine a woken proxy
// otherwise waits for a CPU, which the link's delay should not depend on.
//
// Loopback only: --listen and --target must be 127.0.0.0/8, ::1 or localhost.
// On SIGTERM or SIGINT it prints one JSON line of statistics (chunks, bytes,
// how late chunks were written against their deadline) and exits 0.
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <sched.h>
#include <signal.h>
#include <sys/epoll.h>
#include <sys/prctl.h>
#include <sys/signalfd.h>
#include <sys/socket.h>
#include <sys/timerfd.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <deque>
#include <fstream>
#include <limits>
#include <memory>
#include <string>
#include <unordered_map>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "program_usage.h"

ABSL_FLAG(std::string, listen, "127.0.0.1:0",
          "host:port to accept connections on (loopback; port 0: a free one)");
ABSL_FLAG(std::string, target, "",
          "host:port to forward each connection to (loopback)");
ABSL_FLAG(int64_t, delay_us, 0,
          "one-way delay in microseconds, [0, 10000000]: the round trip gains "
          "twice this");
ABSL_FLAG(std::string, port_file, "",
          "if set, the listening port is written here (atomically) once the "
          "proxy accepts connections");
ABSL_FLAG(int64_t, spin_us, 100,
          "the most microseconds the timer wakes before a deadline, the proxy "
          "polling until the deadline; below that it follows the timer's "
          "observed lateness, [0, 10000]");
ABSL_FLAG(int64_t, max_buffer_mib, 64,
          "bytes held per direction of a connection before the proxy stops "
          "reading from its source, in MiB, [1, 4096]");
ABSL_FLAG(bool, realtime, false,
          "run under SCHED_FIFO (priority 1) so that the machine's other work "
          "does not delay a release (needs CAP_SYS_NICE; otherwise a warning "
          "and the normal policy)");
ABSL_FLAG(int64_t, parent_pid, 0,
          "exit (as on SIGTERM) when the process with this pid, which must be "
          "the one that started delay_proxy, exits (0: off)");

namespace mll::bench {
namespace {

constexpr int64_t kNsPerUs = 1000;
constexpr size_t kReadBytes = 256 * 1024;
constexpr int64_t kNever = std::numeric_limits<int64_t>::max();
// Lateness histogram: 1 us bins up to 100 ms, the last bin for later ones.
constexpr size_t kLateBins = 100001;

int64_t NowNs() {
  timespec now;
  clock_gettime(CLOCK_MONOTONIC, &now);
  return int64_t{now.tv_sec} * 1000000000 + now.tv_nsec;
}

absl::Status ErrnoStatus(const std::string& what) {
  return absl::InternalError(absl::StrCat(what, ": ", std::strerror(errno)));
}

// A loopback socket address parsed from "host:port" or "[::1]:port".
struct Endpoint {
  sockaddr_storage address{};
  socklen_t length = 0;
  int family = AF_INET;
};

absl::StatusOr<Endpoint> ParseLoopback(const std::string& flag,
                                       const std::string& text) {
  const size_t colon = text.rfind(':');
  if (colon == std::string::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", flag, "=", text, " is not host:port"));
  }
  std::string host = text.substr(0, colon);
  int port = 0;
  if (!absl::SimpleAtoi(text.substr(colon + 1), &port) || port < 0 ||
      port > 65535) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", flag, "=", text, ": the port is not 0..65535"));
  }
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  if (host == "localhost") host = "127.0.0.1";
  Endpoint endpoint;
  in_addr v4{};
  in6_addr v6{};
  if (inet_pton(AF_INET, host.c_str(), &v4) == 1 &&
      (ntohl(v4.s_addr) >> 24) == 127) {
    auto* address = reinterpret_cast<sockaddr_in*>(&endpoint.address);
    address->sin_family = AF_INET;
    address->sin_addr = v4;
    address->sin_port = htons(static_cast<uint16_t>(port));
    endpoint.length = sizeof(sockaddr_in);
    endpoint.family = AF_INET;
    return endpoint;
  }
  if (inet_pton(AF_INET6, host.c_str(), &v6) == 1 &&
      IN6_IS_ADDR_LOOPBACK(&v6)) {
    auto* address = reinterpret_cast<sockaddr_in6*>(&endpoint.address);
    address->sin6_family = AF_INET6;
    address->sin6_addr = v6;
    address->sin6_port = htons(static_cast<uint16_t>(port));
    endpoint.length = sizeof(sockaddr_in6);
    endpoint.family = AF_INET6;
    return endpoint;
  }
  return absl::InvalidArgumentError(absl::StrCat(
      "--", flag, "=", text,
      " is not a loopback address (127.0.0.0/8, ::1 or localhost): "
      "delay_proxy only forwards between local processes"));
}

absl::Status CheckRange(const char* flag, int64_t value, int64_t low,
                        int64_t high) {
  if (value < low || value > high) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--", flag, "=", value, " is out of range [", low, ", ", high, "]"));
  }
  return absl::OkStatus();
}

bool WritePortFile(const std::string& path, int port) {
  const std::string temporary = path + ".tmp";
  {
    std::ofstream out(temporary, std::ios::trunc);
    out << port << "\n";
    if (!out.good()) return false;
  }
  return std::rename(temporary.c_str(), path.c_str()) == 0;
}

void SetNoDelay(int fd) {
  const int one = 1;
  setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
}

// Bytes read at one time, due at `release_ns`; `eof` marks the source's end
// (forwarded as a shutdown of the destination's writing side).
struct Chunk {
  int64_t release_ns = 0;
  std::string bytes;
  bool eof = false;
};

// One direction of a connection: read from `from`, written to `to`.
struct Direction {
  int from = -1;
  int to = -1;
  std::deque<Chunk> queue;
  size_t queued_bytes = 0;
  size_t written = 0;          // Bytes of the front chunk already written.
  bool reading = true;         // EPOLLIN wanted on `from`.
  bool write_blocked = false;  // EPOLLOUT wanted on `to`.
  bool read_eof = false;       // `from` said EOF.
  bool finished = false;       // The EOF went out.
};

struct Connection {
  int client = -1;
  int target = -1;
  Direction up;    // client -> target
  Direction down;  // target -> client
};

struct Stats {
  int64_t connections = 0;
  int64_t chunks = 0;
  int64_t bytes = 0;
  std::vector<int64_t> late_us = std::vector<int64_t>(kLateBins, 0);

  int64_t LatePercentile(double fraction) const {
    int64_t total = 0;
    for (int64_t count : late_us) total += count;
    if (total == 0) return 0;
    const auto rank = static_cast<int64_t>(fraction * (total - 1));
    int64_t seen = 0;
    for (size_t bin = 0; bin < late_us.size(); ++bin) {
      seen += late_us[bin];
      if (seen > rank) return static_cast<int64_t>(bin);
    }
    return static_cast<int64_t>(late_us.size() - 1);
  }

  int64_t LateMax() const {
    for (size_t bin = late_us.size(); bin-- > 0;) {
      if (late_us[bin] != 0) return static_cast<int64_t>(bin);
    }
    return 0;
  }
};

class Proxy {
 public:
  Proxy(Endpoint target, int64_t delay_ns, int64_t spin_ns, size_t max_buffer)
      : target_(target),
        delay_ns_(delay_ns),
        spin_ns_(spin_ns),
        max_buffer_(max_buffer) {}

  ~Proxy() {
    for (auto& [id, connection] : connections_) {
      close(connection->client);
      close(connection->target);
    }
    for (int fd : {listener_, epoll_, timer_, signals_}) {
      if (fd >= 0) close(fd);
    }
  }

  // Binds the listener and sets up epoll, the timer and the signals; returns
  // the listening port.
  absl::StatusOr<int> Start(const Endpoint& listen) {
    sigset_t mask;
    sigemptyset(&mask);
    sigaddset(&mask, SIGTERM);
    sigaddset(&mask, SIGINT);
    if (sigprocmask(SIG_BLOCK, &mask, nullptr) != 0) {
      return ErrnoStatus("sigprocmask");
    }
    signals_ = signalfd(-1, &mask, SFD_NONBLOCK | SFD_CLOEXEC);
    if (signals_ < 0) return ErrnoStatus("signalfd");
    timer_ = timerfd_create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC);
    if (timer_ < 0) return ErrnoStatus("timerfd_create");
    epoll_ = epoll_create1(EPOLL_CLOEXEC);
    if (epoll_ < 0) return ErrnoStatus("epoll_create1");
    listener_ =
        socket(listen.family, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
    if (listener_ < 0) return ErrnoStatus("socket");
    const int one = 1;
    setsockopt(listener_, SOL_SOCKET, SO_REUSEADDR, &one, sizeof(one));
    if (bind(listener_, reinterpret_cast<const sockaddr*>(&listen.address),
             listen.length) != 0) {
      return ErrnoStatus("bind --listen");
    }
    if (::listen(listener_, 128) != 0) return ErrnoStatus("listen");
    sockaddr_storage bound{};
    socklen_t bound_length = sizeof(bound);
    if (getsockname(listener_, reinterpret_cast<sockaddr*>(&bound),
                    &bound_length) != 0) {
      return ErrnoStatus("getsockname");
    }
    const int port =
        ntohs(bound.ss_family == AF_INET6
                  ? reinterpret_cast<sockaddr_in6*>(&bound)->sin6_port
                  : reinterpret_cast<sockaddr_in*>(&bound)->sin_port);
    for (auto [fd, tag] :
         {std::pair{listener_, kListenerTag}, std::pair{timer_, kTimerTag},
          std::pair{signals_, kSignalTag}}) {
      epoll_event event{};
      event.events = EPOLLIN;
      event.data.u64 = tag;
      if (epoll_ctl(epoll_, EPOLL_CTL_ADD, fd, &event) != 0) {
        return ErrnoStatus("epoll_ctl");
      }
    }
    return port;
  }

  // Forwards until SIGTERM or SIGINT.
  absl::Status Run() {
    std::array<epoll_event, 64> events;
    while (true) {
      ReleaseDue(NowNs());
      const int64_t next = NextDeadline();
      int timeout_ms = -1;
      if (next != kNever) {
        const int64_t wake = next - margin_ns_;
        if (wake <= NowNs()) {
          timeout_ms = 0;  // Spin: poll the sockets until the deadline.
        } else if (wake != armed_ns_) {
          itimerspec spec{};
          spec.it_value.tv_sec = wake / 1000000000;
          spec.it_value.tv_nsec = wake % 1000000000;
          if (timerfd_settime(timer_, TFD_TIMER_ABSTIME, &spec, nullptr) != 0) {
            return ErrnoStatus("timerfd_settime");
          }
          armed_ns_ = wake;
        }
      }
      const int count =
          epoll_wait(epoll_, events.data(), events.size(), timeout_ms);
      if (count < 0) {
        if (errno == EINTR) continue;
        return ErrnoStatus("epoll_wait");
      }
      for (int i = 0; i < count; ++i) {
        const uint64_t tag = events[i].data.u64;
        if (tag == kSignalTag) return absl::OkStatus();
        if (tag == kTimerTag) {
          if (armed_ns_ != 0) AdaptMargin(NowNs() - armed_ns_);
          uint64_t expirations;
          while (read(timer_, &expirations, sizeof(expirations)) > 0) {
          }
          armed_ns_ = 0;
        } else if (tag == kListenerTag) {
          Accept();
        } else {
          OnSocket(tag, events[i].events);
        }
      }
    }
  }

  const Stats& stats() const { return stats_; }
  int64_t margin_ns() const { return margin_ns_; }

 private:
  // epoll tags: these three (beyond any connection's), or
  // (connection id << 1) | (1 for the target's socket).
  static constexpr uint64_t kListenerTag = ~uint64_t{0};
  static constexpr uint64_t kTimerTag = kListenerTag - 1;
  static constexpr uint64_t kSignalTag = kListenerTag - 2;

  static uint64_t Tag(uint64_t id, bool target) {
    return (id << 1) | (target ? 1 : 0);
  }

  // The spin before a deadline follows how late the timer wakes the proxy:
  // up at once to the latest wake-up seen plus a guard, down slowly (1/32 of
  // the gap per wake-up), within [0, --spin_us]. A busy-waiting proxy would
  // take a core from the endpoints it sits between.
  void AdaptMargin(int64_t overshoot_ns) {
    constexpr int64_t kGuardNs = 10 * kNsPerUs;
    const int64_t wanted = std::max<int64_t>(overshoot_ns, 0) + kGuardNs;
    if (wanted > margin_ns_) {
      margin_ns_ = wanted;
    } else {
      margin_ns_ -= (margin_ns_ - wanted) / 32;
    }
    margin_ns_ = std::min(margin_ns_, spin_ns_);
  }

  void Accept() {
    while (true) {
      const int client =
          accept4(listener_, nullptr, nullptr, SOCK_NONBLOCK | SOCK_CLOEXEC);
      if (client < 0) {
        if (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR) {
          std::fprintf(stderr, "delay_proxy: accept: %s\n",
                       std::strerror(errno));
        }
        return;
      }
      // A blocking connect: on loopback it completes at once, and data the
      // client sends meanwhile waits in its socket.
      const int target = socket(target_.family, SOCK_STREAM | SOCK_CLOEXEC, 0);
      if (target < 0 ||
          connect(target, reinterpret_cast<const sockaddr*>(&target_.address),
                  target_.length) != 0) {
        std::fprintf(stderr, "delay_proxy: connect to --target: %s\n",
                     std::strerror(errno));
        if (target >= 0) close(target);
        close(client);
        continue;
      }
      fcntl(target, F_SETFL, fcntl(target, F_GETFL) | O_NONBLOCK);
      SetNoDelay(client);
      SetNoDelay(target);
      auto connection = std::make_unique<Connection>();
      connection->client = client;
      connection->target = target;
      connection->up.from = client;
      connection->up.to = target;
      connection->down.from = target;
      connection->down.to = client;
      const uint64_t id = next_id_++;
      for (bool is_target : {false, true}) {
        epoll_event event{};
        event.events = EPOLLIN;
        event.data.u64 = Tag(id, is_target);
        epoll_ctl(epoll_, EPOLL_CTL_ADD, is_target ? target : client, &event);
      }
      connections_.emplace(id, std::move(connection));
      ++stats_.connections;
    }
  }

  // The events wanted on one socket of `connection`.
  void UpdateInterest(uint64_t id, Connection& connection, bool target) {
    const Direction& reads = target ? connection.down : connection.up;
    const Direction& writes = target ? connection.up : connection.down;
    epoll_event event{};
    event.events =
        (reads.reading ? EPOLLIN : 0u) | (writes.write_blocked ? EPOLLOUT : 0u);
    event.data.u64 = Tag(id, target);
    epoll_ctl(epoll_, EPOLL_CTL_MOD,
              target ? connection.target : connection.client, &event);
  }

  void CloseConnection(uint64_t id) {
    auto found = connections_.find(id);
    if (found == connections_.end()) return;
    close(found->second->client);
    close(found->second->target);
    connections_.erase(found);
  }

  void OnSocket(uint64_t tag, uint32_t events) {
    const uint64_t id = tag >> 1;
    const bool target = (tag & 1) != 0;
    auto found = connections_.find(id);
    if (found == connections_.end()) return;  // Closed earlier in this batch.
    if (events & EPOLLERR) {
      CloseConnection(id);  // A reset: both sides go at once.
      return;
    }
    Connection& connection = *found->second;
    if (events & EPOLLOUT) {
      (target ? connection.up : connection.down).write_blocked = false;
      UpdateInterest(id, connection, target);
    }
    Direction& reads = target ? connection.down : connection.up;
    const Direction& writes = target ? connection.up : connection.down;
    if ((events & EPOLLHUP) && reads.read_eof && writes.finished) {
      // Nothing more to read or write here; stop the hang-up's events.
      epoll_ctl(epoll_, EPOLL_CTL_DEL, reads.from, nullptr);
      return;
    }
    if ((events & (EPOLLIN | EPOLLHUP)) && reads.reading) {
      const ssize_t got = read(reads.from, buffer_.data(), buffer_.size());
      const int64_t now = NowNs();
      if (got < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR) return;
        CloseConnection(id);  // A reset: both sides go at once.
        return;
      }
      Chunk chunk;
      chunk.release_ns = now + delay_ns_;
      if (got == 0) {
        chunk.eof = true;
        reads.read_eof = true;
        reads.reading = false;
      } else {
        chunk.bytes.assign(buffer_.data(), static_cast<size_t>(got));
        reads.queued_bytes += chunk.bytes.size();
        if (reads.queued_bytes >= max_buffer_) reads.reading = false;
      }
      reads.queue.push_back(std::move(chunk));
      if (!reads.reading) UpdateInterest(id, connection, target);
    }
  }

  // Writes the due chunks of `direction`; false when the connection failed.
  bool Release(Direction& direction, int64_t now, bool& interest_changed) {
    while (!direction.queue.empty() && !direction.write_blocked) {
      Chunk& chunk = direction.queue.front();
      if (chunk.release_ns > now) break;
      if (direction.written == 0) {
        const int64_t late_us = (now - chunk.release_ns) / kNsPerUs;
        ++stats_.late_us[std::min<size_t>(static_cast<size_t>(late_us),
                                          kLateBins - 1)];
        ++stats_.chunks;
      }
      if (chunk.eof) {
        shutdown(direction.to, SHUT_WR);
        direction.finished = true;
        direction.queue.pop_front();
        continue;
      }
      const ssize_t sent =
          send(direction.to, chunk.bytes.data() + direction.written,
               chunk.bytes.size() - direction.written, MSG_NOSIGNAL);
      if (sent < 0) {
        if (errno == EAGAIN || errno == EWOULDBLOCK) {
          direction.write_blocked = true;
          interest_changed = true;
          break;
        }
        if (errno == EINTR) continue;
        return false;
      }
      direction.written += static_cast<size_t>(sent);
      stats_.bytes += sent;
      if (direction.written < chunk.bytes.size()) continue;
      direction.queued_bytes -= chunk.bytes.size();
      direction.written = 0;
      direction.queue.pop_front();
      if (!direction.reading && !direction.read_eof &&
          direction.queued_bytes < max_buffer_) {
        direction.reading = true;
        interest_changed = true;
      }
    }
    return true;
  }

  void ReleaseDue(int64_t now) {
    std::vector<uint64_t> failed;
    std::vector<uint64_t> done;
    for (auto& [id, connection] : connections_) {
      for (bool target : {false, true}) {
        // The direction that writes to the client (target side read) or to
        // the target.
        Direction& direction = target ? connection->up : connection->down;
        bool interest_changed = false;
        if (!Release(direction, now, interest_changed)) {
          failed.push_back(id);
          break;
        }
        if (interest_changed) {
          // Reading interest lives on `from`, writing interest on `to`.
          UpdateInterest(id, *connection, direction.from == connection->target);
          UpdateInterest(id, *connection, direction.to == connection->target);
        }
      }
      if (connection->up.finished && connection->down.finished) {
        done.push_back(id);
      }
    }
    for (uint64_t id : failed) CloseConnection(id);
    for (uint64_t id : done) CloseConnection(id);
  }

  int64_t NextDeadline() const {
    int64_t next = kNever;
    for (const auto& [id, connection] : connections_) {
      for (const Direction* direction : {&connection->up, &connection->down}) {
        if (!direction->queue.empty() && !direction->write_blocked) {
          next = std::min(next, direction->queue.front().release_ns);
        }
      }
    }
    return next;
  }

  const Endpoint target_;
  const int64_t delay_ns_;
  const int64_t spin_ns_;
  const size_t max_buffer_;
  int listener_ = -1;
  int epoll_ = -1;
  int timer_ = -1;
  int signals_ = -1;
  int64_t armed_ns_ = 0;
  int64_t margin_ns_ = spin_ns_;  // How long before a deadline the timer wakes.
  uint64_t next_id_ = 1;
  std::unordered_map<uint64_t, std::unique_ptr<Connection>> connections_;
  std::vector<char> buffer_ = std::vector<char>(kReadBytes);
  Stats stats_;
};

absl::Status Main() {
  const int64_t delay_us = absl::GetFlag(FLAGS_delay_us);
  const int64_t spin_us = absl::GetFlag(FLAGS_spin_us);
  const int64_t max_buffer_mib = absl::GetFlag(FLAGS_max_buffer_mib);
  const int64_t parent_pid = absl::GetFlag(FLAGS_parent_pid);
  if (absl::Status status = CheckRange("delay_us", delay_us, 0, 10000000);
      !status.ok()) {
    return status;
  }
  if (absl::Status status = CheckRange("spin_us", spin_us, 0, 10000);
      !status.ok()) {
    return status;
  }
  if (absl::Status status =
          CheckRange("max_buffer_mib", max_buffer_mib, 1, 4096);
      !status.ok()) {
    return status;
  }
  if (absl::GetFlag(FLAGS_target).empty()) {
    return absl::InvalidArgumentError("--target=host:port is required");
  }
  absl::StatusOr<Endpoint> listen_at =
      ParseLoopback("listen", absl::GetFlag(FLAGS_listen));
  if (!listen_at.ok()) return listen_at.status();
  absl::StatusOr<Endpoint> target =
      ParseLoopback("target", absl::GetFlag(FLAGS_target));
  if (!target.ok()) return target.status();
  if (absl::Status status =
          mll::core::tools::FollowParent(parent_pid, "delay_proxy");
      !status.ok()) {
    return status;
  }
  // Timers fire when asked, not up to 50 us later (the default slack).
  prctl(PR_SET_TIMERSLACK, 1UL);
  if (absl::GetFlag(FLAGS_realtime)) {
    sched_param param{};
    param.sched_priority = 1;
    if (sched_setscheduler(0, SCHED_FIFO, &param) != 0) {
      std::fprintf(stderr,
                   "delay_proxy: --realtime: SCHED_FIFO refused (%s); "
                   "running under the normal policy\n",
                   std::strerror(errno));
    }
  }

  Proxy proxy(*target, delay_us * kNsPerUs, spin_us * kNsPerUs,
              static_cast<size_t>(max_buffer_mib) << 20);
  absl::StatusOr<int> port = proxy.Start(*listen_at);
  if (!port.ok()) return port.status();
  const std::string port_file = absl::GetFlag(FLAGS_port_file);
  if (!port_file.empty() && !WritePortFile(port_file, *port)) {
    return absl::InternalError(
        absl::StrCat("cannot write --port_file=", port_file));
  }
  std::printf("delay_proxy: port %d -> %s, one-way delay %lld us\n", *port,
              absl::GetFlag(FLAGS_target).c_str(),
              static_cast<long long>(delay_us));
  std::fflush(stdout);
  if (absl::Status status = proxy.Run(); !status.ok()) return status;
  const Stats& stats = proxy.stats();
  std::printf(
      "{\"connections\": %lld, \"chunks\": %lld, \"bytes\": %lld, "
      "\"late_us_p50\": %lld, \"late_us_p99\": %lld, \"late_us_max\": %lld, "
      "\"spin_us_at_exit\": %lld}\n",
      static_cast<long long>(stats.connections),
      static_cast<long long>(stats.chunks), static_cast<long long>(stats.bytes),
      static_cast<long long>(stats.LatePercentile(0.5)),
      static_cast<long long>(stats.LatePercentile(0.99)),
      static_cast<long long>(stats.LateMax()),
      static_cast<long long>(proxy.margin_ns() / kNsPerUs));
  std::fflush(stdout);
  return absl::OkStatus();
}

}  // namespace
}  // namespace mll::bench

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "A loopback TCP proxy that delays every byte by --delay_us each way.");
  absl::ParseCommandLine(argc, argv);
  const absl::Status status = mll::bench::Main();
  if (!status.ok()) {
    std::fprintf(stderr, "delay_proxy: %s\n",
                 std::string(status.message()).c_str());
    return 2;
  }
  return 0;
}
