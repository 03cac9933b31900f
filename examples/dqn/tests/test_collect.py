"""The collector's overlap: the environment call runs on a helper thread
while the trainer's work runs on the calling thread."""

import threading

from mll_dqn.collect import Timers, _Collector
from mll_dqn.config import preset

import numpy as np


class _FakeEnv:
    def close(self):
        pass


def test_during_runs_while_the_call_is_in_flight():
    """The call can only return True if `during` (which sets the event) runs
    while the call waits for it: sequential execution would time out."""
    timers = Timers()
    collector = _Collector(None, preset("quick"), np.random.default_rng(0),
                           timers, num_envs=1)
    collector.env = _FakeEnv()
    ran = threading.Event()
    order = []

    def call(x):
        order.append("call")
        return ran.wait(timeout=5.0) and x

    def during():
        order.append("during")
        ran.set()

    assert collector._timed(call, 7, during=during) == 7
    assert sorted(order) == ["call", "during"]
    assert timers.seconds["env_call"] > 0 and "env" in timers.seconds
    # Without `during` the call runs here and is timed as "env" only.
    before = timers.seconds["env_call"]
    ran.clear()
    assert collector._timed(lambda: threading.current_thread().name) == (
        threading.current_thread().name)
    assert timers.seconds["env_call"] == before
    collector.close()
