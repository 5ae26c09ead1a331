"""RTDE wire format (protocol version 2) as a UR controller speaks it on port 30004.

Facts from Universal Robots' RTDE guide: every message is ``uint16 size`` (big-endian, header included),
``uint8 type``, payload. Data packages start with the ``uint8`` recipe id; values are big-endian in the
recipe's order. A recipe's variables are named in a comma-separated list; the controller answers with
the comma-separated types (``NOT_FOUND`` for a name it does not know).
"""

from __future__ import annotations

import re
import struct

HEADER = struct.Struct(">HB")

REQUEST_PROTOCOL_VERSION = ord("V")
GET_URCONTROL_VERSION = ord("v")
TEXT_MESSAGE = ord("M")
DATA_PACKAGE = ord("U")
SETUP_OUTPUTS = ord("O")
SETUP_INPUTS = ord("I")
START = ord("S")
PAUSE = ord("P")

# struct codes per RTDE type (big-endian prefix added when packing)
TYPE_CODES: dict[str, str] = {
    "BOOL": "?", "UINT8": "B", "UINT32": "I", "UINT64": "Q", "INT32": "i", "DOUBLE": "d",
    "VECTOR3D": "3d", "VECTOR6D": "6d", "VECTOR6INT32": "6i", "VECTOR6UINT32": "6I",
}

_V6 = "VECTOR6D"
OUTPUT_TYPES: dict[str, str] = {
    "timestamp": "DOUBLE", "target_q": _V6, "target_qd": _V6, "target_qdd": _V6, "target_current": _V6,
    "target_moment": _V6, "actual_q": _V6, "actual_qd": _V6, "actual_current": _V6,
    "actual_current_window": _V6, "actual_current_as_torque": _V6, "joint_control_output": _V6,
    "actual_TCP_pose": _V6, "actual_TCP_speed": _V6, "actual_TCP_force": _V6, "target_TCP_pose": _V6,
    "target_TCP_speed": _V6, "actual_digital_input_bits": "UINT64", "joint_temperatures": _V6,
    "actual_execution_time": "DOUBLE", "robot_mode": "INT32", "joint_mode": "VECTOR6INT32",
    "safety_mode": "INT32", "safety_status": "INT32", "actual_tool_accelerometer": "VECTOR3D",
    "speed_scaling": "DOUBLE", "target_speed_fraction": "DOUBLE", "actual_momentum": "DOUBLE",
    "actual_main_voltage": "DOUBLE", "actual_robot_voltage": "DOUBLE", "actual_robot_current": "DOUBLE",
    "actual_joint_voltage": _V6, "actual_digital_output_bits": "UINT64", "runtime_state": "UINT32",
    "elbow_position": "VECTOR3D", "elbow_velocity": "VECTOR3D", "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32", "analog_io_types": "UINT32", "standard_analog_input0": "DOUBLE",
    "standard_analog_input1": "DOUBLE", "standard_analog_output0": "DOUBLE",
    "standard_analog_output1": "DOUBLE", "io_current": "DOUBLE", "tool_mode": "UINT32",
    "tool_analog_input_types": "UINT32", "tool_analog_input0": "DOUBLE", "tool_analog_input1": "DOUBLE",
    "tool_output_voltage": "INT32", "tool_output_current": "DOUBLE", "tool_temperature": "DOUBLE",
    "tcp_force_scalar": "DOUBLE", "output_bit_registers0_to_31": "UINT32",
    "output_bit_registers32_to_63": "UINT32", "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32", "payload": "DOUBLE", "payload_cog": "VECTOR3D",
    "payload_inertia": _V6, "script_control_line": "UINT32", "ft_raw_wrench": _V6,
    "joint_position_deviation_ratio": "DOUBLE", "collision_detection_ratio": "DOUBLE",
    "time_scale_source": "UINT32",
}

INPUT_TYPES: dict[str, str] = {
    "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": _V6,
}

_REGISTER = re.compile(r"^(input|output)_(int|double|bit)_register_(\d+)$")
_REGISTER_TYPES = {"int": "INT32", "double": "DOUBLE", "bit": "BOOL"}


def variable_type(name: str, direction: str) -> str:
    """The RTDE type of variable ``name`` in an ``"output"`` or ``"input"`` recipe, or ``NOT_FOUND``.

    General-purpose registers: ints and doubles 0..47, bits 64..127. Outputs may also name input
    registers (their current value), as on a real controller.
    """
    m = _REGISTER.match(name)
    if m is not None:
        kind, index = m.group(2), int(m.group(3))
        in_range = 64 <= index <= 127 if kind == "bit" else 0 <= index <= 47
        if not in_range or (direction == "input" and m.group(1) == "output"):
            return "NOT_FOUND"
        return _REGISTER_TYPES[kind]
    table = OUTPUT_TYPES if direction == "output" else INPUT_TYPES
    return table.get(name, "NOT_FOUND")


def recipe_struct(types: list[str]) -> struct.Struct:
    """The big-endian struct that packs one data package's values (after the recipe id)."""
    return struct.Struct(">" + "".join(TYPE_CODES[t] for t in types))


def flatten(values: list[object]) -> list[object]:
    """Vector values spread into the flat sequence ``struct`` packs."""
    flat: list[object] = []
    for v in values:
        if isinstance(v, (list, tuple)):
            flat.extend(v)
        else:
            flat.append(v)
    return flat


def group(types: list[str], flat: tuple[object, ...]) -> list[object]:
    """The inverse of :func:`flatten`: one value (or list for vectors) per recipe variable."""
    out: list[object] = []
    i = 0
    for t in types:
        code = TYPE_CODES[t]
        n = int(code[0]) if code[0].isdigit() else 1
        out.append(list(flat[i:i + n]) if n > 1 else flat[i])
        i += n
    return out


def message(kind: int, payload: bytes = b"") -> bytes:
    """One RTDE message: header and payload."""
    return HEADER.pack(HEADER.size + len(payload), kind) + payload
