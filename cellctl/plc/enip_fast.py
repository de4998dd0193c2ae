"""The EtherNet/IP fast path: Read Tag and Write Tag of the cell's own tags, parsed with ``struct``.

cpppo parses every frame in pure Python: about 19,000 function calls and 20-35 ms per frame on the
2-core machine at load 6-9 (cProfile of a ``CC_EchoSeq`` read, 2026-12-06: 25 % in the encapsulation
parser, 70 % in ``logix.process``, almost all of it cpppo's state machines). A PLC polling its tags
sends a few frame shapes over and over; :class:`FastPath` answers exactly those, byte for byte as
cpppo does (tests/plc/test_enip_fast.py holds the two together), in about 20 microseconds:

- **SendUnitData** (0x70, connected messaging after a Forward Open: pylogix, a Logix MSG with
  "Connected" ticked) and **SendRRData** (0x6F, unconnected: the CIP request itself or wrapped in an
  Unconnected Send 0x52 routed to backplane port 1 slot 0),
- carrying **Read Tag** (0x4C) of one of our tags (``CC_...``, optionally one element ``[i]`` on,
  DINT, REAL or STRING) or **Write Tag** (0x4D) of one element of a writable DINT tag sent as a DINT.

Everything else is declined (``answer`` returns None) and cpppo answers it, or closes the connection,
as it did before: Register Session, Forward Open/Close, other services, unknown tags, other types,
malformed frames. The fast path is stricter than cpppo, never laxer: it takes a frame only when every
length field agrees with the frame's own, the session handle is the one registered on this TCP
connection and (connected) the connection id one opened on it (cpppo checks neither; they are learnt
from cpppo's own answers, :meth:`FastPath.learn`), and status, options and interface handle are 0.
"""

from __future__ import annotations

import struct

from cellctl.plc.enip_tags import TAG_SPECS, RefusedWrite, TagImage, TagSpec

ENCAPSULATION = struct.Struct("<HHII8sI")
"""Command, length, session handle, status, sender context, options (24 bytes)."""
UNIT_DATA = struct.Struct("<IHHHHIHHH")
"""SendUnitData's interface handle, timeout, item count, the connected address item (0xA1, 4, connection id),
the connected data item (0xB1, length) and the sequence count (22 bytes)."""
RR_DATA = struct.Struct("<IHHHHHH")
"""SendRRData's interface handle, timeout, item count, the null address item (0, 0) and the unconnected
data item (0xB2, length) (16 bytes)."""
REGISTER_SESSION, SEND_RR_DATA, SEND_UNIT_DATA = 0x65, 0x6F, 0x70
READ_TAG, WRITE_TAG, UNCONNECTED_SEND = 0x4C, 0x4D, 0x52
FORWARD_OPEN_REPLIES, FORWARD_CLOSE_REPLY = (0xD4, 0xDB), 0xCE
TYPE_CODES = {"DINT": 0xC4, "REAL": 0xCA, "STRING": 0xD0}
FORMATS = {"DINT": "i", "REAL": "f"}
CONNECTION_MANAGER = bytes([0x02, 0x20, 0x06, 0x24, 0x01])
"""An Unconnected Send's path: 2 words, class 6 (Connection Manager), instance 1."""
BACKPLANE_SLOT_0 = bytes([0x01, 0x00, 0x01, 0x00])
"""An Unconnected Send's route: 1 word, reserved, port 1 (backplane), slot 0 (this controller)."""
REFUSED = bytes([0xFF, 0x01, 0x05, 0x21])
"""General status 0xFF, one extended status word 0x2105: what cpppo answers a write that raises (busy,
read-only), the status a Logix MSG instruction shows in .ERR."""


class FastPath:
    """The fast path for one TCP connection: ``answer(frame)`` or None, ``learn(frame, reply)`` after cpppo."""

    enabled = True
    """False sends every frame to cpppo (to compare the two answers, or to rule the fast path out)."""

    def __init__(self, image: TagImage) -> None:
        self.image = image
        self.session: int | None = None
        self.connections: dict[tuple[int, int, int], int] = {}
        """Forward Open's (connection serial, vendor, originator serial) -> the O->T connection id."""
        self.answered = 0

    # -- what cpppo did -----------------------------------------------------------------------------
    def learn(self, frame: bytes, reply: bytes | None) -> None:
        """Note the session a Register Session opened and the connections a Forward Open/Close changed."""
        if not reply or len(reply) < ENCAPSULATION.size:
            return
        command, _length, session, status, _context, _options = ENCAPSULATION.unpack_from(reply)
        if status:
            return
        if command == REGISTER_SESSION:
            self.session = session
        elif command == SEND_RR_DATA and len(reply) >= 44 and reply[42] == 0:
            service = reply[40]
            if service in FORWARD_OPEN_REPLIES and len(reply) >= 60:
                ot_id, _to_id, serial, vendor, originator = struct.unpack_from("<IIHHI", reply, 44)
                self.connections[(serial, vendor, originator)] = ot_id
            elif service == FORWARD_CLOSE_REPLY and len(reply) >= 52:
                self.connections.pop(struct.unpack_from("<HHI", reply, 44), None)

    # -- frames -------------------------------------------------------------------------------------
    def answer(self, frame: bytes) -> bytes | None:
        """The reply to a frame the fast path takes, or None (cpppo's to answer)."""
        if len(frame) < ENCAPSULATION.size or self.session is None:
            return None
        command, length, session, status, context, options = ENCAPSULATION.unpack_from(frame)
        if length != len(frame) - ENCAPSULATION.size or status or options or session != self.session:
            return None
        if command == SEND_UNIT_DATA:
            reply = self._unit_data(frame)
        elif command == SEND_RR_DATA:
            reply = self._rr_data(frame)
        else:
            return None
        if reply is None:
            return None
        self.answered += 1
        return ENCAPSULATION.pack(command, len(reply), session, 0, context, 0) + reply

    def _unit_data(self, frame: bytes) -> bytes | None:
        at = ENCAPSULATION.size + UNIT_DATA.size
        if len(frame) < at:
            return None
        interface, timeout, items, a_type, a_len, conn, d_type, d_len, seq = UNIT_DATA.unpack_from(
            frame, ENCAPSULATION.size)
        if (interface or items != 2 or a_type != 0xA1 or a_len != 4 or d_type != 0xB1
                or at - 2 + d_len != len(frame) or conn not in self.connections.values()):
            return None
        cip = self._tag_service(frame[at:])
        if cip is None:
            return None
        return UNIT_DATA.pack(0, timeout, 2, 0xA1, 4, conn, 0xB1, len(cip) + 2, seq) + cip

    def _rr_data(self, frame: bytes) -> bytes | None:
        at = ENCAPSULATION.size + RR_DATA.size
        if len(frame) < at:
            return None
        interface, timeout, items, n_type, n_len, d_type, d_len = RR_DATA.unpack_from(frame, ENCAPSULATION.size)
        if interface or items != 2 or n_type or n_len or d_type != 0xB2 or at + d_len != len(frame):
            return None
        request: bytes | None = frame[at:]
        if frame[at : at + 1] == bytes([UNCONNECTED_SEND]):
            request = _unwrap_unconnected_send(frame[at:])
        cip = None if request is None else self._tag_service(request)
        if cip is None:
            return None
        return RR_DATA.pack(0, timeout, 2, 0, 0, 0xB2, len(cip)) + cip

    # -- the CIP request ----------------------------------------------------------------------------
    def _tag_service(self, request: bytes) -> bytes | None:
        """Read Tag / Write Tag of one of our tags: the CIP reply, or None."""
        if len(request) < 2:
            return None
        service, words = request[0], request[1]
        end = 2 + 2 * words
        if end > len(request):
            return None
        target = _tag_path(request[2:end])
        if target is None:
            return None
        spec, element = target
        data = request[end:]
        if service == READ_TAG:
            return self._read(spec, element, data)
        if service == WRITE_TAG:
            return self._write(spec, element, data)
        return None

    def _read(self, spec: TagSpec, element: int, data: bytes) -> bytes | None:
        if len(data) != 2:
            return None
        (count,) = struct.unpack("<H", data)
        if count < 1 or element + count > spec.count:
            return None
        value = self.image.read(spec.name)
        try:
            if spec.cip_type == "STRING":
                text = str(value).encode("ascii")
                payload = struct.pack("<H", len(text)) + text + b"\0" * (len(text) % 2)
            else:
                values = value[element : element + count] if spec.count > 1 else [value]
                payload = struct.pack(f"<{count}{FORMATS[spec.cip_type]}", *values)
        except (struct.error, UnicodeEncodeError, KeyError):
            return None  # not a value this path encodes: cpppo's to answer
        return bytes([READ_TAG | 0x80, 0, 0, 0]) + struct.pack("<H", TYPE_CODES[spec.cip_type]) + payload

    def _write(self, spec: TagSpec, element: int, data: bytes) -> bytes | None:
        if not spec.writable or spec.cip_type != "DINT" or element != 0 or len(data) != 8:
            return None
        cip_type, count, value = struct.unpack("<HHi", data)
        if cip_type != TYPE_CODES["DINT"] or count != 1:
            return None
        try:
            self.image.write(spec.name, value)
        except RefusedWrite:
            return bytes([WRITE_TAG | 0x80, 0]) + REFUSED
        return bytes([WRITE_TAG | 0x80, 0, 0, 0])


def _tag_path(path: bytes) -> tuple[TagSpec, int] | None:
    """A symbolic segment naming one of our tags, then at most one element segment (8 or 16 bit)."""
    if len(path) < 2 or path[0] != 0x91:
        return None
    n = path[1]
    name_end = 2 + n + (n % 2)
    if name_end > len(path) or (n % 2 and path[name_end - 1] != 0):
        return None
    spec = TAG_SPECS.get(path[2 : 2 + n].decode("ascii", "replace"))
    if spec is None:
        return None
    rest = path[name_end:]
    if not rest:
        return spec, 0
    if len(rest) == 2 and rest[0] == 0x28:
        return spec, rest[1]
    if len(rest) == 4 and rest[0] == 0x29 and rest[1] == 0:
        return spec, struct.unpack_from("<H", rest, 2)[0]
    return None


def _unwrap_unconnected_send(request: bytes) -> bytes | None:
    """The request inside an Unconnected Send to the Connection Manager routed to slot 0, or None."""
    if len(request) < 10 or request[1:6] != CONNECTION_MANAGER:
        return None
    (size,) = struct.unpack_from("<H", request, 8)
    end = 10 + size + (size % 2)
    if request[end:] != BACKPLANE_SLOT_0:
        return None
    return request[10 : 10 + size]
