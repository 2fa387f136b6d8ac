"""Framing and payload packing of the serial protocol (pure functions, no I/O)."""

import random

import pytest

from pivla.robot import protocol as P


def test_crc16_matches_ccitt_false_check_value():
    assert P.crc16(b"123456789") == 0x29B1


def test_encode_decode_round_trip_through_garbage():
    frames = [P.encode_frame(i, P.Cmd.SET_TARGETS, P.pack_targets([1000 + i] * 7, 500)) for i in range(5)]
    stream = b"\x00\xa5\xff" + frames[0] + b"\xa5" + frames[1] + b"junk" + b"".join(frames[2:])
    dec = P.FrameDecoder()
    got = []
    for i in range(0, len(stream), 3):  # byte-split arbitrarily
        got += dec.feed(stream[i : i + 3])
    assert [f.seq for f in got] == [0, 1, 2, 3, 4]
    assert P.unpack_targets(got[3].payload) == (500, (1003,) * 7)


def test_corrupt_frames_are_dropped_and_counted():
    good = P.encode_frame(7, P.Cmd.PING)
    bad = bytearray(P.encode_frame(8, P.Cmd.HOME, b"\x00\x00"))
    bad[5] ^= 0x01
    dec = P.FrameDecoder()
    got = dec.feed(bytes(bad) + good)
    assert [f.seq for f in got] == [7]
    assert dec.errors == 1


def test_oversized_payload_refused():
    with pytest.raises(P.ProtocolError):
        P.encode_frame(0, P.Cmd.PING, bytes(P.MAX_PAYLOAD + 1))


def test_state_and_limits_round_trip():
    st = P.BoardState(P.StateFlag.ESTOP | P.StateFlag.MOVING, (1100,) * 7, (1200,) * 7, 123456, 3)
    assert P.unpack_state(P.pack_state(st)) == st
    lim = P.ChannelLimits(3, 900, 2100, 1500)
    assert P.unpack_limits(P.pack_limits(lim)) == lim
    with pytest.raises(P.ProtocolError):
        P.unpack_state(b"\x00" * 5)


def test_decoder_survives_random_bytes():
    rng = random.Random(0)
    dec = P.FrameDecoder()
    for _ in range(200):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 80)))
        for f in dec.feed(data):
            assert len(f.payload) <= P.MAX_PAYLOAD
    assert dec.pending() < 2 * P.MAX_FRAME
