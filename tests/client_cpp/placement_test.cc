// The placement arithmetic (client_cpp/src/placement.h) and name resolution
// (client_cpp/src/discovery.h) of the C++ client, alone: no server.
#include "placement.h"

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "discovery.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace mll::client::internal {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

ServerCapacity Hosting(int envs_hosted, int max_envs) {
  ServerCapacity server;
  server.envs_hosted = envs_hosted;
  server.max_envs = max_envs;
  return server;
}

TEST(PlanPlacementTest, EmptyServersShareEvenlyLowerIndexFirst) {
  const std::vector<ServerCapacity> servers(3, Hosting(0, 100));
  EXPECT_THAT(PlanPlacement(servers, 48), ElementsAre(16, 16, 16));
  EXPECT_THAT(PlanPlacement(servers, 5), ElementsAre(2, 2, 1));
  EXPECT_THAT(PlanPlacement(servers, 0), ElementsAre(0, 0, 0));
}

TEST(PlanPlacementTest, AHalfFullServerGetsNewEnvsOnlyOnceTheOthersCatchUp) {
  // Server 0 hosts 50 of another tenant's envs out of 100.
  const std::vector<ServerCapacity> servers = {
      Hosting(50, 100), Hosting(0, 100), Hosting(0, 100)};
  EXPECT_THAT(PlanPlacement(servers, 48), ElementsAre(0, 24, 24));
  // Water-filling: past 50 each, the three fill together.
  EXPECT_THAT(PlanPlacement(servers, 130), ElementsAre(10, 60, 60));
}

TEST(PlanPlacementTest, FillIsAgainstEachServersLimit) {
  // A server twice as large takes twice the share at the same fill.
  const std::vector<ServerCapacity> servers = {Hosting(0, 200),
                                               Hosting(0, 100)};
  EXPECT_THAT(PlanPlacement(servers, 30), ElementsAre(20, 10));
}

TEST(PlanPlacementTest, RoomRunsOutAndUnusableServersTakeNothing) {
  std::vector<ServerCapacity> servers = {Hosting(8, 10), Hosting(0, 10),
                                         Hosting(0, 10)};
  servers[2].usable = false;
  // 2 + 10 places left: the counts add up to less than asked.
  EXPECT_THAT(PlanPlacement(servers, 20), ElementsAre(2, 10, 0));
}

TEST(PlanPlacementTest, CpuUseBreaksTies) {
  std::vector<ServerCapacity> servers(3, Hosting(4, 100));
  servers[0].cpu_cores = 1.5;
  servers[0].cores_available = 2;
  servers[1].cpu_cores = 0.2;
  servers[1].cores_available = 2;
  servers[2].cpu_cores = 1.0;
  servers[2].cores_available = 2;
  // One env: the least busy server; three: one each.
  EXPECT_THAT(PlanPlacement(servers, 1), ElementsAre(0, 1, 0));
  EXPECT_THAT(PlanPlacement(servers, 2), ElementsAre(0, 1, 1));
  EXPECT_THAT(PlanPlacement(servers, 3), ElementsAre(1, 1, 1));
}

TEST(PlanPlacementTest, UnknownLimitsCountAsTheLargestKnownOne) {
  // A server that reports no load or limit (an older release) is an empty
  // server as large as the largest known.
  const std::vector<ServerCapacity> servers = {Hosting(0, 0), Hosting(10, 20)};
  EXPECT_THAT(PlanPlacement(servers, 10), ElementsAre(10, 0));
  EXPECT_THAT(PlanPlacement(servers, 30), ElementsAre(20, 10));
  // None known: even by count, without bound.
  const std::vector<ServerCapacity> unknown(2, Hosting(0, 0));
  EXPECT_THAT(PlanPlacement(unknown, 5000), ElementsAre(2500, 2500));
}

TEST(PlanEvenTest, AJoinedServerTakesItsShareFromTheFullest) {
  // 48 envs on two servers, a third joins.
  EXPECT_THAT(PlanEven({24, 24, 0}, {true, true, true}),
              ElementsAre(16, 16, 16));
  // Uneven totals: those holding most keep the remainder (fewest moves).
  EXPECT_THAT(PlanEven({25, 24, 0}, {true, true, true}),
              ElementsAre(17, 16, 16));
  EXPECT_THAT(PlanEven({3, 4, 0, 0}, {true, true, true, true}),
              ElementsAre(2, 2, 2, 1));
}

TEST(PlanEvenTest, IneligibleServersKeepTheirs) {
  // Server 0 left its name (still up): its envs stay, the rest even out.
  EXPECT_THAT(PlanEven({10, 20, 0}, {false, true, true}),
              ElementsAre(10, 10, 10));
  EXPECT_THAT(PlanEven({10, 20}, {false, false}), ElementsAre(10, 20));
}

TEST(AddressEntryTest, NamesLiteralsAndTargets) {
  absl::StatusOr<AddressEntry> name = ParseAddressEntry("mll.svc:50051");
  ASSERT_TRUE(name.ok()) << name.status();
  EXPECT_TRUE(name->is_name);
  EXPECT_EQ(name->host, "mll.svc");
  EXPECT_EQ(name->port, "50051");
  for (const char* literal :
       {"127.0.0.2:50051", "[::1]:50051", "unix:/tmp/mll.sock",
        "dns:///mll.svc:50051", "ipv4:127.0.0.1:5"}) {
    absl::StatusOr<AddressEntry> entry = ParseAddressEntry(literal);
    ASSERT_TRUE(entry.ok()) << literal << ": " << entry.status();
    EXPECT_FALSE(entry->is_name) << literal;
    absl::StatusOr<std::vector<std::string>> resolved = ResolveEntry(*entry);
    ASSERT_TRUE(resolved.ok()) << resolved.status();
    EXPECT_THAT(*resolved, ElementsAre(literal));
  }
  for (const char* bad :
       {"", "mll.svc", "mll.svc:0", "mll.svc:99999", "::1:50051"}) {
    EXPECT_EQ(ParseAddressEntry(bad).status().code(),
              absl::StatusCode::kInvalidArgument)
        << bad;
  }
}

TEST(ResolveTest, ANameIsEveryAddressItResolvesTo) {
  absl::StatusOr<AddressEntry> entry = ParseAddressEntry("localhost:50051");
  ASSERT_TRUE(entry.ok()) << entry.status();
  absl::StatusOr<std::vector<std::string>> resolved = ResolveEntry(*entry);
  ASSERT_TRUE(resolved.ok()) << resolved.status();
  // localhost is 127.0.0.1, and ::1 where the hosts file says so.
  EXPECT_THAT(*resolved, ::testing::Contains("127.0.0.1:50051"));
  for (const std::string& address : *resolved) {
    EXPECT_TRUE(address == "127.0.0.1:50051" || address == "[::1]:50051")
        << address;
  }
}

TEST(ResolveTest, ANameWithoutAddressesIsUnavailableNamingIt) {
  absl::StatusOr<AddressEntry> entry =
      ParseAddressEntry("no-such-host.invalid:50051");
  ASSERT_TRUE(entry.ok()) << entry.status();
  const absl::Status status = ResolveEntry(*entry).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(status.message(), HasSubstr("no-such-host.invalid:50051"));
  EXPECT_EQ(DescribeResolution(*entry, {}, status), status.message());
  EXPECT_EQ(DescribeResolution(*entry, {}, absl::OkStatus()),
            "no-such-host.invalid:50051 resolves to no address");
  EXPECT_EQ(DescribeResolution(*entry, {"127.0.0.2:50051", "127.0.0.3:50051"},
                               absl::OkStatus()),
            "no-such-host.invalid:50051 resolves to 127.0.0.2:50051, "
            "127.0.0.3:50051");
}

TEST(ResolveTest, EntriesMergeRepeatedAddressesAndRecordFailures) {
  std::vector<AddressEntry> entries;
  for (const char* text :
       {"127.0.0.1:7", "localhost:7", "no-such.invalid:7", "127.0.0.3:7"}) {
    entries.push_back(*ParseAddressEntry(text));
  }
  std::vector<absl::Status> failures;
  absl::StatusOr<std::vector<Endpoint>> endpoints =
      ResolveEntries(entries, &failures);
  ASSERT_TRUE(endpoints.ok());
  std::vector<std::string> addresses;
  for (const Endpoint& endpoint : *endpoints) {
    if (endpoint.address != "[::1]:7") addresses.push_back(endpoint.address);
  }
  EXPECT_THAT(addresses, ElementsAre("127.0.0.1:7", "127.0.0.3:7"));
  EXPECT_TRUE(failures[0].ok());
  EXPECT_EQ(failures[2].code(), absl::StatusCode::kUnavailable);
  // Without a failure list, the first failure is the answer.
  EXPECT_EQ(ResolveEntries(entries).status().code(),
            absl::StatusCode::kUnavailable);
}

TEST(ResolveTest, TlsChecksTheNameNotTheAddress) {
  ClientOptions options;
  options.use_tls = true;
  const AddressEntry name = *ParseAddressEntry("mll.svc:50051");
  const AddressEntry literal = *ParseAddressEntry("10.0.0.7:50051");
  EXPECT_EQ(EndpointOptions(name, options).tls_target_name_override, "mll.svc");
  EXPECT_EQ(EndpointOptions(literal, options).tls_target_name_override, "");
  options.tls_target_name_override = "other.name";
  EXPECT_EQ(EndpointOptions(name, options).tls_target_name_override,
            "other.name");
  options = ClientOptions();
  EXPECT_EQ(EndpointOptions(name, options).tls_target_name_override, "");
}

}  // namespace
}  // namespace mll::client::internal
