"""ASCII protocol between the PC and the hexapod control box (section 4.5.1).

One command per line, one reply line per command. Lines are 7-bit ASCII ending in
LF (``\\n``; a CR before it is ignored). Fields are separated by single spaces.
Every line the driver sends and every reply the box sends ends with an NMEA-style
checksum ``*HH``: two upper-case hex digits of the XOR of all bytes before the ``*``.
The box also accepts commands without a checksum (typed at a terminal, or in a
command file); a command with a wrong checksum is refused with ``ERR 5``.

Commands (legs 1..6; counts are encoder driving counts, 0 at stroke zero, up to
``MAX`` = stroke x counts per mm)::

    ID?                      -> OK ID <box-name> <firmware> <MAX>
    MOVE <leg> <counts>      -> OK MOVE <leg> <counts>      one leg, full speed
    MOVEALL <c1> ... <c6>    -> OK MOVEALL <c1> ... <c6>    all legs, arriving together
    POS?                     -> OK POS <c1> ... <c6> <IDLE|BUSY>
    STOP                     -> OK STOP                     halt every leg where it is
    HOME                     -> OK HOME                     reference run: all legs to
                                                            stroke zero, counts zeroed

A move is acknowledged at once; the PC polls ``POS?`` until ``IDLE``. Errors::

    ERR 1 <text>   unknown command
    ERR 2 <text>   bad argument (leg number, count not an integer, wrong field count)
    ERR 3 <text>   target out of range (counts < 0 or > MAX)
    ERR 4 <text>   busy (a move is still running; send STOP first)
    ERR 5 <text>   checksum mismatch
    ERR 6 <text>   motor or encoder fault

Example exchange (the checksums are real)::

    >>> frame("POS?")
    b'POS?*73\\n'
    >>> unframe(b'OK POS 5000 5000 5000 5000 5000 5000 IDLE*4C\\r\\n')
    'OK POS 5000 5000 5000 5000 5000 5000 IDLE'
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = [
    "TERMINATOR",
    "ERROR_CODES",
    "MOTION_COMMANDS",
    "ProtocolError",
    "Command",
    "Reply",
    "checksum",
    "frame",
    "unframe",
    "parse_command",
    "parse_reply",
    "format_command",
]

TERMINATOR = b"\n"
ERROR_CODES = {1: "unknown command", 2: "bad argument", 3: "target out of range",
               4: "busy", 5: "checksum mismatch", 6: "motor or encoder fault"}
#: commands that make a leg move
MOTION_COMMANDS = ("MOVE", "MOVEALL", "HOME")
_ARITY = {"ID?": 0, "MOVE": 2, "MOVEALL": 6, "POS?": 0, "STOP": 0, "HOME": 0}


class ProtocolError(ValueError):
    """A line that breaks the protocol (bad framing, checksum, syntax). ``code`` is the ERR code."""

    def __init__(self, message: str, code: int = 2):
        super().__init__(message)
        self.code = code


def checksum(body: str) -> str:
    """Two hex digits of the XOR of the body's bytes.

    >>> checksum("STOP")
    '18'
    """
    x = 0
    for ch in body.encode("ascii"):
        x ^= ch
    return f"{x:02X}"


def frame(body: str) -> bytes:
    """``body*HH\\n`` as bytes."""
    body.encode("ascii")  # refuses non-ASCII early
    return f"{body}*{checksum(body)}".encode("ascii") + TERMINATOR


def unframe(line: bytes, require_checksum: bool = True) -> str:
    """The body of one received line; raises ProtocolError (code 5 for a checksum)."""
    if not line.endswith(TERMINATOR):
        raise ProtocolError(f"incomplete line {line!r} (no LF terminator)")
    try:
        text = line.decode("ascii").rstrip("\r\n")
    except UnicodeDecodeError:
        raise ProtocolError(f"non-ASCII bytes in {line!r}") from None
    if any(not (32 <= ord(c) < 127) for c in text):
        raise ProtocolError(f"control characters in {line!r}")
    if "*" not in text:
        if require_checksum:
            raise ProtocolError(f"no checksum in {line!r}", code=5)
        return text.strip()
    body, _, cs = text.rpartition("*")
    if cs.upper() != checksum(body):
        raise ProtocolError(f"checksum mismatch in {line!r} (expected *{checksum(body)})", code=5)
    return body


@dataclass(frozen=True)
class Command:
    keyword: str
    args: tuple[int, ...]

    @property
    def is_motion(self) -> bool:
        return self.keyword in MOTION_COMMANDS

    def __str__(self) -> str:
        return format_command(self.keyword, *self.args)


def format_command(keyword: str, *args: int) -> str:
    return " ".join([keyword, *(str(int(a)) for a in args)])


def parse_command(body: str) -> Command:
    """Parse a command body (no checksum); checks the keyword, arity and integer fields
    (leg numbers 1..6); ranges of counts are the box's business (ERR 3).

    >>> parse_command("MOVE 3 4200")
    Command(keyword='MOVE', args=(3, 4200))
    """
    fields = body.split()
    if not fields:
        raise ProtocolError("empty command", code=1)
    kw = fields[0].upper()
    if kw not in _ARITY:
        raise ProtocolError(f"unknown command {fields[0]!r}", code=1)
    if len(fields) - 1 != _ARITY[kw]:
        raise ProtocolError(f"{kw} takes {_ARITY[kw]} argument(s), got {len(fields) - 1}")
    try:
        args = tuple(int(f) for f in fields[1:])
    except ValueError:
        raise ProtocolError(f"{kw}: arguments must be integers, got {' '.join(fields[1:])!r}") from None
    if kw == "MOVE" and not 1 <= args[0] <= 6:
        raise ProtocolError(f"MOVE: leg must be 1..6, got {args[0]}")
    return Command(kw, args)


@dataclass(frozen=True)
class Reply:
    """A parsed reply: ``OK <keyword> <fields...>`` or ``ERR <code> <text>``."""

    ok: bool
    keyword: str = ""
    fields: tuple[str, ...] = ()
    code: int = 0
    text: str = ""

    def __str__(self) -> str:
        if self.ok:
            return " ".join(["OK", self.keyword, *self.fields]).strip()
        return f"ERR {self.code} {self.text}".strip()


def parse_reply(body: str) -> Reply:
    """Parse a reply body.

    >>> parse_reply("ERR 3 leg 2 target 12000 outside 0..10000")
    Reply(ok=False, keyword='', fields=(), code=3, text='leg 2 target 12000 outside 0..10000')
    """
    fields = body.split()
    if fields[:1] == ["OK"] and len(fields) >= 2:
        return Reply(True, fields[1], tuple(fields[2:]))
    if fields[:1] == ["ERR"] and len(fields) >= 2:
        try:
            code = int(fields[1])
        except ValueError:
            raise ProtocolError(f"malformed error reply {body!r}") from None
        return Reply(False, code=code, text=" ".join(fields[2:]))
    raise ProtocolError(f"malformed reply {body!r}")
