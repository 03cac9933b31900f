// The ideas that several layers share are defined once; these tests fail
// when a copy drifts from its source: outcome names (the proto's Outcome enum,
// the core's Outcome, the client's LanderOutcome).
#include <string>

#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/core/env.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll {
namespace {

TEST(SingleSourceTest, OutcomeNamesAgreeWithTheProto) {
  const google::protobuf::EnumDescriptor* outcomes = v1::Outcome_descriptor();
  ASSERT_EQ(outcomes->value_count(), 6);
  for (int i = 0; i < outcomes->value_count(); ++i) {
    const int code = outcomes->value(i)->number();
    SCOPED_TRACE(outcomes->value(i)->name());
    EXPECT_EQ(LanderOutcomeName(static_cast<LanderOutcome>(code)),
              OutcomeName(static_cast<Outcome>(code)));
  }
  EXPECT_EQ(LanderOutcomeName(LanderOutcome::kNone), "none");
  EXPECT_EQ(LanderOutcomeName(LanderOutcome::kOutOfBounds), "out_of_bounds");
  EXPECT_EQ(LanderOutcomeName(static_cast<LanderOutcome>(77)), "unknown");
}

}  // namespace
}  // namespace mll
