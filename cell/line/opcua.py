"""The packing line over OPC UA: an asyncua server on the service's event loop, started by ``cell serve``
when the cell file has ``line.opcua`` (:func:`serve_opcua`; :mod:`cell.line.opcua_endpoint` checks its
endpoint first).

Its address space (:mod:`cell.line.opcua_nodes`, documented in ``docs/packml-opcua.md``) offers the line
two ways to drive the cell's PackML state machine (:class:`cell.line.controller.LineController`), as the
REST trigger does:

- PackTags: the PLC writes ``Command/CntrlCmd``, then ``Command/CmdChangeRequest`` true; before the
  write is answered the cell has acted on the command (or refused it) and written ``CmdChangeRequest``
  back to false; ``Status/CommandMessage`` says what was done or why not. ``Command/UnitMode`` with
  ``Command/UnitModeChangeRequest`` changes the unit mode the same way. ``Command/Parameter/PartId`` sets
  the part the next Start scans.
- OPC 30050's methods on the unit, a ``PackMLBaseObjectType`` instance (Start, Stop, Reset, ... of its
  state machines; SetUnitMode): a refused call answers ``Bad_InvalidState`` (not valid in this state) or
  ``Bad_InvalidArgument``, the reason in ``Status/CommandMessage``; SetMachSpeed, SetParameter and
  SetProduct, which the type requires, answer ``Bad_NotSupported``.

A write of the wrong type, of a value out of range (a PartId over 64 characters, a CntrlCmd that is no
command) or with an index range is refused whole (the request's service result is Bad) and changes
nothing; a write of a read-only variable is refused by itself (``Bad_UserAccessDenied``), the request's
other values written. ``Status/CommandMessage`` says why, as it does for a refused method call (it is the
line's message: REST reads it too). Values follow the line: every change the controller reports is
queued and written, in order, by one task; a command's answer waits until its effects are readable. Who
logs in and how is :mod:`cell.line.opcua_security`; how many connections the server keeps, and for how
long one may stay silent, :mod:`cell.line.opcua_connections`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from datetime import UTC
from typing import TYPE_CHECKING, Any, TypeVar

from asyncua import ua
from asyncua.common.callback import CallbackType, ServerItemCallback

from cell.line.config import OPCUAConfig
from cell.line.controller import LineController, LineSnapshot
from cell.line.opcua_connections import GuardedServer, OPCUALimits
from cell.line.opcua_nodes import (
    CMD_CHANGE_REQUEST,
    CNTRL_CMD,
    METHODS,
    PACKML_URI,
    PART_ID,
    SET_PART_ID,
    SET_UNIT_MODE,
    STATE_CURRENT,
    TAGS,
    UNIT_MODE,
    UNIT_MODE_CHANGE_REQUEST,
    MethodSpec,
    Namespaces,
    Tag,
    build,
)
from cell.line.opcua_security import LinePermissions, LineUserManager, caller, ensure_certificate, fingerprint
from cell.line.packml import OFFERED_MODES, Command, UnitMode
from cell.service.keys import KeyRing
from drivers.errors import ConfigError, ServiceError

if TYPE_CHECKING:
    from cell.service.manager import CellService

log = logging.getLogger("cell.line")

S = ua.StatusCodes
STATUS_OF = {"conflict": S.BadInvalidState, "invalid": S.BadInvalidArgument}
"""A refused command's status code by the ``ServiceError`` reason."""
SHUTDOWN_LINGER_S = 0.5
"""How long the server serves on after the line's last change at shutdown [s]: a subscription publishing
at up to this interval hears the Stopped and stop reason 7 before its session closes."""
_TAG = {tag.path: tag for tag in TAGS}
_LINE_TAGS = sorted((tag for tag in TAGS if tag.read is not None),
                    key=lambda tag: tag.path == STATE_CURRENT or "/CurrentState" in tag.path)
"""The tags that follow the line, its state last: a client that sees a new state reads the values that came
with it (the result with Complete, the job id with Execute)."""
_COMMANDS = ", ".join(f"{c.value} {c.label}" for c in Command)
_MODES = ", ".join(f"{m.value} {m.label}" for m in sorted(OFFERED_MODES))
"""The unit modes a client may ask for (Maintenance is a PackML number the cell refuses)."""
MethodResult = ua.StatusCode | ua.CallMethodResult
E = TypeVar("E", Command, UnitMode)


def _status(code: int) -> ua.StatusCode:
    return ua.StatusCode(ua.UInt32(code))


def _source(name: str | None) -> str:
    return f"OPC UA (key {name})"


def _refusal(tag: Tag, item: ua.WriteValue, check_part_id: Callable[[str], str]) -> tuple[str, int] | None:
    """Why a client's write of ``item`` to ``tag`` is refused, with its status code; None: it is not.
    ``check_part_id`` is the line's rule for a part id (``ServiceError`` when it may not be set)."""
    data = item.Value
    if item.IndexRange:
        return "index ranges are not supported", S.BadWriteNotSupported
    if data.StatusCode is not None and not data.StatusCode.is_good():
        return "a value with a Bad status", S.BadWriteNotSupported
    variant = data.Value
    if variant is None or variant.Value is None:
        return f"expects a {tag.vtype.name}, got nothing", S.BadTypeMismatch
    if variant.VariantType != tag.vtype or variant.is_array:
        got = f"an array of {variant.VariantType.name}" if variant.is_array else variant.VariantType.name
        return f"expects a {tag.vtype.name}, got {got}", S.BadTypeMismatch
    value = variant.Value
    if tag.path == CNTRL_CMD and value != 0 and value not in set(Command):
        return f"{value} is no command (0 none, {_COMMANDS})", S.BadOutOfRange
    if tag.path == UNIT_MODE and value != 0 and value not in set(UnitMode):
        return f"{value} is no unit mode (0 none, {_MODES})", S.BadOutOfRange
    if tag.path == PART_ID:
        try:
            check_part_id(value)
        except ServiceError as exc:
            return str(exc), S.BadOutOfRange
    return None


def _mismatch(name: str, expects: str, arg: ua.Variant) -> tuple[str, MethodResult]:
    """The refusal of argument ``name`` given ``arg`` where it ``expects`` another type."""
    got = f"an array of {arg.VariantType.name}" if arg.is_array else arg.VariantType.name
    return (f"{name} expects {expects}, got {got}",
            ua.CallMethodResult(StatusCode=_status(S.BadInvalidArgument),
                                InputArgumentResults=[_status(S.BadTypeMismatch)]))


def _argument_refusal(spec: MethodSpec, args: tuple[ua.Variant, ...]) -> tuple[str, MethodResult] | None:
    """Why a call of ``spec`` with ``args`` is refused before it reaches the line, with its answer; None:
    it is not. Start's ``Parameter`` may be left out or null, or be an empty array of
    ``PackMLDescriptorDataType``: another type is a type mismatch, a descriptor is out of range."""
    if spec.parameters and args:
        if len(args) > 1:
            return f"it takes one argument, Parameter, got {len(args)}", _status(S.BadTooManyArguments)
        (arg,) = args
        if arg.VariantType == ua.VariantType.Null:
            return None
        descriptor = ua.PackMLDescriptorDataType  # type: ignore[attr-defined]  # made by the nodeset's import
        if arg.VariantType != ua.VariantType.ExtensionObject or not arg.is_array or \
                not all(isinstance(value, descriptor) for value in arg.Value or ()):
            return _mismatch("Parameter", "an array of PackMLDescriptorDataType", arg)
        if arg.Value:
            return ("Parameter must be empty: the cell's scans take no parameter (SetPartId sets the part)",
                    ua.CallMethodResult(StatusCode=_status(S.BadInvalidArgument),
                                        InputArgumentResults=[_status(S.BadOutOfRange)]))
        return None
    takes = "no argument" if spec.argument is None else \
        f"one argument, {spec.argument[1].name} {spec.argument[0]}"
    if len(args) > (spec.argument is not None):
        return f"it takes {takes}, got {len(args)}", _status(S.BadTooManyArguments)
    if spec.argument is None:
        return None
    if not args:
        return f"it takes {takes}, got none", _status(S.BadArgumentsMissing)
    (arg,) = args
    if arg.VariantType != spec.argument[1] or arg.is_array:
        return _mismatch(spec.argument[0], f"a {spec.argument[1].name}", arg)
    return None


class LineOPCUA:
    """The OPC UA server of one cell's line (see the module docstring)."""

    def __init__(self, service: CellService, line: LineController, config: OPCUAConfig,
                 keys: KeyRing, limits: OPCUALimits) -> None:
        """``limits`` guard the server's connections (:mod:`cell.line.opcua_connections`)."""
        self._service = service
        self._line = line
        self._config = config
        self._keys = keys
        self._server = GuardedServer(limits, user_manager=LineUserManager(keys))
        self._ids: dict[str, ua.NodeId] = {}
        self._ns = Namespaces(0, 0)  # the server's, once start() registered them
        self._tags: dict[ua.NodeId, Tag] = {}
        self._snapshots: asyncio.Queue[LineSnapshot] = asyncio.Queue()
        self._published: dict[str, Any] = {}
        self._publisher: asyncio.Task[None] | None = None

    @property
    def application_uri(self) -> str:
        """The server's OPC UA application URI (also in its certificate)."""
        return f"urn:cell:{self._service.name}"

    async def start(self) -> None:
        """Build the address space and listen; ``ConfigError`` in one line when the endpoint cannot be
        bound or the certificate cannot be made."""
        server, config = self._server, self._config
        await server.init()
        server.set_endpoint(config.endpoint)
        server.set_server_name(f"cell {self._service.name}")
        await server.set_application_uri(self.application_uri)
        if config.security == "sign-and-encrypt":
            cert, key = await asyncio.to_thread(ensure_certificate, self._service.data_dir / "opcua",
                                                self.application_uri, config.host)
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
            policies = [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt]
            log.info("OPC UA: server certificate %s, SHA-256 %s", cert, fingerprint(cert))
        else:
            policies = [ua.SecurityPolicyType.NoSecurity]
        server.set_security_policy(policies, permission_ruleset=LinePermissions(self._keys))
        server.set_identity_tokens([ua.UserNameIdentityToken])
        self._ns = Namespaces(await server.register_namespace(config.namespace),
                              await server.register_namespace(PACKML_URI))
        handlers = {method.path: self._handler(method.path) for method in METHODS}
        self._ids = await build(server, self._service.name, self._ns, handlers)
        self._tags = {self._ids[tag.path]: tag for tag in TAGS}
        server.subscribe_server_callback(CallbackType.PreWrite, self._pre_write)
        server.subscribe_server_callback(CallbackType.PostWrite, self._post_write)
        self._publisher = asyncio.create_task(self._publish_all(), name="OPC UA values")
        self._line.subscribe(self._heard)
        self._heard(self._line.snapshot())
        await self.settle()
        try:
            await server.start()
        except OSError as exc:
            raise ConfigError(f"cannot listen on {config.endpoint}: {exc.strerror or exc}",
                              field="line.opcua.endpoint") from None
        log.info("OPC UA: listening on %s (security %s)", config.endpoint, config.security)

    async def stop(self) -> None:
        """Write what the line reported last (the service's shutdown), let the subscriptions publish it
        (``SHUTDOWN_LINGER_S``), then close the sessions and stop listening."""
        await self.settle()
        await asyncio.sleep(SHUTDOWN_LINGER_S)
        publisher, self._publisher = self._publisher, None
        await self._server.stop()
        if publisher is not None:
            publisher.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await publisher

    async def settle(self) -> None:
        """Wait until every change the line reported so far is written into the address space."""
        await self._snapshots.join()

    # ------------------------------------------------------------------ values

    def _heard(self, snapshot: LineSnapshot) -> None:
        if self._publisher is not None:
            self._snapshots.put_nowait(snapshot)

    async def _publish_all(self) -> None:
        while True:
            snapshot = await self._snapshots.get()
            try:
                await self._publish(snapshot)
            except Exception:  # one failed write must not leave every later change unpublished
                log.exception("OPC UA: the line's values were not written")
            finally:
                self._snapshots.task_done()

    async def _publish(self, snapshot: LineSnapshot) -> None:
        for tag in _LINE_TAGS:
            await self._set(tag.path, tag.value(snapshot, self._ns))

    async def _set(self, path: str, value: Any) -> None:
        """Write a value the server owns (unchanged values are not written again)."""
        if self._published.get(path) != value:
            self._published[path] = value
            await self._write(path, value)

    async def _write(self, path: str, value: Any) -> None:
        now = ua.DateTime.now(UTC)
        await self._server.write_attribute_value(self._ids[path], ua.DataValue(
            ua.Variant(value, _TAG[path].vtype), SourceTimestamp=now, ServerTimestamp=now))

    async def _say(self, text: str) -> None:
        """What this server refused itself, as the line's message (``Status/CommandMessage``, REST's
        ``message``), once it is readable."""
        log.info("OPC UA: %s", text)
        self._line.say(text)
        await self.settle()

    def _read(self, path: str) -> Any:
        value = self._server.read_attribute_value(self._ids[path]).Value
        return None if value is None else value.Value

    # ------------------------------------------------------------------ writes

    async def _pre_write(self, event: ServerItemCallback, _: Any) -> None:
        """Refuse a client's whole write request when one of its values may not be written."""
        if not event.is_external:
            return
        for item in event.request_params.NodesToWrite:
            tag = self._tags.get(item.NodeId)
            if tag is None or not tag.writable or item.AttributeId != ua.AttributeIds.Value:
                continue  # asyncua refuses what is not writable (_post_write says so)
            refused = _refusal(tag, item, self._line.check_part_id)
            if refused is not None:
                why, code = refused
                await self._say(f"refused a write of {tag.path.rsplit('/', 1)[-1]} from "
                                f"{_source(event.user.name)}: {why}")
                raise ua.UaStatusCodeError(code)

    async def _post_write(self, event: ServerItemCallback, _: Any) -> None:
        """Act on what a client wrote: the part id, the command and mode handshakes."""
        if not event.is_external:
            return
        source = _source(event.user.name)
        for item, status in zip(event.request_params.NodesToWrite, event.response_params, strict=True):
            tag = self._tags.get(item.NodeId)
            if tag is None:
                continue
            if not status.is_good():  # asyncua refused it, the request's other values aside
                why = "only its value may be written" if tag.writable else "read only"
                await self._say(f"refused a write of {tag.path.rsplit('/', 1)[-1]} from {source}: {why}")
                continue
            value = item.Value.Value.Value
            if tag.path == PART_ID:
                self._line.set_part_id(value)
            elif tag.path == CMD_CHANGE_REQUEST and value:
                await self._command(self._read(CNTRL_CMD), source)
                await self._write(CMD_CHANGE_REQUEST, False)
            elif tag.path == UNIT_MODE_CHANGE_REQUEST and value:
                await self._mode(self._read(UNIT_MODE), source)
                await self._write(UNIT_MODE_CHANGE_REQUEST, False)
        await self.settle()

    # ------------------------------------------------------------------ commands

    async def _command(self, number: int, source: str) -> ua.StatusCode:
        """Give the line PackML command ``number``; its status code once its effects are readable."""
        return await self._act(Command, number, lambda command: self._line.command(command, source),
                               f"refused CntrlCmd {number} from {source}: no command; one of {_COMMANDS}")

    async def _mode(self, number: int, source: str) -> ua.StatusCode:
        """Switch the line to unit mode ``number``; its status code."""
        return await self._act(UnitMode, number, lambda mode: self._line.set_mode(mode, source),
                               f"refused unit mode {number} from {source}: one of {_MODES}")

    async def _act(self, kind: Callable[[int], E], number: int, act: Callable[[E], Awaitable[str]],
                   unknown: str) -> ua.StatusCode:
        """``act`` on ``number`` as a member of ``kind`` (``unknown`` said when it is none); the controller
        says what it did, or why not, in the snapshot's message. The status code once its effects are
        readable."""
        try:
            member = kind(number)
        except ValueError:
            await self._say(unknown)
            return _status(S.BadInvalidArgument)
        try:
            await act(member)
        except ServiceError as exc:
            await self.settle()
            return _status(STATUS_OF.get(exc.reason, S.BadInvalidState))
        await self.settle()
        return _status(S.Good)

    async def _part_id(self, part_id: str, source: str) -> MethodResult:
        try:
            self._line.set_part_id(part_id)
        except ServiceError as exc:
            await self._say(f"refused part id from {source}: {exc}")
            return ua.CallMethodResult(StatusCode=_status(S.BadInvalidArgument),
                                       InputArgumentResults=[_status(S.BadOutOfRange)])
        await self.settle()
        return _status(S.Good)

    def _handler(self, path: str) -> Callable[..., Awaitable[MethodResult]]:
        """The handler of method ``path`` (asyncua calls it with the object's NodeId and the arguments)."""
        spec = next(m for m in METHODS if m.path == path)

        async def call(_: ua.NodeId, *args: ua.Variant) -> MethodResult:
            source, name = _source(caller.get()), path.rsplit("/", 1)[-1]
            if spec.refusal is not None:
                await self._say(f"refused a call of {name} from {source}: {spec.refusal}")
                return _status(S.BadNotSupported)
            refused = _argument_refusal(spec, args)
            if refused is not None:
                why, result = refused
                await self._say(f"refused a call of {name} from {source}: {why}")
                return result
            if spec.command is not None:
                return await self._command(int(spec.command), source)
            if path == SET_UNIT_MODE:
                return await self._mode(args[0].Value, source)
            assert path == SET_PART_ID
            # a null String carries no part id: refused as an empty one
            return await self._part_id(args[0].Value or "", source)

        return call


@contextlib.asynccontextmanager
async def serve_opcua(service: CellService, line: LineController, config: OPCUAConfig,
                      keys: KeyRing, limits: OPCUALimits) -> AsyncIterator[LineOPCUA]:
    """The OPC UA server ``config`` of the cell's ``line`` while the context runs; ``keys`` authenticates
    its users and is kept current by the caller; ``limits`` guard its connections."""
    server = LineOPCUA(service, line, config, keys, limits)
    try:
        await server.start()
        yield server
    finally:
        await server.stop()
