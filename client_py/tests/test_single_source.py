"""The client's tables come from the wire contract's descriptors, not from copies: these tests
fail when the proto and what the client exposes drift apart."""

import multi_lunar_lander as mll
from multi_lunar_lander._stubs import pb


def test_outcome_names_follow_the_proto_enum():
    assert mll.OUTCOMES == (None, "landed", "crashed", "out_of_bounds", "truncated", "aborted")
    for value in pb.Outcome.DESCRIPTOR.values:
        name = mll.OUTCOMES[value.number]
        assert (name is None) == (value.number == pb.OUTCOME_UNSPECIFIED)
        if name is not None:
            assert value.name == "OUTCOME_" + name.upper()


def test_config_options_are_the_proto_fields_with_presence():
    fields = pb.EnvConfig.DESCRIPTOR.fields
    assert mll.CONFIG_OPTIONS == tuple(f.name for f in fields if f.name not in ("render_mode", "auto_reset"))
    # Every option can be left unset so that the server's default applies.
    for name in mll.CONFIG_OPTIONS:
        assert not pb.EnvConfig().HasField(name)

