"""
Shutdown vents: the pressure_bridge process against a virtual Due, stopped by a signal.

SIGINT and SIGTERM: the node takes the lifecycle shutdown transition, which vents, then
closes (exit 0). SIGKILL leaves no chance to vent, so the firmware's own watchdog must do
it: the emulator's log shows which one did. The test configures and activates the node over
its lifecycle services, as the physical rig's launch file does.
"""

import signal
import subprocess
import sys
import time

import pytest

from softshape_ros.config import load_rig_config
from softshape_ros.hardware.virtual_due import VirtualDue
from waits import call, round_trip

pytestmark = pytest.mark.ros
CFG = load_rig_config()


def out_of(proc):
    """Return what a failed bridge process printed (it is killed first)."""
    proc.kill()
    return proc.communicate()[0]


@pytest.mark.parametrize('sig, reason', [(signal.SIGINT, 'vent'), (signal.SIGTERM, 'vent'),
                                         (signal.SIGKILL, 'watchdog')])
def test_stopping_the_node_vents(sig, reason, ros, tmp_path):
    from lifecycle_msgs.msg import Transition
    from lifecycle_msgs.srv import ChangeState, GetState
    from std_msgs.msg import Float64MultiArray

    from softshape_ros.nodes.common import RELIABLE_QOS
    with VirtualDue(CFG.max_pressures_pa, link=tmp_path / 'ttyDUE', seed=1) as vd:
        proc = subprocess.Popen(
            [sys.executable, '-c', 'from softshape_ros.nodes.pressure_bridge import main; main()',
             '--ros-args', '-p', f'port:={vd.path}', '-p', 'firmware_watchdog_s:=0.3'],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            node = ros.node('shutdown_client')
            pub = node.create_publisher(Float64MultiArray, CFG.topics.pressure_command,
                                        RELIABLE_QOS)
            ros.wait_for(lambda: pub.get_subscription_count() > 0, 60, what='bridge in graph')
            change = node.create_client(ChangeState, '/pressure_bridge/change_state')
            get_state = node.create_client(GetState, '/pressure_bridge/get_state')
            assert change.wait_for_service(timeout_sec=30)
            for tid, goal in ((Transition.TRANSITION_CONFIGURE, 'inactive'),
                              (Transition.TRANSITION_ACTIVATE, 'active')):
                req = ChangeState.Request()
                req.transition.id = tid
                try:
                    answer = call(ros, change, req, f'transition {tid}')
                    # A resent request after a lost answer is refused (the state has moved
                    # on): then the state must be the transition's goal.
                    state = answer.success or call(ros, get_state, GetState.Request(),
                                                   'the state').current_state.label
                except pytest.fail.Exception as e:     # unanswered: say what the bridge said
                    pytest.fail(f'{e}\nbridge (alive: {proc.poll() is None}) printed:\n'
                                f'{out_of(proc)}\nDue log: {vd.applied()[-3:]}')
                assert state in (True, goal), out_of(proc)
            # Configured (the handshake is done by then) and active: a command is applied. Our
            # publisher's match may be with a bridge process that is gone (still in the graph):
            # the command is repeated until the Due applies it.
            cmd = [40000.0, 0, 20000, 0, 10000, 5000]
            round_trip(ros, lambda k: pub.publish(Float64MultiArray(data=cmd)),
                       lambda: vd.applied()[-1].setpoints_pa == tuple(int(x) for x in cmd),
                       'the command applied at the Due', timeout=20)
            assert vd.applied()[-1].reason == 'command', vd.applied()
            t_signal = time.monotonic()
            proc.send_signal(sig)
            out, _ = proc.communicate(timeout=30)
            if sig != signal.SIGKILL:
                assert proc.returncode == 0, out
                assert 'shutdown: vented' in out
            ros.wait_for(lambda: vd.applied()[-1].t > t_signal, 3, what='a vent after the signal')
            last = vd.applied()[-1]
            assert last.setpoints_pa == (0,) * 6 and last.reason == reason, vd.applied()[-3:]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
