"""The Feetech STS bus through the vendor SDK against the simulated bus: real bytes on a pty, each fault named."""

import time

import pytest

from pivla.robot import feetech as F
from pivla.robot.simbus import SimBus, SimBusConfig

NAMES = {1: "shoulder_pan", 2: "shoulder_lift", 3: "elbow_flex", 4: "wrist_flex", 5: "wrist_roll", 6: "gripper"}
IDS = list(NAMES)


@pytest.fixture
def sim():
    with SimBus(SimBusConfig(speed_ticks_s=1000.0)) as s:
        yield s


@pytest.fixture
def bus(sim):
    with F.FeetechBus(F.BusConfig(sim.port, reply_timeout_ms=50.0), NAMES) as b:
        yield b


def requests(sim: SimBus, instr: int) -> list[F.Packet]:
    """The packets of one instruction the simulated bus received."""
    return [p for p in F.PacketReader().feed(bytes(sim.received)) if p.code == instr]


def test_packets_and_checksum():
    assert F.encode_packet(1, F.Instr.PING) == bytes.fromhex("ff ff 01 02 01 fb")  # ~(1 + 2 + 1) & 0xFF
    read = F.encode_packet(3, F.Instr.READ, bytes([56, 2]))
    assert read == bytes([0xFF, 0xFF, 3, 4, 2, 56, 2, ~(3 + 4 + 2 + 56 + 2) & 0xFF])
    reader = F.PacketReader()
    bad = read[:-1] + bytes([read[-1] ^ 1])
    out = reader.feed(b"\x13\x37" + read + bad + read[:5])
    assert [(p.servo_id, p.checksum_ok, p.garbage_before) for p in out] == [(3, True, 2), (3, False, 0)]
    assert bytes(reader.garbage) == b"\x13\x37" and reader.pending == read[:5]
    assert reader.feed(read[5:])[0].raw == read


def test_sign_magnitude_registers():
    assert F.HOMING_OFFSET.encode(-5) == 5 | 1 << 11
    assert F.HOMING_OFFSET.decode(F.HOMING_OFFSET.encode(-1234)) == -1234
    assert F.GOAL_POSITION.encode(4095) == 4095 and F.PRESENT_SPEED.decode(1 << 15 | 7) == -7


def test_ping_read_write_round_trips(bus, sim):
    assert [bus.ping(sid) for sid in IDS] == [F.STS3215_MODEL] * 6
    bus.write(2, F.ACCELERATION, 50)
    assert bus.read(2, F.ACCELERATION) == 50 and sim.register(2, F.ACCELERATION) == 50
    assert bus.read(3, F.PRESENT_POSITION) == 2048
    bus.write(3, F.HOMING_OFFSET, -100)  # the servo subtracts its offset from the shaft angle
    assert bus.read(3, F.HOMING_OFFSET) == -100 and bus.read(3, F.PRESENT_POSITION) == 2148
    assert bus.read(5, F.MODEL_NUMBER) == F.STS3215_MODEL


def test_sync_read_and_write_are_one_packet_each_and_servos_move_at_bounded_speed(bus, sim):
    assert bus.sync_read(F.PRESENT_POSITION, IDS) == dict.fromkeys(IDS, 2048)
    assert [p.params for p in requests(sim, F.Instr.SYNC_READ)] == [bytes([56, 2, *IDS])]
    goals = {sid: 2048 + 100 * sid for sid in IDS}
    bus.sync_write(F.GOAL_POSITION, goals)
    time.sleep(0.2)
    assert bus.sync_read(F.PRESENT_POSITION, IDS) == dict.fromkeys(IDS, 2048)  # torque off: nothing moves
    bus.torque(IDS, True)
    t0 = time.monotonic()
    time.sleep(0.15)
    now = bus.sync_read(F.PRESENT_POSITION, IDS)
    elapsed = time.monotonic() - t0
    assert now[1] == 2148 and 2048 < now[6] < 2048 + 1000 * elapsed + 5  # 1000 ticks/s: servo 6 still on its way
    deadline = time.monotonic() + 3.0
    while bus.sync_read(F.PRESENT_POSITION, IDS) != goals:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    writes = requests(sim, F.Instr.SYNC_WRITE)
    assert len(writes) == 2 and writes[0].params[:2] == bytes([42, 2])
    assert [(sid, goal) for sid, goal in sim.goal_writes] == list(goals.items())


def test_servo_clamps_goals_to_its_angle_limits(bus, sim):
    bus.write(1, F.MAX_ANGLE_LIMIT, 2500)
    bus.sync_write(F.GOAL_POSITION, {1: 3000})
    assert bus.read(1, F.GOAL_POSITION) == 2500


@pytest.mark.parametrize("fault, kind, words", [
    ("mute", F.NoReply, "servo 3 (elbow_flex) did not answer SYNC_READ"),
    ("corrupt", F.ChecksumError, "servo 3 (elbow_flex): reply to SYNC_READ present_position failed its checksum"),
    ("garbage", F.BusGarbage, "servo 1 (shoulder_pan): 5 bytes of garbage on the bus"),
    ("error_bits", F.ServoFault, "servo 3 (elbow_flex) reports a fault in SYNC_READ present_position: overheat"),
])
def test_each_fault_is_named_and_the_bus_recovers(bus, sim, fault, kind, words):
    if fault == "garbage":
        sim.inject_garbage(b"\x00\x13\x37\xaa\x55")
    elif fault == "error_bits":
        sim.error_bits(3, 4)
    else:
        getattr(sim, fault)(3)
    with pytest.raises(kind, match=words.replace("(", r"\(").replace(")", r"\)")) as info:
        bus.sync_read(F.PRESENT_POSITION, IDS)
    assert info.value.servo_id == (1 if fault == "garbage" else 3)
    if fault in ("mute", "corrupt"):
        assert info.value.partial == {1: 2048, 2: 2048}  # the servos that answered before it
    sim.mute(3, False)
    sim.corrupt(3, False)
    sim.error_bits(3, 0)
    sim.set_position(4, 2222)
    for _ in range(3):  # no late reply of the failed transaction is taken for a fresh one
        assert bus.sync_read(F.PRESENT_POSITION, IDS) == {**dict.fromkeys(IDS, 2048), 4: 2222}


def test_single_register_faults_are_named(bus, sim):
    sim.mute(5)
    with pytest.raises(F.NoReply, match=r"servo 5 \(wrist_roll\) did not answer PING"):
        bus.ping(5)
    sim.mute(5, False)
    sim.corrupt(2)
    with pytest.raises(F.ChecksumError, match=r"servo 2 \(shoulder_lift\): reply to READ present_position"):
        bus.read(2, F.PRESENT_POSITION)


def test_retries_ride_over_a_burst_of_noise(sim):
    with F.FeetechBus(F.BusConfig(sim.port, reply_timeout_ms=50.0, retries=1), NAMES) as bus:
        sim.inject_garbage()
        assert bus.sync_read(F.PRESENT_POSITION, IDS) == dict.fromkeys(IDS, 2048)


def test_a_port_that_goes_away_or_never_was(bus, sim):
    with pytest.raises(F.PortError, match="cannot open serial port /dev/no-such-port"):
        F.FeetechBus(F.BusConfig("/dev/no-such-port"))
    sim.unplug()
    with pytest.raises(F.PortError, match="failed"):
        bus.sync_read(F.PRESENT_POSITION, IDS)
