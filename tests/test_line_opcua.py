"""The packing line over OPC UA, as a PLC drives it: a real ``cell serve`` (``tests.service_process``) whose
cell file has ``line.opcua``, and an asyncua client as the PLC.

One cell (sign-and-encrypt, the server's generated certificate trusted by the PLC) serves most tests: five
parts through the PackTags handshake and OPC 30050's methods, the unit's OPC 30050 types and members
browsed and followed through a Start, Stop during Execute, Start refused in Execute, the PLC
disconnecting mid-scan, anonymous and unknown users refused, writes of the wrong type or too long
refused, the unit mode. A second cell (security ``none`` on loopback) has a protective stop
injected into every scan: Aborted with the stop reason, then Clear and Reset. Last, ``cell serve``
refuses an OPC UA port in use or a host that is not this machine's, in one line.

The cells scan with the raster planner (a part in about a second of wall time); every test brings the
line to Idle itself, so that they do not depend on their order.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import subprocess
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml
from asyncua import Client, Node, ua
from asyncua.crypto import cert_gen
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.x509.oid import ExtendedKeyUsageOID
from fastapi.testclient import TestClient

from cell.api.app import create_app
from cell.line.opcua import LineOPCUA
from cell.line.opcua_security import CERT_FILE, KEY_FILE, ensure_certificate
from cell.service.keys import create_key
from cell.service.startup import ServiceSettings
from cell.service.store import open_data_store, open_store, sqlite_url
from tests.conftest import UR5E
from tests.service_process import CELL, REPO, ServedCell, free_port

NAMESPACE = "urn:cell:packml"
PACKML = "http://opcfoundation.org/UA/PackML/"
PLC_URI = "urn:test:plc"
STOPPED, IDLE, EXECUTE, ABORTED, COMPLETE = 2, 4, 6, 9, 17
RESET, START, STOP, CLEAR = 1, 2, 3, 9
ENDS = (STOPPED, ABORTED, COMPLETE)
EXECUTE_STATE = "BaseStateMachine/MachineState/ExecuteState"
CELL_METHODS = {"SetPartId"}
PARTS = ("horizontal_box@0.01,-0.02,20", "cube", "vertical_box@-0.02,0.01,-35", "pyramid@0.0,0.02,90",
         "horizontal_box@-0.015,0.0,-60")


@dataclass(frozen=True)
class Served:
    """A served cell with OPC UA: ``url`` its endpoint; ``client_cert``/``client_key`` the PLC's own
    certificate (None: security ``none``)."""

    cell: ServedCell
    url: str
    client_cert: Path | None = None
    client_key: Path | None = None

    @property
    def server_cert(self) -> Path:
        return self.cell.data_dir / "opcua" / CERT_FILE

    def rest(self, path: str) -> Any:
        with self.cell.client("viewer") as client:
            return client.get(path).json()


def _serve(tmp: Path, security: str,
           edit: Callable[[dict[str, Any]], None] | None = None) -> tuple[ServedCell, str]:
    url = f"opc.tcp://127.0.0.1:{free_port()}/cell"
    data = yaml.safe_load(UR5E.read_text())
    data["scan"]["planner"] = "raster"
    data["line"] = {"opcua": {"endpoint": url, "security": security}}
    if edit is not None:
        edit(data)
    config = tmp / "cell.yaml"
    config.write_text(yaml.safe_dump(data, sort_keys=False))
    return ServedCell(config, tmp / "data"), url


@pytest.fixture(scope="module")
def encrypted(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    tmp = tmp_path_factory.mktemp("encrypted")
    cell, url = _serve(tmp, "sign-and-encrypt")
    cert, key = tmp / "plc-cert.der", tmp / "plc-key.pem"
    use, subject = [ExtendedKeyUsageOID.CLIENT_AUTH], {"organizationName": "test"}
    asyncio.run(cert_gen.setup_self_signed_certificate(key, cert, PLC_URI, "plc", use, subject))
    try:
        yield Served(cell, url, cert, key)
    finally:
        cell.close()


class PLC:
    """The test's line controller: nodes by path (``PackTags/Status/StateCurrent``), the handshake, the
    methods."""

    def __init__(self, client: Client, ns: int, packml: int) -> None:
        self.client, self.ns, self.packml = client, ns, packml

    def node(self, path: str) -> Node:
        return self.client.get_node(ua.NodeId(path.replace("/", "."), self.ns))

    async def read(self, path: str) -> Any:
        return await self.node(f"PackTags/{path}").read_value()

    async def write(self, path: str, value: Any, vtype: ua.VariantType) -> None:
        await self.node(f"PackTags/{path}").write_value(ua.Variant(value, vtype))

    async def state(self) -> int:
        return int(await self.read("Status/StateCurrent"))

    async def handshake(self, command: int) -> None:
        """CntrlCmd, then CmdChangeRequest true; the cell has acted and reset it when the write returns."""
        await self.write("Command/CntrlCmd", command, ua.VariantType.Int32)
        await self.write("Command/CmdChangeRequest", True, ua.VariantType.Boolean)
        assert await self.read("Command/CmdChangeRequest") is False

    async def call(self, path: str, *args: ua.Variant) -> None:
        """The method at ``path`` (under the unit); raises its Bad status."""
        (await self.call_result(path, *args)).StatusCode.check()

    async def call_result(self, path: str, *args: ua.Variant) -> ua.CallMethodResult:
        """The result of the method at ``path`` (under the unit), found by its browse path: OPC 30050's
        names in the PackML namespace, the cell's own (SetPartId) in the cell's."""
        names = [f"{self.ns if name in CELL_METHODS else self.packml}:{name}" for name in path.split("/")]
        parent = await self.client.nodes.objects.get_child([f"{self.ns}:sim-ur5e-tof", *names[:-1]])
        method = await parent.get_child(names[-1])
        request = ua.CallMethodRequest(ObjectId=parent.nodeid, MethodId=method.nodeid,
                                       InputArguments=list(args))
        return (await self.client.uaclient.call([request]))[0]

    async def start(self, part_id: str, methods: bool = False) -> str:
        """Start a scan of ``part_id`` in Idle, through the handshake or SetPartId and the Start method;
        its job id once in Execute."""
        if methods:
            await self.call("SetPartId", ua.Variant(part_id, ua.VariantType.String))
            await self.call(f"{EXECUTE_STATE}/Start")
        else:
            await self.write("Command/Parameter/PartId", part_id, ua.VariantType.String)
            await self.handshake(START)
        await self.wait((EXECUTE,))
        return str(await self.read("Status/JobId"))

    async def wait(self, states: tuple[int, ...], timeout_s: float = 60.0) -> int:
        """Poll StateCurrent until it is one of ``states`` (a bound on waiting, not a timed check)."""
        deadline = time.monotonic() + timeout_s
        while (state := await self.state()) not in states:
            assert time.monotonic() < deadline, f"the line stayed in {state}, not {states}"
            await asyncio.sleep(0.01)
        return state

    async def to_idle(self) -> None:
        """Bring the line to Idle from wherever an earlier test left it."""
        state = await self.wait((STOPPED, IDLE, EXECUTE, ABORTED, COMPLETE))
        if state == EXECUTE:
            await self.handshake(STOP)
            state = await self.wait((STOPPED,))
        if state == ABORTED:
            await self.handshake(CLEAR)
            state = await self.wait((STOPPED,))
        if state != IDLE:
            await self.handshake(RESET)
            await self.wait((IDLE,))


async def _client(served: Served, user: str | None, secret: str | None = None) -> Client:
    """A client of ``served`` logging in as ``user`` (None: anonymous) with ``secret`` (None: the line
    key's), trusting the server's certificate when the cell encrypts."""
    client = Client(served.url, timeout=30)
    client.application_uri = PLC_URI
    if user is not None:
        client.set_user(user)
        client.set_password(secret if secret is not None else served.cell.keys["line"])
    if served.client_cert is not None:
        await client.set_security(SecurityPolicyBasic256Sha256, str(served.client_cert),
                                  str(served.client_key), server_certificate=str(served.server_cert))
    return client


@contextlib.asynccontextmanager
async def plc(served: Served, user: str | None = "test-line",
              secret: str | None = None) -> AsyncIterator[PLC]:
    async with await _client(served, user, secret) as client:
        yield await _plc(client)


async def _plc(client: Client) -> PLC:
    """The PLC of a connected ``client``."""
    namespaces = await client.get_namespace_array()
    return PLC(client, namespaces.index(NAMESPACE), namespaces.index(PACKML))


def run(coroutine: Any) -> Any:
    return asyncio.run(coroutine)


# ------------------------------------------------------------------------------------------------ cycles


def test_five_parts_through_the_handshake_and_the_methods(encrypted):
    async def scenario() -> list[dict[str, Any]]:
        results = []
        async with plc(encrypted) as line:
            await line.to_idle()
            seen: list[int] = []

            class Handler:
                def datachange_notification(self, node: Node, value: int, data: Any) -> None:
                    seen.append(value)

            subscription = await line.client.create_subscription(10, Handler())
            await subscription.subscribe_data_change(line.node("PackTags/Status/StateCurrent"))
            processed = await line.read("Admin/ProdProcessedCount")
            for i, part in enumerate(PARTS):
                methods = i % 2 == 1
                job_id = await line.start(part, methods)
                assert await line.wait(ENDS) == COMPLETE
                result = {name: await line.read(f"Result/{name}") for name in (
                    "JobId", "PartId", "Status", "LengthM", "WidthM", "HeightM", "UpperLengthM",
                    "UpperWidthM", "UpperHeightM", "Container", "ClearanceM", "Fits", "ScanTimeS",
                    "Converged", "Message")}
                assert result["JobId"] == job_id and result["PartId"] == part, result
                assert await line.read("Admin/ProdProcessedCount") == processed + i + 1
                # Complete holds the cycle's job, the one whose result it holds, until Reset
                assert await line.read("Status/JobId") == job_id
                results.append(result)
                if methods:
                    await line.call(f"{EXECUTE_STATE}/Reset")
                else:
                    await line.handshake(RESET)
                assert await line.wait((IDLE,)) == IDLE
                assert await line.read("Status/JobId") == ""
            await subscription.delete()
            assert seen.count(EXECUTE) == len(PARTS) and seen.count(COMPLETE) == len(PARTS), seen
            # a part the feeder does not know: no scan, a defective part, not a fault
            defective = await line.read("Admin/ProdDefectiveCount")
            await line.write("Command/Parameter/PartId", "unicorn", ua.VariantType.String)
            await line.handshake(START)
            assert await line.wait(ENDS) == COMPLETE
            assert (await line.read("Result/Status"), await line.read("Result/Fits")) == ("rejected", False)
            assert "unicorn" in await line.read("Result/Message")
            assert await line.read("Admin/ProdDefectiveCount") == defective + 1
            await line.handshake(RESET)
        return results

    results = run(scenario())
    for result in results:
        assert result["Status"] == "completed", result
        assert result["LengthM"] >= result["WidthM"] > 0.0 and result["HeightM"] > 0.0, result
        assert result["UpperLengthM"] >= result["LengthM"], result
        assert result["UpperHeightM"] >= result["HeightM"], result
        assert result["Fits"] and result["Container"] and result["ClearanceM"] >= 0.0, result
        # the raster ends by itself, within the time budget
        assert result["Converged"] and 0.0 < result["ScanTimeS"] < 60.0, result
    # a horizontal box measures the same wherever the feeder puts it
    first, last = results[0], results[-1]
    assert abs(first["LengthM"] - last["LengthM"]) < 0.02 and abs(first["HeightM"] - last["HeightM"]) < 0.02
    job = encrypted.rest(f"/api/v1/jobs/{results[-1]['JobId']}")
    assert job["status"] == "completed" and job["part_id"] == PARTS[-1]
    line = encrypted.rest("/api/v1/line")
    assert line["result"]["part_id"] == "unicorn" and line["state_name"] == "Idle"
    causes = [t["cause"] for t in encrypted.rest("/api/v1/line/history?limit=200")]
    assert "Start from OPC UA (key test-line)" in causes and "Reset from OPC UA (key test-line)" in causes


def test_the_unit_is_opc_30050s_typed_base_object_and_its_members_follow_a_start(encrypted):
    """A client that browses by OPC 30050's types (browse names in the PackML namespace, no NodeId known
    beforehand) finds the unit a PackMLBaseObjectType with its Status, Admin and state machines typed,
    reads its members follow a Start cycle (Start with the Parameter argument the standard declares), and
    is told SetMachSpeed is not offered."""
    async def typed(parent: Node, name: str, type_id: int, packml: int) -> Node:
        node = await parent.get_child(f"{packml}:{name}")
        assert await node.read_type_definition() == ua.NodeId(type_id, packml), name
        return node

    async def until(node: Node, value: Any) -> None:
        """Poll ``node`` until it reads ``value`` (a bound on waiting, not a timed check)."""
        deadline = time.monotonic() + 30.0
        while (seen := await node.read_value()) != value:
            assert time.monotonic() < deadline, f"{node} stayed {seen}, not {value}"
            await asyncio.sleep(0.01)

    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.to_idle()
            await line.client.load_data_type_definitions()  # PackMLCountDataType, from the server
            pk = line.packml
            unit = await line.client.nodes.objects.get_child(f"{line.ns}:sim-ur5e-tof")
            assert await unit.read_type_definition() == ua.NodeId(6, pk)  # PackMLBaseObjectType
            status = await typed(unit, "Status", 4, pk)  # PackMLStatusObjectType
            admin = await typed(unit, "Admin", 5, pk)  # PackMLAdminObjectType
            base = await typed(unit, "BaseStateMachine", 3, pk)  # PackMLBaseStateMachineType
            machine = await typed(base, "MachineState", 2, pk)  # PackMLMachineStateMachineType
            execute = await typed(machine, "ExecuteState", 1, pk)  # PackMLExecuteStateMachineType
            states = [await m.get_child("0:CurrentState") for m in (base, machine, execute)]
            execute_id = await states[2].get_child("0:Id")
            processed = await admin.get_child(f"{pk}:ProdProcessedCount")

            assert await (await status.get_child(f"{pk}:UnitModeCurrent")).read_value() == 1  # Produce
            assert await (await status.get_child(f"{pk}:UnitSupportedModes")).read_value() == \
                ua.NodeId(11, pk)  # ProductionMaintenanceModeEnum
            assert [(await s.read_value()).Text for s in states] == ["Cleared", "Running", "Idle"]
            assert await execute_id.read_value() == ua.NodeId(28, pk)  # the Idle state object
            (count,) = await processed.read_value()
            assert (count.Count, count.AccCount) == (await line.read("Admin/ProdProcessedCount"),) * 2

            await line.call("SetPartId", ua.Variant("cube", ua.VariantType.String))
            parameters = ua.Variant([ua.PackMLDescriptorDataType(ID=1, Name="speed", Value=1.0)],
                                    ua.VariantType.ExtensionObject)
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await execute.call_method(f"{pk}:Start", parameters)
            assert "Parameter must be empty" in await line.read("Status/CommandMessage")
            # Start as OPC 30050 declares it, with its Parameter array (empty: the cell takes none)
            await execute.call_method(f"{pk}:Start", ua.Variant([], ua.VariantType.ExtensionObject))
            await until(states[2], ua.LocalizedText("Execute"))
            assert await execute_id.read_value() == ua.NodeId(36, pk)
            await until(states[2], ua.LocalizedText("Complete"))
            assert (await processed.read_value())[0].Count == count.Count + 1
            await execute.call_method(f"{pk}:Reset")
            await until(states[2], ua.LocalizedText("Idle"))

            with pytest.raises(ua.uaerrors.BadNotSupported):
                await unit.call_method(f"{pk}:SetMachSpeed", ua.Variant(1.0, ua.VariantType.Float))
            assert await line.read("Status/CommandMessage") == (
                "refused a call of SetMachSpeed from OPC UA (key test-line): the cell has no machine speed")

    run(scenario())


def test_the_machine_states_reset_leaves_stopped_where_the_execute_state_machine_is_inactive(encrypted):
    """OPC 30050's Stopped -> Running (StoppedToRunning, i=59) is caused by PackMLMachineStateMachineType's
    Reset: a client following the standard finds it on MachineState, as ExecuteState is not active in
    Stopped."""
    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.to_idle()
            await line.handshake(STOP)
            await line.wait((STOPPED,))
            machine = "BaseStateMachine/MachineState"
            assert await line.node(f"Unit/{machine}/ExecuteState/CurrentState").read_value() == \
                ua.LocalizedText("")
            await line.call(f"{machine}/Reset")
            assert await line.wait((IDLE,)) == IDLE
            assert await line.read("Status/CommandMessage") == "Reset from OPC UA (key test-line)"

    run(scenario())


def test_the_state_machines_list_their_states_and_transitions_and_the_status_is_typed(encrypted):
    """Each state machine's AvailableStates and AvailableTransitions (mandatory) list the state and
    transition objects of its type in OPC 30050's nodeset; MachSpeed's and CurMachSpeed's EURange is 0..0
    (the cell has no speed); UnitModeCurrent's DataType is ProductionMaintenanceModeEnum."""
    machines = {  # the state machine's path: its type's states and transitions (numeric ids in the nodeset)
        "BaseStateMachine": ({61, 62, 71}, {65, 66, 67}),
        "BaseStateMachine/MachineState": ({53, 54, 55, 75}, {57, 58, 59, 60}),
        EXECUTE_STATE: (set(range(27, 39)), {39, 40, 41, 42, 43, 44, 45, 46, 47, 48, 49, 50, 51, 52, 99, 100,
                                             101, 102, 103}),
    }

    async def scenario() -> None:
        async with plc(encrypted) as line:
            pk = line.packml
            for machine, expected in machines.items():
                for name, ids in zip(("AvailableStates", "AvailableTransitions"), expected, strict=True):
                    value = await line.node(f"Unit/{machine}/{name}").read_value()
                    assert value is not None and {i.Identifier for i in value} == ids, (machine, name, value)
                    assert {i.NamespaceIndex for i in value} == {pk}, (machine, name)
            for speed in ("MachSpeed", "CurMachSpeed"):
                assert await line.node(f"Unit/Status/{speed}/EURange").read_value() == \
                    ua.Range(Low=0.0, High=0.0)
            mode = line.node("Unit/Status/UnitModeCurrent")
            assert await mode.read_data_type() == ua.NodeId(11, pk)  # ProductionMaintenanceModeEnum
            assert await mode.read_value() == await line.read("Status/UnitModeCurrent")

    run(scenario())


def test_only_the_five_command_tags_are_writable(encrypted):
    """Every variable under the unit, the typed members and their properties included, is read only but
    the five PackTags/Command variables: a nodeset update or a stray set_writable is caught here."""
    async def walk(node: Node, ns: int, seen: set[ua.NodeId]) -> AsyncIterator[Node]:
        for child in await node.get_children(refs=ua.ObjectIds.HierarchicalReferences):
            if child.nodeid in seen or child.nodeid.NamespaceIndex != ns:  # not the unit's: a type's
                continue
            seen.add(child.nodeid)
            yield child
            async for grandchild in walk(child, ns, seen):
                yield grandchild

    async def scenario() -> tuple[int, set[str]]:
        async with plc(encrypted) as line:
            unit = await line.client.nodes.objects.get_child(f"{line.ns}:sim-ur5e-tof")
            variables, writable = 0, set()
            async for node in walk(unit, line.ns, set()):
                if await node.read_node_class() != ua.NodeClass.Variable:
                    continue
                variables += 1
                for attribute in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
                    level = (await node.read_attribute(attribute)).Value.Value
                    if level & ua.AccessLevel.CurrentWrite.mask:
                        writable.add(str(node.nodeid.Identifier))
            return variables, writable

    variables, writable = run(scenario())
    assert variables > 50, variables  # the walk reached the typed members and the PackTags
    assert writable == {"PackTags.Command.CntrlCmd", "PackTags.Command.CmdChangeRequest",
                        "PackTags.Command.UnitMode", "PackTags.Command.UnitModeChangeRequest",
                        "PackTags.Command.Parameter.PartId"}


def test_stop_during_execute_stops_the_scan(encrypted):
    async def scenario() -> tuple[str, int, str]:
        async with plc(encrypted) as line:
            await line.to_idle()
            job_id = await line.start("vertical_box", methods=True)
            await line.call("BaseStateMachine/MachineState/Stop")
            assert await line.wait(ENDS) == STOPPED
            return job_id, await line.read("Admin/StopReason/ID"), await line.read("Admin/StopReason/Message")

    job_id, reason_id, reason = run(scenario())
    assert reason_id == 1 and reason == "Stop from OPC UA (key test-line)"
    job = encrypted.cell.wait_job(job_id, ("stopped", "completed", "failed"))
    assert job["status"] == "stopped", job
    assert encrypted.rest("/api/v1/cell")["job"] is None


def test_a_part_placed_into_the_robot_base_is_rejected_at_start_with_the_reason(encrypted):
    """The placement is checked when the scan is submitted: a defective part saying why, no scan and no
    fault (its scan was accepted, and failed on the arm's first tick: Aborted)."""
    async def scenario() -> tuple[int, str, str, int, int]:
        async with plc(encrypted) as line:
            await line.to_idle()
            defective = await line.read("Admin/ProdDefectiveCount")
            await line.write("Command/Parameter/PartId", "cube@-0.42,0,0", ua.VariantType.String)
            await line.handshake(START)
            ended = await line.wait(ENDS)
            status, message = await line.read("Result/Status"), await line.read("Result/Message")
            counted = await line.read("Admin/ProdDefectiveCount") - defective
            reason_id = await line.read("Admin/StopReason/ID")
            if ended == COMPLETE:
                await line.handshake(RESET)
            return ended, status, message, counted, reason_id

    ended, status, message, counted, reason_id = run(scenario())
    assert (ended, status, counted) == (COMPLETE, "rejected", 1), (ended, status, message, reason_id)
    assert message.startswith("object_pose: object pose [-0.42, 0.0, 0.0] puts cube into the robot base "
                              "(link0) at the arm's home joints"), message
    assert encrypted.rest("/api/v1/cell")["job"] is None


def test_start_in_execute_is_refused_and_changes_nothing(encrypted):
    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.to_idle()
            job_id = await line.start("cube")
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await line.call(f"{EXECUTE_STATE}/Start")
            assert await line.state() == EXECUTE and await line.read("Status/JobId") == job_id
            message = await line.read("Status/CommandMessage")
            assert message == ("refused Start from OPC UA (key test-line): Start is not valid in Execute "
                               "(valid in: Idle)")
            # a refused write says so; the same refusal again says so again, not the write's refusal
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await line.write("Command/Parameter/PartId", 1, ua.VariantType.Int32)
            assert "refused a write of PartId" in await line.read("Status/CommandMessage")
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await line.call(f"{EXECUTE_STATE}/Start")
            assert await line.read("Status/CommandMessage") == message
            await line.write("Command/Parameter/PartId", "bunny", ua.VariantType.String)
            await line.handshake(START)
            assert await line.state() == EXECUTE and await line.read("Status/JobId") == job_id
            assert "refused Start" in await line.read("Status/CommandMessage")
            assert await line.wait(ENDS) == COMPLETE
            assert await line.read("Result/PartId") == "cube"

    run(scenario())


def test_the_result_waits_in_complete_for_a_plc_that_disconnected(encrypted):
    async def start() -> str:
        async with plc(encrypted) as line:
            await line.to_idle()
            return await line.start("pyramid")

    async def later() -> tuple[int, str, str]:
        async with plc(encrypted) as line:
            return await line.wait(ENDS), await line.read("Result/JobId"), await line.read("Result/Status")

    job_id = run(start())  # the PLC is gone mid-scan
    assert encrypted.rest("/api/v1/line")["state_name"] in ("Execute", "Completing", "Complete")
    encrypted.cell.wait_job(job_id, ("completed", "stopped", "failed"))
    time.sleep(0.5)  # a Complete that did not hold would have moved on by now
    assert run(later()) == (COMPLETE, job_id, "completed")


def test_the_unit_mode_through_the_handshake_and_set_unit_mode(encrypted):
    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.to_idle()
            await line.write("Command/UnitMode", 3, ua.VariantType.Int32)
            await line.write("Command/UnitModeChangeRequest", True, ua.VariantType.Boolean)
            assert await line.read("Command/UnitModeChangeRequest") is False
            assert await line.read("Status/UnitModeCurrent") == 3
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await line.call(f"{EXECUTE_STATE}/Start")
            assert "Manual mode" in await line.read("Status/CommandMessage")
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await line.call("SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
            assert "not offered" in await line.read("Status/CommandMessage")
            await line.call("SetUnitMode", ua.Variant(1, ua.VariantType.Int32))
            assert await line.read("Status/UnitModeCurrent") == 1
            assert await line.state() == IDLE
            # a mode the unit is in already is accepted, and said
            with pytest.raises(ua.uaerrors.BadInvalidArgument):
                await line.call("SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
            await line.call("SetUnitMode", ua.Variant(1, ua.VariantType.Int32))
            assert await line.read("Status/CommandMessage") == (
                "unit mode Production from OPC UA (key test-line): already Production")

    run(scenario())


# ------------------------------------------------------------------------------------------------ refusals


def test_writes_of_the_wrong_type_or_too_long_are_refused_and_change_nothing(encrypted):
    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.write("Command/Parameter/PartId", "cube", ua.VariantType.String)
            part_id = line.node("PackTags/Command/Parameter/PartId")
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await line.write("Command/Parameter/PartId", 42, ua.VariantType.Int32)
            assert "expects a String, got Int32" in await line.read("Status/CommandMessage")
            with pytest.raises(ua.uaerrors.BadOutOfRange):  # REST's rule: printable ASCII only
                await line.write("Command/Parameter/PartId", "würfel部品", ua.VariantType.String)
            assert "got 'würfel部品'" in await line.read("Status/CommandMessage")
            with pytest.raises(ua.uaerrors.BadOutOfRange):
                await line.write("Command/Parameter/PartId", "x" * 65, ua.VariantType.String)
            assert "1 to 64 printable ASCII characters, got 65" in await line.read("Status/CommandMessage")
            # a sim cell's part id is the feeder's NAME[@x_m,y_m,yaw_deg]: a malformed one is refused
            # when it is written or set, not scanned as a defective part at Start
            for malformed in ("cube@abc", "cube@0.01,0", "cube @0,0,0"):
                with pytest.raises(ua.uaerrors.BadOutOfRange):
                    await line.write("Command/Parameter/PartId", malformed, ua.VariantType.String)
                message = await line.read("Status/CommandMessage")
                assert message.startswith(f"refused a write of PartId from OPC UA (key test-line): part id "
                                          f"{malformed!r}: "), message
                result = await line.call_result("SetPartId", ua.Variant(malformed, ua.VariantType.String))
                assert result.StatusCode.value == ua.StatusCodes.BadInvalidArgument, (malformed, result)
                assert await line.read("Status/CommandMessage") == message.replace(
                    "a write of PartId", "part id")
            with pytest.raises(ua.uaerrors.BadOutOfRange):  # one bad value refuses the whole request
                await line.client.write_values(
                    [part_id, line.node("PackTags/Command/CntrlCmd")],
                    [ua.Variant("bunny", ua.VariantType.String), ua.Variant(42, ua.VariantType.Int32)])
            with pytest.raises(ua.uaerrors.BadTypeMismatch):
                await line.write("Command/CmdChangeRequest", 1, ua.VariantType.Int32)
            assert await part_id.read_value() == "cube"
            for refused in (None, "würfel部品", "y" * 65, ""):  # None: a null String
                result = await line.call_result("SetPartId", ua.Variant(refused, ua.VariantType.String))
                assert result.StatusCode.value == ua.StatusCodes.BadInvalidArgument, (refused, result)
                assert [r.value for r in result.InputArgumentResults] == [ua.StatusCodes.BadOutOfRange]
                assert "refused part id" in await line.read("Status/CommandMessage")
            with pytest.raises(ua.UaStatusCodeError):
                await line.call("SetPartId", ua.Variant(7, ua.VariantType.Int32))
            assert await part_id.read_value() == "cube"
            for read_only, value in (("Status/StateCurrent", ua.Variant(4, ua.VariantType.Int32)),
                                     ("Admin/ProdProcessedCount", ua.Variant(0, ua.VariantType.Int32)),
                                     ("Result/Fits", ua.Variant(True, ua.VariantType.Boolean))):
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await line.node(f"PackTags/{read_only}").write_value(value)
                name = read_only.rsplit("/", 1)[-1]
                assert await line.read("Status/CommandMessage") == (
                    f"refused a write of {name} from OPC UA (key test-line): read only")
            assert await part_id.read_value() == "cube"

    run(scenario())
    assert encrypted.rest("/api/v1/line")["part_id"] == "cube"


def test_every_refused_call_says_why_in_the_command_message(encrypted):
    """A call refused for its arguments (their number or type) replaces the message of an earlier
    refusal, and the unit modes a refusal offers are those the cell accepts."""
    async def scenario() -> None:
        async with plc(encrypted) as line:
            await line.to_idle()

            async def refused(path: str, code: int, message: str, *args: ua.Variant) -> None:
                with pytest.raises(ua.uaerrors.BadInvalidState):
                    await line.call("BaseStateMachine/Clear")  # an earlier refusal: Clear in Idle
                result = await line.call_result(path, *args)
                assert result.StatusCode.value == code, (path, args, result)
                assert await line.read("Status/CommandMessage") == message

            source = "from OPC UA (key test-line)"
            await refused(f"{EXECUTE_STATE}/Reset", ua.StatusCodes.BadTooManyArguments,
                          f"refused a call of Reset {source}: it takes no argument, got 1",
                          ua.Variant(1, ua.VariantType.Int32))
            await refused("SetUnitMode", ua.StatusCodes.BadArgumentsMissing,
                          f"refused a call of SetUnitMode {source}: it takes one argument, Int32 "
                          "RequestedMode, got none")
            await refused("SetUnitMode", ua.StatusCodes.BadTooManyArguments,
                          f"refused a call of SetUnitMode {source}: it takes one argument, Int32 "
                          "RequestedMode, got 2",
                          ua.Variant(1, ua.VariantType.Int32), ua.Variant(1, ua.VariantType.Int32))
            await refused("SetPartId", ua.StatusCodes.BadInvalidArgument,
                          f"refused a call of SetPartId {source}: PartId expects a String, got Int32",
                          ua.Variant(7, ua.VariantType.Int32))
            await refused("SetUnitMode", ua.StatusCodes.BadInvalidArgument,
                          f"refused unit mode 7 {source}: one of 1 Production, 3 Manual",
                          ua.Variant(7, ua.VariantType.Int32))
            # Start's Parameter of another type, empty or not, is a type mismatch, not a value refused
            for parameter, got in ((ua.Variant(7, ua.VariantType.Int32), "Int32"),
                                   (ua.Variant([], ua.VariantType.Int32), "an array of Int32"),
                                   (ua.Variant([7], ua.VariantType.Int32), "an array of Int32")):
                await refused(f"{EXECUTE_STATE}/Start", ua.StatusCodes.BadInvalidArgument,
                              f"refused a call of Start {source}: Parameter expects an array of "
                              f"PackMLDescriptorDataType, got {got}", parameter)
                result = await line.call_result(f"{EXECUTE_STATE}/Start", parameter)
                assert [r.value for r in result.InputArgumentResults] == [ua.StatusCodes.BadTypeMismatch]
            assert await line.state() == IDLE
            with pytest.raises(ua.uaerrors.BadOutOfRange):
                await line.write("Command/UnitMode", 9, ua.VariantType.Int32)
            assert await line.read("Status/CommandMessage") == (
                f"refused a write of UnitMode {source}: 9 is no unit mode (0 none, 1 Production, 3 Manual)")

    run(scenario())


def test_anonymous_and_unknown_users_can_do_nothing(encrypted):
    keys = encrypted.cell.keys

    async def refused(user: str | None, secret: str | None) -> None:
        why = ua.uaerrors.BadUserAccessDenied if user else ua.uaerrors.BadIdentityTokenRejected
        with pytest.raises(why):
            async with plc(encrypted, user, secret):
                pass

    async def unactivated(ns: int) -> None:
        """A session that never logged in may read, browse and write nothing."""
        client = await _client(encrypted, None)
        await client.connect_socket()
        try:
            await client.send_hello()
            await client.open_secure_channel()
            await client.create_session()
            state, command = (client.get_node(ua.NodeId(f"PackTags.{name}", ns))
                              for name in ("Status.StateCurrent", "Command.CntrlCmd"))
            for action in (client.nodes.server_state.read_value(), state.read_value(),
                           client.nodes.objects.get_children(),
                           command.write_value(ua.Variant(1, ua.VariantType.Int32))):
                with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                    await action
        finally:
            client.disconnect_socket()

    async def scenario() -> None:
        await refused(None, None)
        await refused("test-line", "cell_" + "x" * 43)
        await refused("test-line", keys["operator"])  # another key's secret
        await refused("test-viewer", keys["viewer"])  # a key without the line permission
        await refused("test-operator", keys["operator"])
        await refused(keys["line"], "test-line")  # the user name and the password swapped
        await refused(f" {keys['line']}\n", "test-line")  # so, pasted with a space and a line end
        async with plc(encrypted, "test-admin", keys["admin"]) as line:  # admin keys have it too
            assert await line.state() in (STOPPED, IDLE, COMPLETE, ABORTED)
            ns = line.ns
        await unactivated(ns)

    run(scenario())
    assert not any(secret in encrypted.cell.log() for secret in keys.values())
    # the PLC hears only BadUserAccessDenied: the cell's log tells the integrator which mistake it was
    said = {json.loads(line)["msg"] for line in encrypted.cell.log().splitlines() if line.startswith("{")}
    login = "OPC UA: login refused for user name"
    role_line = "which may not drive the line: give the PLC a key of role line (cell keys create --role line)"
    assert {
        f"{login} 'test-line': the password is no active key's secret: a mistyped secret, or a key revoked "
        "or made in another store than this service's (cell keys list --data-dir, as the service's user)",
        f"{login} 'test-line': the password is another key's secret: the user name must be the name of the "
        "key whose secret it is",
        f"{login} 'test-viewer': key test-viewer has role viewer, {role_line}",
        f"{login} 'test-operator': key test-operator has role operator, {role_line}",
        f"{login} <a key's secret, not shown>: the user name is a key's secret: the user name is the key's "
        "name, the password its secret (swapped?)",
    } <= said


def test_a_revoked_key_is_refused_from_its_next_request(encrypted):
    store = open_store(sqlite_url(encrypted.cell.data_dir))
    try:
        secret = create_key(store, "line", "plc-revoked")[1]
    finally:
        store.close()
    time.sleep(1.5)  # the service reloads its keys every second

    async def scenario() -> None:
        async with plc(encrypted, "plc-revoked", secret) as line:
            await line.state()
            store = open_store(sqlite_url(encrypted.cell.data_dir))
            try:
                store.revoke_key("plc-revoked")
            finally:
                store.close()
            await asyncio.sleep(1.5)
            # refused: the read itself, or the client's own keep-alive read first, which drops the session
            with pytest.raises((ua.uaerrors.BadUserAccessDenied, ConnectionError)):
                await line.state()

    run(scenario())


def test_the_server_certificate_is_made_once_and_its_key_kept_private(encrypted, tmp_path):
    folder = encrypted.cell.data_dir / "opcua"
    assert (folder / KEY_FILE).stat().st_mode & 0o777 == 0o600 and folder.stat().st_mode & 0o777 == 0o700
    cert = x509.load_der_x509_certificate((folder / CERT_FILE).read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "urn:cell:sim-ur5e-tof" in names.get_values_for_type(x509.UniformResourceIdentifier)
    # made on the first start, then the same files
    made = ensure_certificate(tmp_path / "opcua", "urn:cell:x", "127.0.0.1")
    first = [path.read_bytes() for path in made]
    again = ensure_certificate(tmp_path / "opcua", "urn:cell:x", "127.0.0.1")
    assert again == made and [path.read_bytes() for path in again] == first


# ------------------------------------------------------------------------------------------------ faults


def test_a_driver_fault_during_execute_aborts_then_clear_and_reset_recover(tmp_path):
    def faulty(data: dict[str, Any]) -> None:
        data["sim"]["faults"] = [{"at_s": 0.5, "kind": "protective stop"}]

    cell, url = _serve(tmp_path, "none", faulty)
    served = Served(cell, url)

    async def scenario() -> tuple[int, str]:
        async with plc(served) as line:
            await line.to_idle()
            await line.write("Command/Parameter/PartId", "cube", ua.VariantType.String)
            await line.handshake(START)
            assert await line.wait(ENDS) == ABORTED
            reason = (await line.read("Admin/StopReason/ID"), await line.read("Admin/StopReason/Message"))
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await line.call(f"{EXECUTE_STATE}/Reset")
            assert await line.state() == ABORTED
            await line.handshake(CLEAR)
            await line.wait((STOPPED,))
            await line.call(f"{EXECUTE_STATE}/Reset")
            await line.wait((IDLE,))
            return reason

    try:
        reason_id, reason = run(scenario())
        assert reason_id == 5 and "protective stop" in reason, reason
        arm = served.rest("/api/v1/cell")["arm"]
        assert not arm["faults"], arm
    finally:
        cell.close()


# ------------------------------------------------------------------------------------------------ in process


def test_an_operators_stop_holds_the_plcs_reset_and_the_plc_sees_the_shutdown(tmp_path, monkeypatch):
    """A cell served in this process: an operator's STOP holds the queue until an operator resumes it (the
    PLC's Reset is refused till then), and a shutdown during Execute is Stopping, then Stopped (stop reason
    7), which the PLC reads before the server closes."""
    url = f"opc.tcp://127.0.0.1:{free_port()}/cell"
    cell = yaml.safe_load(UR5E.read_text())
    cell["line"] = {"opcua": {"endpoint": url, "security": "none"}, "max_time_s": 60.0}
    config, data = tmp_path / "cell.yaml", tmp_path / "data"
    config.write_text(yaml.safe_dump(cell))
    store = open_data_store(data, sqlite_url(data))
    keys = {role: create_key(store, role, f"test-{role}")[1] for role in ("operator", "line")}
    store.close()

    @contextlib.asynccontextmanager
    async def connected() -> AsyncIterator[PLC]:
        client = Client(url, timeout=30)
        client.set_user("test-line")
        client.set_password(keys["line"])
        async with client:
            yield await _plc(client)

    seen_at_close: list[tuple[int, int]] = []
    stop = LineOPCUA.stop

    async def stop_after_a_plc_read(server: LineOPCUA) -> None:
        await server.settle()
        async with connected() as line:  # the last moment the server serves
            seen_at_close.append((await line.state(), await line.read("Admin/StopReason/ID")))
        await stop(server)

    monkeypatch.setattr(LineOPCUA, "stop", stop_after_a_plc_read)
    operator = {"Authorization": f"Bearer {keys['operator']}"}

    async def scenario(http: TestClient) -> None:
        async with connected() as line:
            await line.to_idle()
            await line.start("bunny")
            stop = await asyncio.to_thread(http.post, "/api/v1/stop", json={"reason": "person in cell"},
                                           headers=operator)
            assert stop.status_code == 200
            assert await line.wait((STOPPED,)) == STOPPED
            with pytest.raises(ua.uaerrors.BadInvalidState):
                await line.call(f"{EXECUTE_STATE}/Reset")
            await line.handshake(RESET)
            assert await line.state() == STOPPED
            message = await line.read("Status/CommandMessage")
            assert message.startswith("refused Reset") and "POST /api/v1/queue/resume" in message, message
            resumed = await asyncio.to_thread(http.post, "/api/v1/queue/resume", headers=operator)
            assert resumed.status_code == 200
            await line.handshake(RESET)
            await line.wait((IDLE,))
            await line.start("bunny")  # and the service shuts down while it scans

    with TestClient(create_app(ServiceSettings(config_file=config, data_dir=data))) as http:
        run(scenario(http))
    assert seen_at_close == [(STOPPED, 7)]
    store = open_store(sqlite_url(data))
    try:
        stopping, stopped = reversed([t for _, t in store.line_transitions("sim-ur5e-tof", limit=2)])
        line = store.get_line("sim-ur5e-tof")
    finally:
        store.close()
    assert (stopping.from_state, stopping.to_state, stopped.to_state) == (EXECUTE, 7, STOPPED)
    # the scan's job stopped, or cancelled before it started: "is shutting down", "shut down before ..."
    assert line is not None and line.stop_reason_id == 7 and "the service" in line.stop_reason
    assert "shut" in line.stop_reason


@pytest.mark.parametrize("host", ["127.0.0.1", "192.0.2.1"])  # a port in use; an address of no interface here
def test_serve_refuses_an_endpoint_it_cannot_listen_on_in_one_line(tmp_path, host):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        data = yaml.safe_load(UR5E.read_text())
        data["line"] = {"opcua": {"endpoint": f"opc.tcp://{host}:{port}/cell"}}
        config = tmp_path / "cell.yaml"
        config.write_text(yaml.safe_dump(data))
        serve = [*CELL, "serve", "--config", str(config), "--data-dir", str(tmp_path / "data"), "--port",
                 str(free_port())]
        out = subprocess.run(serve, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out.stdout + out.stderr
    why = "Address already in use" if host == "127.0.0.1" else "Cannot assign requested address"
    endpoint = f"opc.tcp://{host}:{port}/cell"
    assert out.stderr.strip() == f"error: line.opcua.endpoint: cannot listen on {endpoint}: {why}", out.stderr
    assert not (tmp_path / "data").exists()  # refused before the store, its lease and its files were made
