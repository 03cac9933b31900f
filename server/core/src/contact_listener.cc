#include "contact_listener.h"

#include "collision.h"

namespace mll::core {
namespace internal {

void ContactListener::BeginContact(b2Contact* contact) {
  Begin(contact->GetFixtureA(), contact->GetFixtureB());
  Begin(contact->GetFixtureB(), contact->GetFixtureA());
}

void ContactListener::EndContact(b2Contact* contact) {
  End(contact->GetFixtureA(), contact->GetFixtureB());
  End(contact->GetFixtureB(), contact->GetFixtureA());
}

void ContactListener::Begin(b2Fixture* self, b2Fixture* other) {
  const FixtureTag tag = TagOf(self);
  if (!IsLanderPart(tag.part)) return;
  LanderContacts& flags = (*contacts_)[tag.agent];
  if (tag.part == Part::kBody) {
    flags.body_touched = true;
    return;
  }
  const int leg = tag.part == Part::kLeg0 ? 0 : 1;
  if (TagOf(other).part == Part::kMoon) {
    flags.leg_ground[leg] = true;
  } else {
    flags.leg_touched_other = true;
  }
}

void ContactListener::End(b2Fixture* self, b2Fixture* other) {
  const FixtureTag tag = TagOf(self);
  if (tag.part != Part::kLeg0 && tag.part != Part::kLeg1) return;
  if (TagOf(other).part != Part::kMoon) return;
  (*contacts_)[tag.agent].leg_ground[tag.part == Part::kLeg0 ? 0 : 1] = false;
}

}  // namespace internal
}  // namespace mll::core
