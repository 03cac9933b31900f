// The ideas that several layers share are defined once; these tests fail
// when a copy drifts from its source: the environment options (the core's
// MLL_ENV_OPTIONS, the proto's EnvConfig, the C++ client's RemoteEnvConfig
// and its encoding) and the outcome names (the proto's Outcome enum, the
// core's Outcome, the client's LanderOutcome). The Python client reads both
// from the proto's descriptors (client_py/tests/test_single_source.py).
#include <string>
#include <utility>
#include <vector>

#include "core_bridge.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"
#include "mll/v1/multi_lunar_lander.pb.h"
#include "wire.h"

namespace mll::client {
namespace {

using google::protobuf::FieldDescriptor;

// The proto's options: EnvConfig's fields with presence (an unset one takes
// the server's default), in field order.
std::vector<const FieldDescriptor*> ProtoOptions() {
  std::vector<const FieldDescriptor*> fields;
  const google::protobuf::Descriptor* config = v1::EnvConfig::descriptor();
  for (int i = 0; i < config->field_count(); ++i) {
    if (config->field(i)->has_presence()) fields.push_back(config->field(i));
  }
  return fields;
}

template <typename T>
constexpr FieldDescriptor::CppType CppTypeOf();
template <>
constexpr FieldDescriptor::CppType CppTypeOf<int>() {
  return FieldDescriptor::CPPTYPE_INT32;
}
template <>
constexpr FieldDescriptor::CppType CppTypeOf<bool>() {
  return FieldDescriptor::CPPTYPE_BOOL;
}
template <>
constexpr FieldDescriptor::CppType CppTypeOf<double>() {
  return FieldDescriptor::CPPTYPE_DOUBLE;
}

TEST(SingleSourceTest, CoreOptionsAreTheProtoOptionsInOrder) {
  std::vector<std::pair<std::string, FieldDescriptor::CppType>> core;
#define MLL_LIST_OPTION(type, name, default_value, range, help) \
  core.emplace_back(#name, CppTypeOf<type>());
  MLL_ENV_OPTIONS(MLL_LIST_OPTION)
#undef MLL_LIST_OPTION
  std::vector<std::pair<std::string, FieldDescriptor::CppType>> proto;
  for (const FieldDescriptor* field : ProtoOptions()) {
    proto.emplace_back(field->name(), field->cpp_type());
  }
  EXPECT_EQ(core, proto);
}

// RemoteConfigFrom is expanded from the core's list (it does not compile
// when the client lacks an option); the client's encoding must then carry
// every proto option with the core's value.
TEST(SingleSourceTest, TheClientEncodesEveryOption) {
  const core::EnvConfig defaults;
  v1::EnvConfig proto;
  internal::EncodeConfig(RemoteConfigFrom(defaults), &proto);
  for (const FieldDescriptor* field : ProtoOptions()) {
    EXPECT_TRUE(proto.GetReflection()->HasField(proto, field))
        << field->name() << " is not encoded by the C++ client";
  }
#define MLL_CHECK_ENCODED(type, name, default_value, range, help) \
  EXPECT_EQ(proto.name(), defaults.name) << #name;
  MLL_ENV_OPTIONS(MLL_CHECK_ENCODED)
#undef MLL_CHECK_ENCODED
  const RemoteEnvConfig decoded = internal::DecodeConfig(proto);
#define MLL_CHECK_DECODED(type, name, default_value, range, help) \
  EXPECT_EQ(decoded.name, defaults.name) << #name;
  MLL_ENV_OPTIONS(MLL_CHECK_DECODED)
#undef MLL_CHECK_DECODED
}

// Ranges are worded in errors as the option help words them.
TEST(SingleSourceTest, OptionRangesAreWordedAsTheyAreChecked) {
  EXPECT_EQ(core::OptionRange::Integers(1, 32).Describe(), "1..32");
  EXPECT_EQ(core::OptionRange::AtLeast(1).Describe(), ">= 1");
  EXPECT_EQ(core::OptionRange::Closed(0, 20).Describe(), "[0, 20]");
  EXPECT_EQ(core::OptionRange::Open(-12, 0).Describe(), "(-12, 0), exclusive");
  EXPECT_FALSE(core::OptionRange::Open(-12, 0).Contains(0.0));
  EXPECT_FALSE(core::OptionRange::Closed(0, 2).Contains(2.5));
  EXPECT_TRUE(core::OptionRange::Closed(0, 2).Contains(2.0));
}

TEST(SingleSourceTest, OutcomeNamesAgreeWithTheProto) {
  const google::protobuf::EnumDescriptor* outcomes = v1::Outcome_descriptor();
  ASSERT_EQ(outcomes->value_count(), 6);
  for (int i = 0; i < outcomes->value_count(); ++i) {
    const int code = outcomes->value(i)->number();
    SCOPED_TRACE(outcomes->value(i)->name());
    EXPECT_EQ(LanderOutcomeName(static_cast<LanderOutcome>(code)),
              OutcomeName(static_cast<core::Outcome>(code)));
  }
  EXPECT_EQ(LanderOutcomeName(LanderOutcome::kNone), "none");
  EXPECT_EQ(LanderOutcomeName(LanderOutcome::kOutOfBounds), "out_of_bounds");
  EXPECT_EQ(LanderOutcomeName(static_cast<LanderOutcome>(77)), "unknown");
}

}  // namespace
}  // namespace mll::client
