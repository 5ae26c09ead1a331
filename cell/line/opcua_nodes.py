"""The cell's OPC UA address space: what each node is, its type, who may write it, and its value.

``Objects/<cell name>`` (NodeId ``s=Unit``) is an instance of OPC 30050's ``PackMLBaseObjectType``
(OPC 30050 v1.01, its nodeset ``Opc.Ua.PackML.NodeSet2.xml`` shipped next to this module and imported at
start: :data:`NODESET`), made by asyncua's instantiation of the type, so that a client browsing by type
finds the standard's typed members:

- ``Status`` (``PackMLStatusObjectType``): ``UnitModeCurrent``, ``UnitSupportedModes``, ``MachSpeed``,
  ``CurMachSpeed``, ``EquipmentBlocked``, ``EquipmentStarved`` (its mandatory members).
- ``Admin`` (``PackMLAdminObjectType``): the optional ``ProdProcessedCount`` and ``ProdDefectiveCount``
  (one ``PackMLCountDataType`` each), added by the cell.
- ``BaseStateMachine`` (``PackMLBaseStateMachineType``; Abort, Clear), its ``MachineState``
  (``PackMLMachineStateMachineType``; Stop, Reset) and that one's ``ExecuteState``
  (``PackMLExecuteStateMachineType``; Reset, Start, Hold, Unhold, Suspend, Unsuspend), each with its
  ``CurrentState`` and ``CurrentState/Id`` (the state's NodeId in the nodeset), and its
  ``AvailableStates`` and ``AvailableTransitions`` (the NodeIds of its type's states and transitions in
  the nodeset, written once); the methods are the types' optional members, added by the cell.
- The type's methods: ``SetUnitMode(Int32 RequestedMode)``; ``SetMachSpeed``, ``SetParameter`` and
  ``SetProduct`` are there (the type requires them) and answer ``Bad_NotSupported``.

The typed members' NodeIds are the ones asyncua gives an instance's members: the unit's and the browse
path, with dots (``s=Unit.Status.UnitModeCurrent``); their browse names are OPC 30050's (the PackML
namespace ``http://opcfoundation.org/UA/PackML/``; ``CurrentState`` and ``Id`` namespace 0's).

The cell's own nodes, in the cell's namespace (``line.opcua.namespace``) with the path with dots as
NodeId (``s=PackTags.Command.CntrlCmd``), untyped (``BaseObjectType``):

- ``PackTags/`` the classic PackML tags (ISA-TR88.00.02) OPC 30050 has no member for or gives another
  type: ``Command/`` the CntrlCmd and UnitMode handshakes and the part id the PLC writes, ``Status/``
  (the Int32 StateCurrent, ...), ``Admin/`` (the stop reason, ...), and the cell's scan ``Result/``
  (:data:`TAGS`; no MachSpeed, no StateRequested or ChangeInProcess tags: ``docs/packml-opcua.md``
  lists what is not offered).
- ``SetPartId(String PartId)`` on the unit (OPC 30050's ``SetParameter`` carries numbers only)
  (:data:`METHODS`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.instantiate_util import instantiate

from cell.line.config import PART_ID_MAX
from cell.line.controller import LineSnapshot
from cell.line.packml import Command, State
from cell.line.result import CycleResult

PACKML_URI = "http://opcfoundation.org/UA/PackML/"
"""OPC 30050's namespace: its types, and the browse names of its members."""
NODESET = Path(__file__).with_name("Opc.Ua.PackML.NodeSet2.xml")
"""OPC 30050 v1.01's nodeset (OPC Foundation, MIT licence in its header; it requires namespace 0 only),
from github.com/OPCFoundation/UA-Nodeset ``PackML/``."""
UNIT_ID = "Unit"
"""The NodeId (string, in the cell's namespace) of the cell's object under ``Objects``."""
BASE_OBJECT_TYPE = 6
"""``PackMLBaseObjectType``'s NodeId (numeric, in OPC 30050's namespace): the unit's type."""
COUNT_DATA_TYPE = 14
"""``PackMLCountDataType``'s NodeId: the Admin counters' DataType."""
DESCRIPTOR_DATA_TYPE = 16
"""``PackMLDescriptorDataType``'s NodeId: the type of Start's ``Parameter`` argument."""
MODE_ENUM = 11
"""``ProductionMaintenanceModeEnum``'s NodeId: the unit modes (1 Produce, 2 Maintenance, 3 Manual), and
the DataType of ``Status/UnitModeCurrent`` (the type declares the abstract Enumeration)."""
MACHINE_TYPES = {"BaseStateMachine": 3, "BaseStateMachine/MachineState": 2,
                 "BaseStateMachine/MachineState/ExecuteState": 1}
"""The unit's state machines (path) and their types' NodeIds (``PackMLBaseStateMachineType``,
``PackMLMachineStateMachineType``, ``PackMLExecuteStateMachineType``)."""
STATE_TYPES = frozenset({ua.NodeId(ua.Int32(ua.ObjectIds.StateType)),
                         ua.NodeId(ua.Int32(ua.ObjectIds.InitialStateType))})
"""The type definitions of a state machine type's state objects (OPC UA Part 16)."""
TRANSITION_TYPE = ua.NodeId(ua.Int32(ua.ObjectIds.TransitionType))
"""The type definition of its transition objects."""
NO_SPEED = ua.Range(Low=0.0, High=0.0)
"""``Status/MachSpeed``'s and ``CurMachSpeed``'s EURange (AnalogItemType's mandatory property): the cell
has no machine speed, its speeds are always 0."""
STATE_IDS = {"Cleared": 71, "Aborting": 61, "Aborted": 62, "Stopped": 53, "Stopping": 54, "Clearing": 55,
             "Running": 75, "Resetting": 27, "Idle": 28, "Starting": 29, "Suspending": 30, "Suspended": 31,
             "Unsuspending": 32, "Holding": 33, "Held": 34, "Unholding": 35, "Execute": 36,
             "Completing": 37, "Complete": 38}
"""The NodeId (numeric, in OPC 30050's namespace) of each state object of its state machine types
(``PackML.NodeIds.csv``): a ``CurrentState/Id``'s value."""
TYPED = frozenset({"Status", "Admin", "BaseStateMachine", "SetUnitMode", "SetMachSpeed", "SetParameter",
                   "SetProduct"})
"""The unit's members that are OPC 30050's (the first part of their path)."""
PIECE = ua.EUInformation(NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
                         UnitId=(ord("H") << 16) | (ord("8") << 8) | ord("7"),
                         DisplayName=ua.LocalizedText("pcs"), Description=ua.LocalizedText("piece"))
"""The Admin counters' unit: UNECE H87, piece (OPC UA Part 8's UnitId of a three-letter code)."""
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


def _count(read: Callable[[LineSnapshot], int]) -> Reader:
    """An Admin counter's value: one ``PackMLCountDataType`` (a class asyncua makes from the nodeset when
    it is imported), of every part, its count kept across restarts (so Count and AccCount are equal)."""

    def value(s: LineSnapshot) -> list[Any]:
        count = read(s)
        return [ua.PackMLCountDataType(ID=0, Name="parts", Unit=PIECE, Count=count,  # type: ignore[attr-defined]
                                       AccCount=count)]

    return value


@dataclass(frozen=True)
class Tag:
    """One variable: ``path`` under the unit (``/``-separated), its type, what it means (the node's
    Description), whether a client may write it, and ``read``, its value from the line's snapshot (None:
    the PLC's own register, or a node the server sets by itself). A NodeId tag reads the numeric id of a
    node in OPC 30050's namespace (0: the null NodeId). ``datatype``: the OPC 30050 DataType (numeric id)
    of an optional member of the type the cell adds, whose value is an array of it."""

    path: str
    vtype: ua.VariantType
    doc: str
    writable: bool = False
    read: Reader | None = None
    datatype: int | None = None

    @property
    def initial(self) -> Any:
        """The value before the line's first snapshot is written: zero, false or empty."""
        return {V.Int32: 0, V.Boolean: False, V.String: "", V.Double: 0.0, V.Float: 0.0,
                V.NodeId: ua.NodeId(), V.ExtensionObject: [],
                V.LocalizedText: ua.LocalizedText("")}[self.vtype]

    def value(self, snapshot: LineSnapshot, ns: Namespaces) -> Any:
        """The tag's value in ``snapshot`` (``read`` must be set), a NodeId made in OPC 30050's namespace."""
        assert self.read is not None
        value = self.read(snapshot)
        if self.vtype is V.NodeId:
            return ns.packml_id(value) if value else ua.NodeId()
        return value


def _current_state(level: int, machine: str, states: str) -> tuple[Tag, Tag]:
    """``CurrentState`` and its ``Id`` of the state machine at ``machine``, ``level`` deep (0 the base
    state machine: :func:`machine_states`), whose states are ``states``."""
    return (Tag(f"{machine}/CurrentState", V.LocalizedText, f"OPC 30050: {states}.",
                read=lambda s: ua.LocalizedText(machine_states(s.state)[level])),
            Tag(f"{machine}/CurrentState/Id", V.NodeId, "The current state's object in OPC 30050's nodeset "
                "(null when the state machine is not active).",
                read=lambda s: STATE_IDS.get(machine_states(s.state)[level], 0)))


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
    Tag("PackTags/Status/JobId", V.String,
        "The scan job of the current cycle, from its submission until Reset (empty before it and after).",
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
    Tag("Status/UnitModeCurrent", V.Int32, "The unit mode (ProductionMaintenanceModeEnum: 1 Produce, the "
        "line starts scans; 3 Manual, the operator's).", read=lambda s: int(s.mode)),
    Tag("Status/UnitSupportedModes", V.NodeId, "The DataType whose values are the unit modes: "
        "ProductionMaintenanceModeEnum (the cell offers 1 Produce and 3 Manual).", read=lambda s: MODE_ENUM),
    Tag("Status/MachSpeed", V.Float, "The cell has no machine speed: 0.", read=lambda s: 0.0),
    Tag("Status/CurMachSpeed", V.Float, "The cell has no machine speed: 0.", read=lambda s: 0.0),
    Tag("Status/EquipmentBlocked", V.Boolean, "Always false: the cell is not blocked by the line "
        "downstream (it holds a result in Complete until the PLC resets).", read=lambda s: False),
    Tag("Status/EquipmentStarved", V.Boolean, "Always false: the cell scans the part it is given.",
        read=lambda s: False),
    Tag("Admin/ProdProcessedCount", V.ExtensionObject, "Parts processed (each cycle that reached Complete), "
        "kept across restarts: one PackMLCountDataType, Count and AccCount equal.",
        read=_count(lambda s: s.processed), datatype=COUNT_DATA_TYPE),
    Tag("Admin/ProdDefectiveCount", V.ExtensionObject, "Of those, parts that fit no container or could not "
        "be scanned: one PackMLCountDataType, Count and AccCount equal.",
        read=_count(lambda s: s.defective), datatype=COUNT_DATA_TYPE),
    *_current_state(0, "BaseStateMachine", "Aborting, Aborted or Cleared"),
    *_current_state(1, "BaseStateMachine/MachineState", "within Cleared: Stopped, Stopping, Clearing or "
                    "Running (empty outside Cleared)"),
    *_current_state(2, "BaseStateMachine/MachineState/ExecuteState", "within Running: Resetting, Idle, "
                    "Starting, Execute, Completing, Complete, Holding, Held, Unholding, Suspending, "
                    "Suspended or Unsuspending (empty outside Running)"),
)


@dataclass(frozen=True)
class MethodSpec:
    """One method: ``path`` under the unit, what it does, and either the PackML command it gives, or
    ``argument`` (its name and type), or ``refusal``: why every call is refused (a method OPC 30050's type
    requires and the cell does not offer, answered ``Bad_NotSupported``). ``parameters``: it declares
    OPC 30050's ``Parameter`` argument (Start's: an array of ``PackMLDescriptorDataType``), which a call
    may leave out or give empty, the cell's scans having no parameter."""

    path: str
    doc: str
    command: Command | None = None
    argument: tuple[str, ua.VariantType] | None = None
    refusal: str | None = None
    parameters: bool = False


_BASE, _MACHINE = "BaseStateMachine", "BaseStateMachine/MachineState"
_EXECUTE = "BaseStateMachine/MachineState/ExecuteState"
SET_UNIT_MODE = "SetUnitMode"
SET_PART_ID = "SetPartId"

METHODS: tuple[MethodSpec, ...] = (
    MethodSpec(f"{_BASE}/Abort", "Abort (8): the fault path, from every state but Aborting and Aborted.",
               Command.ABORT),
    MethodSpec(f"{_BASE}/Clear", "Clear (9): recover the arm, Aborted to Stopped.", Command.CLEAR),
    MethodSpec(f"{_MACHINE}/Stop", "Stop (3): stop the scan and the arm, then Stopped.", Command.STOP),
    MethodSpec(f"{_MACHINE}/Reset", "Reset (1): Stopped to Idle (OPC 30050's StoppedToRunning; "
               "ExecuteState's Reset does the same, and Complete to Idle).", Command.RESET),
    MethodSpec(f"{_EXECUTE}/Reset", "Reset (1): Stopped or Complete to Idle.", Command.RESET),
    MethodSpec(f"{_EXECUTE}/Start", "Start (2): in Idle, scan the part PackTags/Command/Parameter/PartId "
               "(Parameter: none or empty).", Command.START, parameters=True),
    MethodSpec(f"{_EXECUTE}/Hold", "Hold (4): stop the scan in Execute; Unhold scans the part again.",
               Command.HOLD),
    MethodSpec(f"{_EXECUTE}/Unhold", "Unhold (5): Held to Execute.", Command.UNHOLD),
    MethodSpec(f"{_EXECUTE}/Suspend", "Suspend (6): stop the scan in Execute; Unsuspend scans the part "
               "again.", Command.SUSPEND),
    MethodSpec(f"{_EXECUTE}/Unsuspend", "Unsuspend (7): Suspended to Execute.", Command.UNSUSPEND),
    MethodSpec(SET_UNIT_MODE, "OPC 30050 SetUnitMode: 1 Produce or 3 Manual, in Stopped, Idle or "
               "Aborted.", argument=("RequestedMode", V.Int32)),
    MethodSpec("SetMachSpeed", "Not offered: the cell has no machine speed.",
               refusal="the cell has no machine speed"),
    MethodSpec("SetParameter", "Not offered: the cell's scans take no numeric parameter (SetPartId sets the "
               "part).", refusal="the cell's scans take no numeric parameter; SetPartId sets the part"),
    MethodSpec("SetProduct", "Not offered: the cell has no products (SetPartId sets the part).",
               refusal="the cell has no products; SetPartId sets the part"),
    MethodSpec(SET_PART_ID, f"The part the next Start scans (1 to {PART_ID_MAX} printable ASCII characters), "
               "as writing PackTags/Command/Parameter/PartId.", argument=("PartId", V.String)),
)


@dataclass(frozen=True)
class Namespaces:
    """Namespace indexes: the cell's (NodeIds, its own browse names) and OPC 30050's."""

    cell: int
    packml: int

    def browse_name(self, path: str) -> ua.QualifiedName:
        """The browse name of the node at ``path``: its last part, in OPC 30050's namespace for the
        members of its type (:data:`TYPED`), else in the cell's."""
        return ua.QualifiedName(path.rsplit("/", 1)[-1],
                                self.packml if path.split("/", 1)[0] in TYPED else self.cell)

    def packml_id(self, number: int) -> ua.NodeId:
        """The NodeId of OPC 30050's node ``number`` (its nodeset's numeric ids)."""
        return ua.NodeId(ua.Int32(number), ua.Int16(self.packml))

    def node_id(self, path: str) -> ua.NodeId:
        """The NodeId of the node at ``path``, a string in the cell's namespace: the path with dots, after
        ``Unit.`` for a member of OPC 30050's type (as asyncua's instantiation names them)."""
        typed = path.split("/", 1)[0] in TYPED
        return ua.NodeId(ua.String((f"{UNIT_ID}.{path}" if typed else path).replace("/", ".")),
                         ua.Int16(self.cell))


async def _describe(node: Node, text: str) -> None:
    await node.write_attribute(ua.AttributeIds.Description, ua.DataValue(ua.Variant(ua.LocalizedText(text))))


def _inputs(method: MethodSpec, ns: Namespaces) -> list[ua.Argument]:
    """The InputArguments of a method the cell adds."""
    if method.parameters:
        return [ua.Argument(Name="Parameter", DataType=ns.packml_id(DESCRIPTOR_DATA_TYPE),
                            ValueRank=ua.ValueRank.OneDimension, ArrayDimensions=[0],
                            Description=ua.LocalizedText("None or empty: the cell's scans take no parameter "
                                                         "(SetPartId sets the part)."))]
    if method.argument is None:
        return []
    return [ua.Argument(Name=method.argument[0], DataType=ua.NodeId(ua.Int32(method.argument[1].value)),
                        ValueRank=-1, Description=ua.LocalizedText(method.doc))]


async def _state_machines(server: Server, ns: Namespaces) -> None:
    """Write each state machine's ``AvailableStates`` and ``AvailableTransitions``: the NodeIds of its
    type's state and transition objects in OPC 30050's nodeset (its type's components, so that they
    follow the nodeset), which a client reads to learn the states and transitions the machine has."""
    for machine, type_id in MACHINE_TYPES.items():
        states: list[ua.NodeId] = []
        transitions: list[ua.NodeId] = []
        for child in await server.get_node(ns.packml_id(type_id)).get_children(
                refs=ua.ObjectIds.HasComponent, nodeclassmask=ua.NodeClass.Object):
            kind = await child.read_type_definition()
            if kind in STATE_TYPES:
                states.append(child.nodeid)
            elif kind == TRANSITION_TYPE:
                transitions.append(child.nodeid)
        for name, ids in (("AvailableStates", states), ("AvailableTransitions", transitions)):
            await server.get_node(ns.node_id(f"{machine}/{name}")).write_value(
                ua.Variant(sorted(ids, key=lambda i: i.Identifier), V.NodeId))


async def build(server: Server, unit_name: str, ns: Namespaces,
                handlers: dict[str, Callable[..., Any]]) -> dict[str, ua.NodeId]:
    """Import OPC 30050's nodeset (its namespace ``ns.packml``, registered already), add the unit as an
    instance of ``PackMLBaseObjectType`` with its mandatory members, the optional ones of :data:`TAGS` and
    :data:`METHODS`, and the cell's own objects, tags and methods to ``server``'s address space; link each
    method to its handler (``handlers`` by method path). Returns each tag's NodeId by path."""
    await server.import_xml(str(NODESET))
    made = await instantiate(server.nodes.objects, server.get_node(ns.packml_id(BASE_OBJECT_TYPE)),
                             ns.node_id(UNIT_ID), ua.QualifiedName(unit_name, ns.cell),
                             instantiate_optional=False)
    typed = {node.nodeid: node for node in made}
    unit = typed[ns.node_id(UNIT_ID)]
    await _describe(unit, "A scanning cell on the packing line: a PackML unit (ISA-TR88.00.02, OPC 30050).")
    await _state_machines(server, ns)
    for speed in ("Status/MachSpeed", "Status/CurMachSpeed"):
        await server.get_node(ns.node_id(f"{speed}/EURange")).write_value(ua.Variant(NO_SPEED))
    await server.get_node(ns.node_id("Status/UnitModeCurrent")).write_attribute(
        ua.AttributeIds.DataType, ua.DataValue(ua.Variant(ns.packml_id(MODE_ENUM))))
    objects: dict[str, Node] = {"": unit}

    async def parent(path: str) -> Node:
        folder = path.rpartition("/")[0]
        if folder not in objects:
            node = typed.get(ns.node_id(folder))
            if node is None:
                node = await (await parent(folder)).add_object(ns.node_id(folder), ns.browse_name(folder))
            objects[folder] = node
        return objects[folder]

    ids: dict[str, ua.NodeId] = {}
    for tag in TAGS:
        node = typed.get(ns.node_id(tag.path))
        if node is None:
            datatype = None if tag.datatype is None else ns.packml_id(tag.datatype)
            node = await (await parent(tag.path)).add_variable(ns.node_id(tag.path), ns.browse_name(tag.path),
                                                               tag.initial, tag.vtype, datatype)
            if datatype is not None:
                await node.write_value_rank(ua.ValueRank.OneDimension)
        await _describe(node, tag.doc)
        if tag.writable:
            await node.set_writable()
        ids[tag.path] = node.nodeid
    for method in METHODS:
        node = typed.get(ns.node_id(method.path))
        if node is None:
            node = await (await parent(method.path)).add_method(
                ns.node_id(method.path), ns.browse_name(method.path), handlers[method.path],
                _inputs(method, ns), [])
        else:
            server.link_method(node, handlers[method.path])
        await _describe(node, method.doc)
    return ids
