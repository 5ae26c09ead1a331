"""The cell's OPC UA address space: what each node is, its type, who may write it, and its value.

Under ``Objects/<cell name>`` (NodeId ``s=Unit``):

- ``PackTags/`` a subset of the classic PackML tags (ISA-TR88.00.02) and the cell's own: ``Command/`` what
  the PLC writes, ``Status/``, ``Admin/`` and ``Result/`` what it reads (:data:`TAGS`; no MachSpeed, no
  StateRequested or ChangeInProcess tags: ``docs/packml-opcua.md`` lists what is not offered).
- OPC 30050's state machine objects and methods: ``BaseStateMachine`` (Abort, Clear), its
  ``MachineState`` (Stop) and that one's ``ExecuteState`` (Reset, Start, Hold, Unhold, Suspend,
  Unsuspend), each with its ``CurrentState``; and on the unit ``SetUnitMode(Int32 RequestedMode)`` and
  the cell's own ``SetPartId(String PartId)`` (OPC 30050's ``SetParameter`` carries numbers only)
  (:data:`METHODS`).

Every NodeId is a string in the cell's namespace (``line.opcua.namespace``): the path with dots
(``s=PackTags.Command.CntrlCmd``), the same on every cell. Browse names are in the cell's namespace too,
except OPC 30050's names (the state machines, their methods, ``SetUnitMode``: the PackML namespace
``http://opcfoundation.org/UA/PackML/``) and ``CurrentState`` (namespace 0), so that a client that
resolves OPC 30050 browse paths finds them. The nodeset's types are not instantiated: the objects are
plain ``BaseObjectType`` objects with the members named here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from asyncua import Node, Server, ua

from cell.line.config import PART_ID_MAX
from cell.line.controller import LineSnapshot
from cell.line.packml import Command, State
from cell.line.result import CycleResult

PACKML_URI = "http://opcfoundation.org/UA/PackML/"
"""OPC 30050's namespace: the browse names of its objects and methods."""
UNIT_ID = "Unit"
"""The NodeId (string, in the cell's namespace) of the cell's object under ``Objects``."""
V = ua.VariantType

Reader = Callable[[LineSnapshot], Any]


def _result(read: Callable[[CycleResult], Any], empty: Any) -> Reader:
    return lambda s: empty if s.result is None else read(s.result)


def machine_states(state: State) -> tuple[str, str, str]:
    """``CurrentState`` of OPC 30050's BaseStateMachine, MachineState and ExecuteState for the PackML
    ``state`` ("" for a sub-machine that is not active): Aborting and Aborted are the base machine's own;
    every other state is within Cleared, where Stopped, Stopping and Clearing are the machine state's
    own and every other state is within Running, the execute state machine's."""
    if state in (State.ABORTING, State.ABORTED):
        return state.label, "", ""
    if state in (State.STOPPED, State.STOPPING, State.CLEARING):
        return "Cleared", state.label, ""
    return "Cleared", "Running", state.label


@dataclass(frozen=True)
class Tag:
    """One variable: ``path`` under the unit (``/``-separated), its type, what it means (the node's
    Description), whether a client may write it, and ``read``, its value from the line's snapshot (None:
    the PLC's own register, or a node the server sets by itself)."""

    path: str
    vtype: ua.VariantType
    doc: str
    writable: bool = False
    read: Reader | None = None

    @property
    def initial(self) -> Any:
        """The value before the line's first snapshot is written: zero, false or empty."""
        return {V.Int32: 0, V.Boolean: False, V.String: "", V.Double: 0.0,
                V.LocalizedText: ua.LocalizedText("")}[self.vtype]


CNTRL_CMD = "PackTags/Command/CntrlCmd"
CMD_CHANGE_REQUEST = "PackTags/Command/CmdChangeRequest"
UNIT_MODE = "PackTags/Command/UnitMode"
UNIT_MODE_CHANGE_REQUEST = "PackTags/Command/UnitModeChangeRequest"
PART_ID = "PackTags/Command/Parameter/PartId"
COMMAND_MESSAGE = "PackTags/Status/CommandMessage"
STATE_CURRENT = "PackTags/Status/StateCurrent"

_COMMANDS = ", ".join(f"{c.value} {c.label}" for c in Command)

TAGS: tuple[Tag, ...] = (
    Tag(CNTRL_CMD, V.Int32, f"The command the PLC asks for ({_COMMANDS}; 0 none); acted on when "
        "CmdChangeRequest goes true.", writable=True),
    Tag(CMD_CHANGE_REQUEST, V.Boolean, "The PLC writes true after CntrlCmd: the cell acts on CntrlCmd, "
        "then writes it false (Status/CommandMessage says what was done or why not).", writable=True),
    Tag(UNIT_MODE, V.Int32, "The unit mode the PLC asks for (1 Production, 3 Manual); acted on when "
        "UnitModeChangeRequest goes true.", writable=True),
    Tag(UNIT_MODE_CHANGE_REQUEST, V.Boolean, "The PLC writes true after UnitMode: the cell changes mode "
        "(in Stopped, Idle or Aborted only), then writes it false.", writable=True),
    Tag(PART_ID, V.String, f"The part the next Start scans (1 to {PART_ID_MAX} printable ASCII "
        "characters; in a sim cell the simulated feeder's part: NAME or NAME@x_m,y_m,yaw_deg).",
        writable=True, read=lambda s: s.part_id),
    Tag(STATE_CURRENT, V.Int32, "The PackML state (1 Clearing, 2 Stopped, 3 Starting, "
        "4 Idle, 5 Suspended, 6 Execute, 7 Stopping, 8 Aborting, 9 Aborted, 10 Holding, 11 Held, "
        "12 Unholding, 13 Suspending, 14 Unsuspending, 15 Resetting, 16 Completing, 17 Complete).",
        read=lambda s: int(s.state)),
    Tag("PackTags/Status/UnitModeCurrent", V.Int32, "The unit mode (1 Production: the line starts scans; "
        "3 Manual: the operator's).", read=lambda s: int(s.mode)),
    Tag("PackTags/Status/JobId", V.String, "The scan job of the current cycle (empty outside one).",
        read=lambda s: s.job_id or ""),
    Tag(COMMAND_MESSAGE, V.String, "The outcome of the last command or mode change from any way in "
        "(OPC UA, REST, digital I/O), or of a write or call this server refused, in words: why a command "
        "was refused.", read=lambda s: s.message),
    Tag("PackTags/Admin/ProdProcessedCount", V.Int32, "Parts processed (each cycle that reached "
        "Complete), kept across restarts.", read=lambda s: s.processed),
    Tag("PackTags/Admin/ProdDefectiveCount", V.Int32, "Of those, parts that fit no container or could "
        "not be scanned (defective, not a fault).", read=lambda s: s.defective),
    Tag("PackTags/Admin/StopReason/ID", V.Int32, "Why the cell last stopped or aborted (0 none, 1 the "
        "line's Stop, 2 an operator's STOP, 3 the line's Abort, 4 a safety stop, 5 an arm fault, 6 a failed "
        "scan, 7 the service shut down or started, 8 Clear could not recover the arm).",
        read=lambda s: int(s.stop_reason_id)),
    Tag("PackTags/Admin/StopReason/Message", V.String, "The last stop reason in words.",
        read=lambda s: s.stop_reason),
    Tag("PackTags/Result/JobId", V.String, "The last result's scan job (empty: no scan ran, see Status).",
        read=_result(lambda r: r.job_id, "")),
    Tag("PackTags/Result/PartId", V.String, "The part id the last result is of.",
        read=_result(lambda r: r.part_id, "")),
    Tag("PackTags/Result/Status", V.String, "How the last cycle that reached Complete ended: completed, "
        "no_object (nothing on the table) or rejected (no scan ran: an unknown part).",
        read=_result(lambda r: r.status, "")),
    Tag("PackTags/Result/LengthM", V.Double, "The packing box's length [m] (>= WidthM; 0: not measured).",
        read=_result(lambda r: r.length_m, 0.0)),
    Tag("PackTags/Result/WidthM", V.Double, "The packing box's width [m].",
        read=_result(lambda r: r.width_m, 0.0)),
    Tag("PackTags/Result/HeightM", V.Double, "The packing box's height [m].",
        read=_result(lambda r: r.height_m, 0.0)),
    Tag("PackTags/Result/UpperLengthM", V.Double, "The upper bound of the box's length [m] from the "
        "sensor's error model: the box the container is chosen for (0: not measured).",
        read=_result(lambda r: r.upper_length_m, 0.0)),
    Tag("PackTags/Result/UpperWidthM", V.Double, "The upper bound of the box's width [m].",
        read=_result(lambda r: r.upper_width_m, 0.0)),
    Tag("PackTags/Result/UpperHeightM", V.Double, "The upper bound of the box's height [m].",
        read=_result(lambda r: r.upper_height_m, 0.0)),
    Tag("PackTags/Result/Container", V.String, "The container chosen from the cell's catalogue "
        "(packing.containers; empty when none fits).", read=_result(lambda r: r.container, "")),
    Tag("PackTags/Result/ClearanceM", V.Double, "The smallest gap between the box's upper bound and the "
        "container's walls or lid [m] (0 when none fits).", read=_result(lambda r: r.clearance_m, 0.0)),
    Tag("PackTags/Result/Fits", V.Boolean, "Whether a container was chosen (false: the part is "
        "defective).", read=_result(lambda r: r.fits, False)),
    Tag("PackTags/Result/ScanTimeS", V.Double, "The scan's time on the cell [s]: its job's clock from "
        "its start, the move to the first view included (the clock line.max_time_s counts; 0: no scan ran).",
        read=_result(lambda r: r.scan_time_s, 0.0)),
    Tag("PackTags/Result/Converged", V.Boolean, "Whether the scan completed by its planner's own "
        "termination rule (false: its time budget ran out, or no part was measured).",
        read=_result(lambda r: r.converged, False)),
    Tag("PackTags/Result/Message", V.String, "Why the cycle ended as it did, in words.",
        read=_result(lambda r: r.message, "")),
    Tag("BaseStateMachine/CurrentState", V.LocalizedText, "OPC 30050: Aborting, Aborted or Cleared.",
        read=lambda s: ua.LocalizedText(machine_states(s.state)[0])),
    Tag("BaseStateMachine/MachineState/CurrentState", V.LocalizedText, "OPC 30050, within Cleared: "
        "Stopped, Stopping, Clearing or Running (empty outside Cleared).",
        read=lambda s: ua.LocalizedText(machine_states(s.state)[1])),
    Tag("BaseStateMachine/MachineState/ExecuteState/CurrentState", V.LocalizedText, "OPC 30050, within "
        "Running: Resetting, Idle, Starting, Execute, Completing, Complete, Holding, Held, Unholding, "
        "Suspending, Suspended or Unsuspending (empty outside Running).",
        read=lambda s: ua.LocalizedText(machine_states(s.state)[2])),
)


@dataclass(frozen=True)
class MethodSpec:
    """One method: ``path`` under the unit, the PackML command it gives (None: it takes an argument,
    ``argument`` its name and type), what it does."""

    path: str
    doc: str
    command: Command | None = None
    argument: tuple[str, ua.VariantType] | None = None


_BASE, _MACHINE = "BaseStateMachine", "BaseStateMachine/MachineState"
_EXECUTE = "BaseStateMachine/MachineState/ExecuteState"
SET_UNIT_MODE = "SetUnitMode"
SET_PART_ID = "SetPartId"

METHODS: tuple[MethodSpec, ...] = (
    MethodSpec(f"{_BASE}/Abort", "Abort (8): the fault path, from every state but Aborting and Aborted.",
               Command.ABORT),
    MethodSpec(f"{_BASE}/Clear", "Clear (9): recover the arm, Aborted to Stopped.", Command.CLEAR),
    MethodSpec(f"{_MACHINE}/Stop", "Stop (3): stop the scan and the arm, then Stopped.", Command.STOP),
    MethodSpec(f"{_EXECUTE}/Reset", "Reset (1): Stopped or Complete to Idle.", Command.RESET),
    MethodSpec(f"{_EXECUTE}/Start", "Start (2): in Idle, scan the part PackTags/Command/Parameter/PartId.",
               Command.START),
    MethodSpec(f"{_EXECUTE}/Hold", "Hold (4): stop the scan in Execute; Unhold scans the part again.",
               Command.HOLD),
    MethodSpec(f"{_EXECUTE}/Unhold", "Unhold (5): Held to Execute.", Command.UNHOLD),
    MethodSpec(f"{_EXECUTE}/Suspend", "Suspend (6): stop the scan in Execute; Unsuspend scans the part "
               "again.", Command.SUSPEND),
    MethodSpec(f"{_EXECUTE}/Unsuspend", "Unsuspend (7): Suspended to Execute.", Command.UNSUSPEND),
    MethodSpec(SET_UNIT_MODE, "OPC 30050 SetUnitMode: 1 Production or 3 Manual, in Stopped, Idle or "
               "Aborted.", argument=("RequestedMode", V.Int32)),
    MethodSpec(SET_PART_ID, f"The part the next Start scans (1 to {PART_ID_MAX} printable ASCII characters), "
               "as writing PackTags/Command/Parameter/PartId.", argument=("PartId", V.String)),
)

_PACKML_NAMES = frozenset({"BaseStateMachine", "MachineState", "ExecuteState", SET_UNIT_MODE,
                           *(m.path.rsplit("/", 1)[-1] for m in METHODS if m.command is not None)})


@dataclass(frozen=True)
class Namespaces:
    """Namespace indexes: the cell's (NodeIds, its own browse names) and OPC 30050's."""

    cell: int
    packml: int

    def browse_name(self, path: str) -> ua.QualifiedName:
        """The browse name of the node at ``path``: its last part, in OPC 30050's namespace for the
        specification's names, in namespace 0 for ``CurrentState`` (FiniteStateMachineType's), else in
        the cell's."""
        name = path.rsplit("/", 1)[-1]
        if name == "CurrentState":
            return ua.QualifiedName(name, 0)
        return ua.QualifiedName(name, self.packml if name in _PACKML_NAMES else self.cell)

    def node_id(self, path: str) -> ua.NodeId:
        """The NodeId of the node at ``path``: the path with dots, a string in the cell's namespace."""
        return ua.NodeId(ua.String(path.replace("/", ".")), ua.Int16(self.cell))


async def _describe(node: Node, text: str) -> None:
    await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(ua.LocalizedText(text))))


async def build(server: Server, unit_name: str, ns: Namespaces,
                handlers: dict[str, Callable[..., Any]]) -> dict[str, ua.NodeId]:
    """Add the unit's objects, :data:`TAGS` and :data:`METHODS` (``handlers`` by method path) to
    ``server``'s address space; returns each tag's NodeId by path."""
    unit = await server.nodes.objects.add_object(ns.node_id(UNIT_ID), ua.QualifiedName(unit_name, ns.cell))
    await _describe(unit, "A scanning cell on the packing line: a PackML unit (ISA-TR88.00.02, OPC 30050).")
    objects: dict[str, Node] = {"": unit}

    async def parent(path: str) -> Node:
        folder = path.rpartition("/")[0]
        if folder not in objects:
            above = await parent(folder)
            objects[folder] = await above.add_object(ns.node_id(folder), ns.browse_name(folder))
        return objects[folder]

    ids: dict[str, ua.NodeId] = {}
    for tag in TAGS:
        node = await (await parent(tag.path)).add_variable(ns.node_id(tag.path), ns.browse_name(tag.path),
                                                           tag.initial, varianttype=tag.vtype)
        await _describe(node, tag.doc)
        if tag.writable:
            await node.set_writable()
        ids[tag.path] = node.nodeid
    for method in METHODS:
        inputs = [] if method.argument is None else [ua.Argument(
            Name=method.argument[0], DataType=ua.NodeId(ua.Int32(method.argument[1].value)), ValueRank=-1,
            Description=ua.LocalizedText(method.doc))]
        node = await (await parent(method.path)).add_method(
            ns.node_id(method.path), ns.browse_name(method.path), handlers[method.path], inputs, [])
        await _describe(node, method.doc)
    return ids
