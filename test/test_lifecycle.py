"""valve_hardware as a managed (lifecycle) node: a lifecycle manager's client walks it through configure -> activate ->
a latched fault -> reset -> deactivate -> cleanup -> configure -> activate -> shutdown with the standard
``~/change_state`` and ``~/get_state`` services; at each state the voltage written to the DAQ is checked, and no
command is applied outside ``active``.

The node runs in this process on the real-time clock with the kit's fault-injecting backend around the simulated
valve, on a clock the test moves (each period is the node's own pacing tick, claimed before it is configured).
"""
import math
import os
import time
from itertools import count

import pytest
import rclpy
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter
from std_msgs.msg import Float64, String
from std_srvs.srv import Trigger

from piezo_valve_ros.backends import SimBackend
from piezo_valve_ros.backends import FaultInjectingBackend
from piezo_valve_ros.core.sim import ValveSimConfig
from piezo_valve_ros.nodes.hardware import ValveHardwareNode
from piezo_valve_ros.ros import COMMAND_QOS, SENSOR_QOS, STATE_QOS, make_executor

_ids = count()
PERIOD_S = 1e-3
SAFE_V = 5.0


class CountedDaq(FaultInjectingBackend):
    """The fault-injecting backend that also counts how often it was opened and closed."""

    def __init__(self, inner):
        super().__init__(inner)
        self.opened = self.closed = 0

    def open(self) -> None:
        self.opened += 1
        super().open()

    def close(self) -> None:
        self.closed += 1
        super().close()


@pytest.fixture(scope="module")
def ros_context():
    rclpy.init()
    yield
    rclpy.try_shutdown()


class Manager:
    """A lifecycle manager's view of the node: its services, a command publisher, what it publishes."""

    def __init__(self, autostart: bool):
        ns = f"/life{os.getpid()}_{next(_ids)}"
        self.now = 100.0
        self.daq = CountedDaq(SimBackend(ValveSimConfig(dt=1e-4, seed=5), clock=lambda: self.now))
        self.hw = ValveHardwareNode(backend=self.daq, namespace=ns, parameter_overrides=[
            Parameter("autostart", value=autostart), Parameter("command_timeout_s", value=0.5),
            Parameter("diagnostics_period_s", value=0.0)])
        self.pacing = self.hw.claim_pacing()
        self.probe = rclpy.create_node("lifecycle_manager", namespace=ns)
        self.states, self.positions = [], []
        self.probe.create_subscription(String, "hardware_state", lambda m: self.states.append(m.data), STATE_QOS)
        self.probe.create_subscription(Float64, "spool_position", lambda m: self.positions.append(m.data), SENSOR_QOS)
        self.commands = self.probe.create_publisher(Float64, "voltage_command", COMMAND_QOS)
        self.change_client = self.probe.create_client(ChangeState, f"{ns}/valve_hardware/change_state")
        self.get_client = self.probe.create_client(GetState, f"{ns}/valve_hardware/get_state")
        self.reset_client = self.probe.create_client(Trigger, f"{ns}/valve_hardware/reset")
        self.executor = make_executor()
        for node in (self.hw, self.probe):
            self.executor.add_node(node)
        deadline = time.monotonic() + 5.0
        while self.commands.get_subscription_count() < 1 and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def call(self, client, request):
        assert client.wait_for_service(timeout_sec=5.0), client.srv_name
        future = client.call_async(request)
        deadline = time.monotonic() + 5.0
        while not future.done() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)
        assert future.done(), client.srv_name
        return future.result()

    def state(self) -> str:
        return self.call(self.get_client, GetState.Request()).current_state.label

    def change(self, label: str) -> bool:
        return self.call(self.change_client, ChangeState.Request(transition=Transition(label=label))).success

    def reset(self):
        return self.call(self.reset_client, Trigger.Request())

    def run(self, periods: int, command=None) -> None:
        """``periods`` control periods, each sending ``command(k)`` [V] first (None: none) and waiting until the node
        has written it, refused it or latched a fault."""
        for k in range(periods):
            if command is not None:
                seen = self._seen()
                self.commands.publish(Float64(data=float(command(k))))
                deadline = time.monotonic() + 1.0
                while self._seen() == seen and time.monotonic() < deadline:
                    self.executor.spin_once(timeout_sec=0.005)
                assert self._seen() != seen, "the command was neither written nor refused"
            self.now += PERIOD_S
            self.pacing.tick()

    def _seen(self):
        return (len(self.daq.writes), self.hw.refused_in_fault, self.hw.refused_inactive, self.hw.fault)

    def spin(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.01)

    def close(self):
        for node in (self.hw, self.probe):
            self.executor.remove_node(node)
        self.hw.shutdown_safely()
        self.hw.destroy_node()
        self.probe.destroy_node()
        self.executor.shutdown()


@pytest.fixture
def manager(ros_context):
    made = Manager(autostart=False)
    yield made
    made.close()


def sine(k):
    return 5.0 + 3.0 * math.sin(2 * math.pi * k / 200.0)


def test_the_hardware_drives_the_valve_only_while_active(manager):
    m = manager
    # unconfigured: the backend not even opened, nothing written; a command is refused and said
    assert m.state() == "unconfigured" and m.daq.opened == 0 and m.daq.writes == []
    m.run(3, lambda k: 7.0)
    assert m.daq.writes == [] and m.hw.refused_inactive == 3 and m.hw.periods == 0
    # configure: opened at the safe voltage, nothing driven, nothing published as a position
    assert m.change("configure") and m.state() == "inactive"
    assert m.daq.opened == 1 and m.daq.writes == [SAFE_V]
    m.run(20, lambda k: 7.0)
    assert m.daq.writes == [SAFE_V] and m.hw.refused_inactive == 23 and m.hw.periods == 0
    level, message = m.hw.diagnostics.publish().status[0].level, m.hw.diagnostics.publish().status[0].message
    assert level == b"\x01" and message.startswith("inactive (lifecycle)"), message
    # activate: commands applied, positions published
    assert m.change("activate") and m.state() == "active"
    m.run(100, sine)
    assert m.daq.writes[-1] == pytest.approx(sine(99)) and m.hw.periods == 100
    m.spin(0.2)
    assert m.positions and m.states[-1] == "ok", m.states
    # a latched fault leaves active: the safe voltage, commands refused
    m.daq.inject("nan")
    m.run(1, sine)
    assert m.hw.fault is not None and m.hw.fault.kind == "non_finite_sample"
    assert m.state() == "inactive" and m.daq.writes[-1] == SAFE_V
    before = len(m.daq.writes)
    m.run(30, lambda k: 7.0)
    assert len(m.daq.writes) == before and m.hw.refused_in_fault >= 30
    m.spin(0.2)
    assert m.states[-1].startswith("fault: non_finite_sample"), m.states
    # the cause gone, ~/reset returns it to active
    m.daq.inject(None)
    m.run(3)
    assert m.reset().success and m.state() == "active" and m.hw.fault is None
    m.run(50, lambda k: sine(k + 7))
    assert m.daq.writes[-1] == pytest.approx(sine(56))
    m.spin(0.2)
    assert m.states[-1] == "ok", m.states
    # deactivate: the safe voltage, commands refused again
    assert m.change("deactivate") and m.state() == "inactive" and m.daq.writes[-1] == SAFE_V
    periods, refused = m.hw.periods, m.hw.refused_inactive
    m.run(10, lambda k: 7.0)
    assert m.daq.writes[-1] == SAFE_V and 7.0 not in m.daq.writes[-10:] and m.hw.refused_inactive == refused + 10
    assert m.hw.periods == periods
    # cleanup: the backend closed at the safe voltage; configure opens it again, activate drives again
    assert m.change("cleanup") and m.state() == "unconfigured"
    assert m.daq.closed == 1 and m.daq.writes[-1] == SAFE_V
    m.run(5, lambda k: 7.0)
    assert m.daq.writes[-1] == SAFE_V
    assert m.change("configure") and m.change("activate") and m.state() == "active" and m.daq.opened == 2
    m.run(10, lambda k: 6.0)
    assert m.daq.writes[-1] == 6.0
    # shutdown from active: the safe voltage and the backend closed; a transition that is not there is refused
    assert not m.change("activate")
    assert m.change("shutdown") and m.state() == "finalized"
    assert m.daq.writes[-1] == SAFE_V and m.daq.closed == 2
    m.run(3, lambda k: 7.0)
    assert m.daq.writes[-1] == SAFE_V


def test_started_on_its_own_it_comes_up_active(ros_context):
    """autostart (the default): configured and active at once, as every documented command expects."""
    m = Manager(autostart=True)
    try:
        assert m.state() == "active" and m.daq.opened == 1 and m.daq.writes == [SAFE_V]
        m.run(20, lambda k: 6.5)
        assert m.daq.writes[-1] == 6.5
    finally:
        m.close()
