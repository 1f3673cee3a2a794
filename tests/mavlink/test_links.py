"""The router's vocabulary: refusal lines and which links share a station's ids."""

from __future__ import annotations

from antireplay.mavlink.endpoints import Transport, parse_endpoint
from antireplay.mavlink.links import FrameRefusal, Role, RouterLink, receivers, same_station


def _link(role: Role, key: bytes | None, *, fixed: bool = True) -> RouterLink:
    return RouterLink(Transport(parse_endpoint("udpin:127.0.0.1:14550"), fixed=fixed), role, key)


def test_a_ground_link_with_the_same_key_is_the_same_station() -> None:
    owner = _link(Role.GROUND, b"k" * 32)
    assert same_station(owner, owner)
    assert same_station(owner, _link(Role.GROUND, b"k" * 32))
    assert not same_station(owner, _link(Role.GROUND, b"o" * 32))
    assert not same_station(owner, _link(Role.TRUSTED, b"k" * 32))


def test_receivers_are_the_fixed_destination_or_the_authenticated_peers() -> None:
    assert list(receivers(_link(Role.VEHICLE, b"k" * 32))) == [None]
    learning = _link(Role.GROUND, b"k" * 32, fixed=False)
    assert list(receivers(learning)) == []
    learning.peers[("10.0.0.2", 14550)] = None
    assert list(receivers(learning)) == [("10.0.0.2", 14550)]


def test_a_summary_refusal_says_how_many_frames() -> None:
    one = FrameRefusal("inbound", "udpin:0.0.0.0:14550", "REPLAY", "seen", b"")
    assert str(one) == "refused inbound frame on udpin:0.0.0.0:14550: REPLAY: seen"
    many = FrameRefusal("inbound", "udpin:0.0.0.0:14550", "FENCED", "behind", b"", 4)
    assert str(many) == "refused 4 inbound frames on udpin:0.0.0.0:14550: FENCED: behind"
