"""The host link and board API against the pure-Python fake board (fast; the simavr tests are the truth)."""

import time

import pytest

from pivla.robot import protocol as P
from pivla.robot.fakeboard import FakeBoard
from pivla.robot.link import Board, BoardError, LinkConfig, LinkLost, SerialLink


@pytest.fixture
def fake():
    with FakeBoard() as fb:
        yield fb


@pytest.fixture
def board(fake):
    b = Board.open(fake.port, reply_timeout_s=0.1, retries=1)
    yield b
    b.close()


def test_ping_state_and_motion(board, fake):
    info = board.ping()
    assert info.protocol == P.PROTOCOL_VERSION and info.channels == P.N_CHANNELS
    st = board.set_targets([1600, 1400, 1500, 1500, 1500, 1500, 1800], 1500)
    assert st.targets_us[0] == 1600
    st = board.wait_idle(3.0)
    assert st.pulses_us[0] == 1600 and st.pulses_us[6] == 1800


def test_out_of_limit_targets_are_refused_without_moving(board, fake):
    with pytest.raises(BoardError, match="LIMIT"):
        board.set_targets([2100, 1500, 1500, 1500, 1500, 1500, 1500])
    assert max(fake.max_seen) <= 1500.5


def test_estop_latches_until_cleared(board):
    board.estop()
    with pytest.raises(BoardError, match="ESTOP"):
        board.set_targets([1500] * 7)
    assert not board.clear_estop().estop
    board.set_targets([1510] * 7)


def test_watchdog_holds_when_the_host_goes_quiet(board, fake):
    board.set_targets([1000] * 7, 100)  # slow: 5 s to get there
    time.sleep(0.9)
    held = fake.pulses()
    time.sleep(0.3)
    assert fake.pulses() == held and held[0] > 1000
    st = board.state()
    assert st.watchdog and not st.moving


def test_in_flight_bytes_are_bounded(fake):
    """Unanswered requests never exceed the budget (the Uno's RX buffer would drop bytes), and sending waits
    for replies rather than refusing: 20 requests fill the budget, then flow as replies come."""
    link = SerialLink(LinkConfig(fake.port, max_in_flight_bytes=50))
    seqs, unanswered = [], []
    for _ in range(20):  # 7-byte frames: at most 7 outstanding
        seqs.append(link.send(P.Cmd.GET_STATE))
        unanswered.append(link._in_flight_bytes())
    assert 43 < max(unanswered) <= 50
    replies = [link.wait(s, 1.0) for s in seqs]
    assert all(r is not None and r.cmd == P.Cmd.GET_STATE | P.REPLY_FLAG for r in replies)
    with pytest.raises(ValueError):
        SerialLink(LinkConfig(fake.port, max_in_flight_bytes=64))
    link.close()


def test_lost_link_raises(fake):
    b = Board.open(fake.port, reply_timeout_s=0.05, retries=1)
    fake.close()
    with pytest.raises(LinkLost):
        for _ in range(3):
            b.state()
    with pytest.raises(LinkLost):
        b.ping()  # stays lost
    b.close()


def test_open_fails_clearly_without_a_board(tmp_path):
    with pytest.raises(LinkLost, match="cannot open"):
        Board.open(str(tmp_path / "no-such-port"))
