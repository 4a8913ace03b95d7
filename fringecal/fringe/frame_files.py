"""Reading one frame file (PNG, BMP, TIFF) into its slot of a measurement's stack.

The readers behind :func:`fringecal.fringe.importer.read_frames`; the decisions and
their measurements are in that module's docstring. Each reader checks the file against
the stack's ``sequence.yaml`` (:class:`~fringecal.fringe.importer.StackSpec`: size,
bit depth, grey) and decodes straight into ``out``; every problem raises one
:class:`FrameStackError` naming the file.
"""

from __future__ import annotations

import os
import struct
import threading
from pathlib import Path

import imagecodecs
import numba as nb
import numpy as np
import tifffile

__all__ = ["FrameStackError", "SEQUENCE_FILE", "Scratch", "check_image", "read_png", "read_bmp", "read_tif",
           "probe_png", "probe_bmp", "probe_tif", "empty_file"]

SEQUENCE_FILE = "sequence.yaml"
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_COLOUR = {2: "RGB", 3: "palette (colour-mapped)", 4: "grey+alpha", 6: "RGBA"}
_PNG_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # the last chunk: length 0, type, CRC
_PNG_TAIL_SEARCH = 65536  # bytes searched for IEND when a PNG has data after it


class FrameStackError(ValueError):
    """A frame folder that cannot be decoded; the message names the file (and frame)."""


def check_image(path: Path, shape: tuple, dtype, spec) -> None:
    """Refuse an image of another shape, channel count or sample type than the spec's."""
    dtype = np.dtype(dtype)
    if len(shape) == 3 and shape[2] == 1:
        shape = shape[:2]
    if len(shape) != 2:
        raise FrameStackError(f"{path}: expected a single-channel (grey) image, got shape {tuple(shape)}")
    if tuple(shape) != (spec.height_px, spec.width_px):
        raise FrameStackError(f"{path}: image is {shape[1]}x{shape[0]} px, "
                              f"{SEQUENCE_FILE} says {spec.width_px}x{spec.height_px}")
    if dtype != spec.dtype:
        raise FrameStackError(f"{path}: {dtype.itemsize * 8}-bit {dtype.name} image, but {SEQUENCE_FILE} says "
                              f"bit_depth {spec.bit_depth} ({spec.dtype.itemsize * 8}-bit files)")


class Scratch(threading.local):
    """Per-thread buffers reused from frame to frame: the file's bytes, a PNG's zlib
    stream (its IDAT payloads joined) and its inflated rows."""

    def __init__(self):
        self.file = np.empty(0, np.uint8)
        self.zlib = np.empty(0, np.uint8)
        self.rows = np.empty(0, np.uint8)

    def grow(self, name: str, size: int) -> np.ndarray:
        buf = getattr(self, name)
        if buf.size < size:
            buf = np.empty(size, np.uint8)
            setattr(self, name, buf)
        return buf[:size]


def read_file(path: Path, scratch: Scratch) -> np.ndarray:
    """The file's bytes, in the thread's file buffer."""
    try:
        with open(path, "rb", buffering=0) as f:
            size = os.fstat(f.fileno()).st_size
            buf = scratch.grow("file", size)
            view, n = memoryview(buf), 0
            while n < size and (got := f.readinto(view[n:])):
                n += got
    except OSError as err:
        raise FrameStackError(f"{path}: cannot read file ({err.strerror or err})") from None
    return buf[:n]


def empty_file(path: Path, kind: str) -> FrameStackError:
    """The error for a 0-byte frame file (a capture that wrote nothing)."""
    return FrameStackError(f"{path}: empty file (0 bytes); expected a grey {kind} frame")


def _png_header(path: Path, head, size: int, spec) -> tuple[int, int, int]:
    """(width, height, interlace) from a PNG's first 33 bytes ``head`` (of a ``size``-byte
    file), after refusing anything but a grey 8/16-bit image of the spec's size and depth."""

    def corrupt(why):
        return FrameStackError(f"{path}: corrupt or unreadable PNG ({why})")

    if size == 0:
        raise empty_file(path, "PNG")
    if bytes(head[:8]) != _PNG_SIGNATURE:
        raise corrupt("no PNG signature")
    if size < 33:
        raise corrupt(f"truncated: {size} bytes, no complete header")
    length, kind = struct.unpack_from(">I4s", head, 8)
    if kind != b"IHDR" or length != 13:
        raise corrupt("no IHDR header")
    w, h, depth, colour, method, filtering, interlace = struct.unpack_from(">IIBBBBB", head, 16)
    if colour in _PNG_COLOUR:
        raise FrameStackError(f"{path}: expected a single-channel (grey) image, got a {_PNG_COLOUR[colour]} PNG")
    if colour != 0 or depth not in (1, 2, 4, 8, 16) or method or filtering or interlace > 1:
        raise corrupt(f"invalid header: colour type {colour}, bit depth {depth}")
    if depth < 8:
        raise FrameStackError(f"{path}: {depth}-bit grey PNG, but {SEQUENCE_FILE} says bit_depth "
                              f"{spec.bit_depth} ({spec.dtype.itemsize * 8}-bit files)")
    check_image(path, (h, w), np.uint8 if depth == 8 else np.uint16, spec)
    return w, h, interlace


def _open_frame(path: Path):
    try:
        return open(path, "rb")
    except OSError as err:
        raise FrameStackError(f"{path}: cannot read file ({err.strerror or err})") from None


def probe_png(path: Path, spec) -> None:
    """Check a PNG frame from its header and its last bytes, reading no pixel: grey,
    8/16-bit, the spec's size and depth, not empty, and ending with its IEND chunk (a
    file cut short by a full disk or an interrupted copy does not)."""
    with _open_frame(path) as f:
        size = os.fstat(f.fileno()).st_size
        _png_header(path, f.read(33), size, spec)
        f.seek(max(0, size - 12))
        if f.read(12) == _PNG_IEND:
            return
        f.seek(max(0, size - _PNG_TAIL_SEARCH))  # data after IEND is allowed (libpng ignores it)
        tail = f.read()
    at = tail.rfind(_PNG_IEND)
    if at < 0 or size - len(tail) + at < 33:
        raise FrameStackError(f"{path}: corrupt or unreadable PNG (truncated: the {size}-byte file does not end "
                              "with the IEND chunk)")


def probe_bmp(path: Path, spec) -> None:
    """Check a BMP frame from its headers and palette, reading no pixel: 8-bit with a
    grey palette, the spec's size, not empty, not shorter than its rows need."""
    with _open_frame(path) as f:
        size = os.fstat(f.fileno()).st_size
        head = f.read(54)
        if size == 0:
            raise empty_file(path, "BMP")
        if len(head) < 54 or head[:2] != b"BM":
            raise FrameStackError(f"{path}: corrupt or unreadable BMP (no BMP header)")
        offset = struct.unpack_from("<I", head, 10)[0]
        header, w, h, _, bits, compression = struct.unpack_from("<IiiHHI", head, 14)
        if bits in (16, 24, 32):
            raise FrameStackError(f"{path}: expected a single-channel (grey) image, got a {bits}-bit colour BMP")
        if bits != 8:
            raise FrameStackError(f"{path}: {bits}-bit BMP; BMP frames must be 8-bit grey (paletted)")
        check_image(path, (abs(h), w), np.uint8, spec)
        used = struct.unpack_from("<I", head, 46)[0] or 256
        f.seek(14 + header)
        palette = np.frombuffer(f.read(4 * min(used, 256)), np.uint8)
    if used > 256 or palette.size != 4 * used:
        raise FrameStackError(f"{path}: corrupt or unreadable BMP (palette of {used} colours)")
    bgr = palette.reshape(used, 4)[:, :3]
    if not (bgr == bgr[:, :1]).all():
        raise FrameStackError(f"{path}: expected a single-channel (grey) image, got a BMP with a colour palette")
    need = offset + (w + 3) // 4 * 4 * abs(h)
    if compression == 0 and need > size:
        raise FrameStackError(f"{path}: corrupt or unreadable BMP (truncated: {w}x{abs(h)} px need {need} bytes, "
                              f"the file has {size})")


def probe_tif(path: Path, spec) -> None:
    """Check a TIFF frame from its directory, reading no pixel: one grey page of the
    spec's size and sample type, not empty, its image data within the file."""
    try:
        size = path.stat().st_size
    except OSError as err:
        raise FrameStackError(f"{path}: cannot read file ({err.strerror or err})") from None
    if size == 0:
        raise empty_file(path, "TIFF")
    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) != 1:
                raise FrameStackError(f"{path}: {len(tif.pages)} pages; expected one grey frame per file")
            page = tif.pages[0]
            check_image(path, page.shape, np.dtype(page.dtype), spec)
            end = max((int(o) + int(n) for o, n in zip(page.dataoffsets, page.databytecounts)), default=0)
    except FrameStackError:
        raise
    except Exception as err:  # tifffile raises many types on damaged files
        raise FrameStackError(f"{path}: corrupt or unreadable TIFF ({type(err).__name__}: {err})") from None
    if end > size:
        raise FrameStackError(f"{path}: corrupt or unreadable TIFF (truncated: its image data runs to byte {end}, "
                              f"the file has {size})")


def read_png(path: Path, spec, out: np.ndarray, scratch: Scratch) -> None:
    buf = read_file(path, scratch)

    def corrupt(why):
        return FrameStackError(f"{path}: corrupt or unreadable PNG ({why})")

    w, h, interlace = _png_header(path, buf[:33], buf.size, spec)
    if interlace:  # Adam7: rare from scanners; libpng de-interlaces
        try:
            imagecodecs.png_decode(buf, out=out)
        except Exception as err:  # imagecodecs raises PngError, ValueError...
            raise corrupt(f"{type(err).__name__}: {err}") from None
        return
    z = scratch.grow("zlib", buf.size)
    zlen, where = _png_gather_idat(buf, z)
    if zlen < 0:
        raise corrupt({-1: f"truncated: the chunk at byte {where} runs past the end of the {buf.size}-byte file",
                       -2: "no image data (IDAT) before IEND", -3: "truncated: no IEND chunk"}[zlen])
    rows = scratch.grow("rows", h * (w * out.itemsize + 1))
    try:
        got = len(imagecodecs.deflate_decode(z[:zlen], out=memoryview(rows)))
    except Exception as err:  # DeflateError: bad stream, Adler-32 mismatch, too much data
        raise corrupt(f"image data: {err}") from None
    if got != rows.size:
        raise corrupt(f"image data inflates to {got} bytes, {w}x{h} px need {rows.size}")
    bad_row = _png_unfilter(rows, out)
    if bad_row >= 0:
        raise corrupt(f"invalid filter type {rows[bad_row * (rows.size // h)]} in row {bad_row}")


@nb.njit(nogil=True, cache=True)
def _png_gather_idat(buf, z):  # pragma: no cover - numba
    """Walk the chunks after IHDR and copy the IDAT payloads, one after the other, to ``z``
    (as large as ``buf``).

    Returns (length of the zlib stream, 0), or (-1, offset) for a chunk running past the
    end, (-2, 0) for no IDAT, (-3, 0) for no IEND.
    """
    n = buf.size
    pos, dst = 8, 0
    while pos + 12 <= n:
        length = (np.int64(buf[pos]) << 24) | (np.int64(buf[pos + 1]) << 16) | \
                 (np.int64(buf[pos + 2]) << 8) | np.int64(buf[pos + 3])
        if pos + 12 + length > n:
            return -1, pos
        a, b, c, d = buf[pos + 4], buf[pos + 5], buf[pos + 6], buf[pos + 7]
        if a == 73 and b == 68 and c == 65 and d == 84:  # IDAT
            z[dst:dst + length] = buf[pos + 8:pos + 8 + length]
            dst += length
        elif a == 73 and b == 69 and c == 78 and d == 68:  # IEND
            return (dst, 0) if dst > 0 else (-2, 0)
        pos += 12 + length
    return (-3, 0) if pos == n else (-1, pos)


@nb.njit(nogil=True, cache=True, inline="always")
def _paeth(a, b, c):  # pragma: no cover - numba
    """PNG's Paeth predictor of byte ``a`` (left), ``b`` (up), ``c`` (up-left), as selects
    (noise makes the choice unpredictable, so branches would mispredict)."""
    pa = abs(b - c)
    pb = abs(a - c)
    pc = abs(a + b - 2 * c)
    r = b if pb <= pc else c
    return a if (pa <= pb) & (pa <= pc) else r


@nb.njit(nogil=True, cache=True, inline="always")
def _predict(ft, a, b, c):  # pragma: no cover - numba
    """Prediction of a byte by filter ``ft`` (1 Sub, 3 Average, 4 Paeth) from its left
    ``a``, upper ``b`` and upper-left ``c`` neighbours."""
    if ft == 1:
        return a
    if ft == 3:
        return (a + b) >> 1
    return _paeth(a, b, c)


@nb.njit(nogil=True, cache=True, inline="always")
def _unfilter_row(ft, cur, prev, bpp):  # pragma: no cover - numba
    """Undo filter ``ft`` (1, 3 or 4: those that use the left neighbour) of one row in
    place. Inlined with a constant ``ft`` at each call, so each filter is its own loop.
    The left neighbours are carried in registers, two byte lanes interleaved for 16-bit
    samples: each byte depends on the one before it, so latency is the limit."""
    for i in range(bpp):
        cur[i] = cur[i] + _predict(ft, np.int32(0), np.int32(prev[i]), np.int32(0))
    if bpp == 1:
        a, c = np.int32(cur[0]), np.int32(prev[0])
        for i in range(1, cur.size):
            b = np.int32(prev[i])
            a = (np.int32(cur[i]) + _predict(ft, a, b, c)) & 255
            cur[i] = a
            c = b
    else:
        a0, a1, c0, c1 = np.int32(cur[0]), np.int32(cur[1]), np.int32(prev[0]), np.int32(prev[1])
        for j in range(1, cur.size // 2):
            b0, b1 = np.int32(prev[2 * j]), np.int32(prev[2 * j + 1])
            a0 = (np.int32(cur[2 * j]) + _predict(ft, a0, b0, c0)) & 255
            a1 = (np.int32(cur[2 * j + 1]) + _predict(ft, a1, b1, c1)) & 255
            cur[2 * j] = a0
            cur[2 * j + 1] = a1
            c0, c1 = b0, b1


@nb.njit(nogil=True, cache=True)
def _png_unfilter(rows, out):  # pragma: no cover - numba
    """Undo PNG row filters in place in ``rows`` (h rows of a filter byte and w * bpp
    bytes) and store the big-endian samples in ``out`` (h, w) of uint8 or uint16.

    Returns -1, or the first row with an invalid filter type.
    """
    h, w = out.shape
    bpp = out.itemsize
    rb = w * bpp
    stride = rb + 1
    zero = np.zeros(rb, np.uint8)
    for r in range(h):
        ft = rows[r * stride]
        cur = rows[r * stride + 1:(r + 1) * stride]
        prev = rows[(r - 1) * stride + 1:r * stride] if r > 0 else zero
        if ft == 2:  # Up
            for i in range(rb):
                cur[i] = cur[i] + prev[i]
        elif ft == 1:  # Sub, Average, Paeth: one inlined loop each
            _unfilter_row(1, cur, prev, bpp)
        elif ft == 3:
            _unfilter_row(3, cur, prev, bpp)
        elif ft == 4:
            _unfilter_row(4, cur, prev, bpp)
        elif ft != 0:
            return r
        row = out[r]
        if bpp == 2:
            for c in range(w):
                row[c] = (np.uint16(cur[2 * c]) << 8) | np.uint16(cur[2 * c + 1])
        else:
            for c in range(w):
                row[c] = cur[c]
    return -1


def read_bmp(path: Path, spec, out: np.ndarray, scratch: Scratch) -> None:
    buf = read_file(path, scratch)
    grey = _bmp_grey_palette(buf, out.shape) if out.dtype == np.uint8 else None
    try:
        if grey is not None:  # 8-bit paletted, grey, the right size: indices straight into ``out``
            imagecodecs.bmp_decode(buf, asrgb=False, out=out)
            if not np.array_equal(grey, np.arange(grey.size)):
                np.take(grey, out, out=out)
            return
        img = imagecodecs.bmp_decode(buf)
    except Exception as err:  # BmpError, ValueError
        raise FrameStackError(f"{path}: corrupt or unreadable BMP ({type(err).__name__}: {err})") from None
    check_image(path, img.shape, img.dtype, spec)  # refuses colour, 24/32-bit and colour palettes
    out[...] = img.reshape(out.shape)


def _bmp_grey_palette(buf: np.ndarray, shape: tuple) -> np.ndarray | None:
    """The grey level of each of the 256 indices of an 8-bit paletted BMP of ``shape``
    whose palette is grey (R = G = B); None for anything else (decoded in full then)."""
    if buf.size < 54 or buf[:2].tobytes() != b"BM":
        return None
    header, w, h, _, bits = struct.unpack_from("<IiiHH", buf, 14)
    used = struct.unpack_from("<I", buf, 46)[0] or 256
    start = 14 + header
    if bits != 8 or (abs(h), w) != shape or used > 256 or start + 4 * used > buf.size:
        return None
    bgr = buf[start:start + 4 * used].reshape(used, 4)[:, :3]
    if not (bgr == bgr[:, :1]).all():
        return None
    return np.concatenate([bgr[:, 0], np.zeros(256 - used, np.uint8)])


def read_tif(path: Path, spec, out: np.ndarray, scratch: Scratch) -> None:
    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) != 1:
                raise FrameStackError(f"{path}: {len(tif.pages)} pages; expected one grey frame per file")
            page = tif.pages[0]
            shape, dtype = page.shape, np.dtype(page.dtype)
            if shape != out.shape or dtype != out.dtype:
                check_image(path, shape, dtype, spec)  # refuses all but an (h, w, 1) page
                out[...] = page.asarray(maxworkers=1).reshape(out.shape)
            else:
                page.asarray(out=out, maxworkers=1)  # one thread per frame already
    except FrameStackError:
        raise
    except Exception as err:  # tifffile raises many types on damaged files
        raise FrameStackError(f"{path}: corrupt or unreadable TIFF ({type(err).__name__}: {err})") from None
