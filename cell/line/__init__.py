"""The packing line: PackML state machine and its three ways in (OPC UA, digital I/O, REST)."""
