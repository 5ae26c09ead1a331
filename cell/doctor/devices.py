"""Checks of the devices a cell file names: the sensor's serial port, the UR5e's controller (RTDE and the
dashboard server, its software version, remote control) and the Franka's research interface (FCI).

A robot's driver module is imported only by the check of that robot: :mod:`drivers.arm.franka` imports
franky, which a venv built with the ``ur5e`` extra alone does not have, and ``cell doctor`` failed there
before checking anything.
"""

from __future__ import annotations

import os
import socket
import stat
import struct
from importlib import metadata
from pathlib import Path

from cell.deploy import UDEV_RULE, install_command
from cell.doctor.findings import Finding
from drivers.errors import CellError
from drivers.file_access import group_name, user_name
from drivers.hosts import recv_exact

RTDE_PORT = 30004
RTDE_HEADER = struct.Struct(">HB")
"""An RTDE package's header: its size [bytes, header included] and type."""
RTDE_PROTOCOL_VERSION = ord("V")
RTDE_VERSION = 2
DASHBOARD_PORT = 29999
FRANKA_COMMAND_PORT = 1337
CONNECT_TIMEOUT_S = 2.0
UR_SOFTWARE_MAJOR = 5
"""A UR5e is an e-Series robot: PolyScope 5 (PolyScope X has no dashboard server of this kind)."""
UDEV_DEVICE = "/dev/vl53l8cx"
"""The bridge board's device under the shipped udev rule (``cell.deploy``)."""
GROUP_RW = stat.S_IRGRP | stat.S_IWGRP


def serial_port(port: str) -> Finding:
    """The sensor's port: a device that exists and that this user may open (else which group to join, or,
    for a device no group but root's may open, the shipped udev rule).
    A pyserial URL (``socket://``, ``loop://``) is not a device and is not checked here."""
    name = "serial port"
    if "://" in port:
        return Finding.ok(name, f"{port} is a URL, not a device: `cell sensor check` tries it")
    try:
        st = os.stat(port)
    except FileNotFoundError:
        return Finding.fail(name, f"{port} does not exist", "plug the bridge board in; with the udev rule "
                            f"of `cell deploy files` it appears as {UDEV_DEVICE} (`ls /dev/ttyACM*` lists "
                            "candidates)")
    if not stat.S_ISCHR(st.st_mode):
        return Finding.fail(name, f"{port} is not a character device",
                            "set sensor.port to the board's device")
    if not os.access(port, os.R_OK | os.W_OK):
        me, group = user_name(), group_name(st.st_gid)
        found = (f"{port} belongs to {user_name(st.st_uid)}:{group} with mode "
                 f"{stat.S_IMODE(st.st_mode):04o}, and user {me} may not open it")
        if st.st_gid == 0 or st.st_mode & GROUP_RW != GROUP_RW:
            # no group to join but root's, which would give the user the whole machine
            return Finding.fail(name, found, f"install the sensor's udev rule, which gives the board to "
                                f"group dialout as {UDEV_DEVICE}: cell deploy files DIR, then "
                                f"{install_command(UDEV_RULE, Path('DIR'))}; and sensor.port: {UDEV_DEVICE}")
        return Finding.fail(name, found, f"sudo usermod -aG {group} {me} and log in again (the service's "
                            "unit joins dialout)")
    try:
        fd = os.open(port, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError as exc:
        return Finding.fail(name, f"cannot open {port}: {exc.strerror}",
                            "close the program that holds it (`fuser -v` names it), or replug the board")
    os.close(fd)
    return Finding.ok(name, f"{port} opens")


def _connect(host: str, port: int) -> socket.socket | str:
    """A connected socket, or why there is none."""
    try:
        return socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
    except OSError as exc:
        return exc.strerror or str(exc) or type(exc).__name__


def _dashboard(sock: socket.socket, command: str) -> str:
    sock.sendall(command.encode() + b"\n")
    reply = b""
    while not reply.endswith(b"\n"):
        chunk = sock.recv(1024)
        if not chunk:
            break
        reply += chunk
    return reply.decode(errors="replace").strip()


def _rtde(host: str, unreachable: str) -> Finding:
    """RTDE's first exchange: the client asks for protocol version 2, the controller accepts it."""
    sock = _connect(host, RTDE_PORT)
    if isinstance(sock, str):
        return Finding.fail("robot RTDE", f"{host}:{RTDE_PORT} does not answer ({sock})", unreachable)
    try:
        with sock:
            sock.sendall(RTDE_HEADER.pack(RTDE_HEADER.size + 2, RTDE_PROTOCOL_VERSION) +
                         struct.pack(">H", RTDE_VERSION))
            size, kind = RTDE_HEADER.unpack(recv_exact(sock, RTDE_HEADER.size))
            payload = recv_exact(sock, size - RTDE_HEADER.size)
    except OSError as exc:
        return Finding.fail("robot RTDE", f"{host}:{RTDE_PORT} accepted a connection but did not speak RTDE "
                            f"({exc})", "is this the robot's address? (another machine may answer on it)")
    if kind != RTDE_PROTOCOL_VERSION or payload[:1] != b"\x01":
        return Finding.fail("robot RTDE", f"the controller refused RTDE protocol {RTDE_VERSION}",
                            "update the controller's software (PolyScope 5)")
    return Finding.ok("robot RTDE", f"{host}:{RTDE_PORT} speaks RTDE protocol {RTDE_VERSION}")


def ur_controller(host: str) -> list[Finding]:
    """RTDE and the dashboard answer; the controller's software version; remote control."""
    unreachable = (f"check the robot is on, the cable, and that this PC has an address in {host}'s "
                   f"subnet (ping {host})")
    found = [_rtde(host, unreachable)]
    dash = _connect(host, DASHBOARD_PORT)
    if isinstance(dash, str):
        found.append(Finding.fail("robot dashboard", f"{host}:{DASHBOARD_PORT} does not answer ({dash})",
                                  unreachable))
        return found
    try:
        with dash:
            dash.recv(1024)  # "Connected: Universal Robots Dashboard Server"
            version = _dashboard(dash, "PolyscopeVersion")
            remote = _dashboard(dash, "is in remote control")
    except OSError as exc:
        found.append(Finding.fail("robot dashboard", f"{host}:{DASHBOARD_PORT} broke off ({exc})",
                                  unreachable))
        return found
    numbers = version.split()[1] if version.startswith("URSoftware ") and len(version.split()) > 1 else ""
    if not numbers.split(".")[0].isdigit():
        found.append(Finding.fail("robot software", f"unexpected answer to PolyscopeVersion: {version!r}",
                                  "is this a UR e-Series controller? (PolyScope 5)"))
    elif int(numbers.split(".")[0]) != UR_SOFTWARE_MAJOR:
        found.append(Finding.fail("robot software", version,
                                  "a UR5e runs PolyScope 5: update the controller"))
    else:
        found.append(Finding.ok("robot software", version))
    if remote.strip().lower() != "true":
        found.append(Finding.warn("robot remote control", f"the pendant is not in Remote Control "
                                  f"({remote!r}): the cell cannot start its control script",
                                  "on the pendant: the Local/Remote switch at the top right, Remote Control"))
    else:
        found.append(Finding.ok("robot remote control", "on"))
    return found


def franka_controller(host: str) -> Finding:
    """The research interface (FCI) answers the connect handshake and accepts this client's version."""
    try:
        from drivers.arm.franka import client_version, server_version
    except ImportError as exc:
        return Finding.fail("robot FCI", f"the Franka driver does not load: {exc}",
                            "pip install 'cell[franka]'")
    try:
        accepted, version = server_version(host, CONNECT_TIMEOUT_S)
    except (CellError, metadata.PackageNotFoundError) as exc:
        return Finding.fail("robot FCI", f"cannot offer a client version: {exc}",
                            "pip install 'cell[franka]'")
    except OSError as exc:
        return Finding.fail("robot FCI", f"{host}:{FRANKA_COMMAND_PORT} does not answer ({exc})",
                            "in Desk: unlock the joints and activate FCI; check the cable to the control "
                            f"unit's LAN port (ping {host})")
    if not accepted:
        return Finding.fail("robot FCI", f"the robot speaks research-interface version {version}, this "
                            f"client {client_version()}", "install the franky-control that matches the "
                            "robot's system version (Desk: Settings > System)")
    return Finding.ok("robot FCI", f"research-interface version {version}")
