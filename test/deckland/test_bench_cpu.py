"""CPU cuts on the hot path: a throttled warning costs nothing until it is due (rclpy's own
throttle inspects the caller's source file on every call, throttled or not)."""

from deckland_common.checks import InputGuard
from deckland_common.ros_node import LOG_THROTTLE_S, GuardedNode


class FakeLogger:
    def __init__(self):
        self.lines = []

    def warn(self, text, **kw):
        assert not kw, 'no rclpy throttling: it inspects the stack on every call'
        self.lines.append(text)


class Guarded(GuardedNode):
    def __init__(self):
        self.logger = FakeLogger()
        self.attach_guard(InputGuard((), ()), 'publishing nothing')

    def get_logger(self):
        return self.logger


def test_a_rejection_storm_logs_one_line_per_reason_per_interval(monkeypatch):
    import deckland_common.ros_node as rn
    t = [100.0]
    monkeypatch.setattr(rn.time, 'monotonic', lambda: t[0])
    node = Guarded()
    for _ in range(1000):
        node._reject('stale_stamp', 'vehicle/imu')
    node._reject('bad_frame', 'vehicle/imu')
    node._log_withheld('stale')
    assert node.rejected == {'stale_stamp': 1000, 'bad_frame': 1}      # all counted
    assert node.logger.lines == ['rejected vehicle/imu: stale_stamp (1 so far)',
                                 'rejected vehicle/imu: bad_frame (1 so far)',
                                 'publishing nothing: stale']
    t[0] += LOG_THROTTLE_S
    node._reject('stale_stamp', 'vehicle/imu')
    assert node.logger.lines[-1] == 'rejected vehicle/imu: stale_stamp (1001 so far)'
