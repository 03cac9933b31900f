// Records contacts as flags only, like Gymnasium's ContactDetector: nothing is
// created, destroyed or decided inside the physics step. Env reads the flags
// after b2World::Step and applies the rules.
#ifndef MLL_CORE_SRC_CONTACT_LISTENER_H_
#define MLL_CORE_SRC_CONTACT_LISTENER_H_

#include <array>
#include <vector>

#include "box2d/box2d.h"

namespace mll::core {
namespace internal {

struct LanderContacts {
  // The body touched anything (moon, another lander, a leg): damage.
  bool body_touched = false;
  // A leg touched something other than the moon: damage.
  bool leg_touched_other = false;
  // Each leg currently touches the moon (set on BeginContact, cleared on
  // EndContact with the moon), observation[6] and [7].
  std::array<bool, 2> leg_ground = {false, false};
};

class ContactListener : public b2ContactListener {
 public:
  // `contacts` is indexed by agent and must outlive the listener.
  explicit ContactListener(std::vector<LanderContacts>* contacts)
      : contacts_(contacts) {}

  void BeginContact(b2Contact* contact) override;
  void EndContact(b2Contact* contact) override;

 private:
  // Records that `self` (a fixture of some lander) began touching `other`.
  void Begin(b2Fixture* self, b2Fixture* other);
  void End(b2Fixture* self, b2Fixture* other);

  std::vector<LanderContacts>* contacts_;
};

}  // namespace internal
}  // namespace mll::core

#endif  // MLL_CORE_SRC_CONTACT_LISTENER_H_
