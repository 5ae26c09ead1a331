"""The Franka backend's version check against a control unit that speaks the connect handshake only
(tests/franka_connect_peer.py): a robot whose server speaks another research-interface version is refused
before franky connects, with both versions named. franky itself is the reference for the reply's layout:
against the same peer it reports the same server version."""

from __future__ import annotations

from collections.abc import Iterator

import franky
import pytest

from drivers.arm.franka import FrankaArm, client_version
from drivers.errors import DriverError
from drivers.robots import get_robot_model
from tests.arm_backends import franka_config
from tests.franka_connect_peer import FrankaConnectPeer

OLD_SERVER_VERSION = 5  # a Panda on system 4.2 (libfranka 0.9)


@pytest.fixture
def old_robot() -> Iterator[FrankaConnectPeer]:
    peer = FrankaConnectPeer(OLD_SERVER_VERSION)
    yield peer
    peer.stop()


def test_a_robot_with_another_server_version_is_refused_naming_both(old_robot: FrankaConnectPeer) -> None:
    arm = FrankaArm(franka_config(old_robot.host), get_robot_model("panda"))
    with pytest.raises(DriverError) as refused:
        arm.connect()
    message = str(refused.value)
    assert f"server speaks research-interface version {OLD_SERVER_VERSION}" in message
    assert f"speaks {client_version()}" in message and "franky-control 2.0.0" in message
    assert not arm.is_connected
    assert old_robot.offered == [client_version()]  # refused at the handshake: franky never connected


def test_franky_reads_the_peers_reply_as_the_same_server_version(old_robot: FrankaConnectPeer) -> None:
    with pytest.raises(franky.IncompatibleVersionException,
                       match=rf"server version: {OLD_SERVER_VERSION}, library version: {client_version()}"):
        franky.Robot(old_robot.host, realtime_config=franky.RealtimeConfig.Ignore)
