"""Image-stack importer: one measurement's fringe frames from a folder.

Layout::

    measurement/
        sequence.yaml          orientations, fringe_counts, n_steps, width_px, height_px,
                               bit_depth (8..16), optional scanner and measurement ids
        x_064_00.png           one grey 8- or 16-bit PNG or TIFF, or 8-bit BMP, per frame,
        x_064_01.png           named {orientation}_{fringes:03d}_{step:02d}.png
        ...                    (or .tif/.tiff/.bmp)
    or, instead of the per-frame files,
        frames.npy             all frames, shape (n_frames, height, width), in acquisition order

Every problem (unreadable YAML, missing/extra/misnamed frames, mixed formats, wrong
size, wrong bit depth, empty, corrupt, truncated or colour image, saturated or dark
frame) raises one :class:`FrameStackError` whose message starts with the offending file.

Checked before decoding
-----------------------
:func:`check_stack` checks a folder without decoding a pixel: ``sequence.yaml``, the
listing, and the header of every frame (empty file, signature, grey, bit depth, size,
and a PNG's IEND chunk at the end, a TIFF's image data or a BMP's rows within the
file, so a truncated frame is found); :meth:`fringecal.dataset.DataSet.open` and
``fringecal decode`` run it on every stack. :func:`check_levels` then decodes one frame
per orientation (the first of its sequence; 2 of a stack's 98 frames) for the checks
that need pixels, so that a stack recorded with the lens cap on, the projector off or
far too much exposure is refused before any decoding (``fringecal run --dataset``,
``fringecal decode``). :func:`read_frames` applies the same value checks to every frame.

* **Colour** frames are refused, not converted: a scanner's camera is monochrome, and a
  colour file means a wrong camera or export setting whose grey conversion would not be
  the sensor's intensity.
* **Saturation**: a pixel at full scale (``2**bit_depth - 1``) in any frame is invalid
  in decoding (:mod:`fringecal.fringe.decode`); a frame with more than
  :data:`MAX_SATURATED_FRACTION` (25 %) of its pixels at full scale refuses the stack
  (over-exposed: reduce the exposure).
* **Darkness**: a frame with at most :data:`MIN_LIT_FRACTION` (0.01 %) of its pixels at
  or above :data:`DARK_LEVEL` (2 % of full scale, the decoder's default minimum
  modulation) is dark and refuses the stack; hot pixels stay below that count, while a
  projected fringe lights about half of what the camera sees.
* **One level**: every phase step shows the same mean level (the fringes move, their
  average does not); a frame below the stack's median level divided by
  :data:`LEVEL_RATIO` (4: two bits) was saved at another bit depth or scaling (a 16-bit
  stack with one frame 4 bits short lost 30 % of its valid pixels silently) and
  refuses the stack.
* **Repeated step**: consecutive phase steps of one fringe count differ by a phase
  shift; a step whose mean difference from the one before is below the stack's median
  step difference divided by :data:`REPEAT_RATIO` (8) repeats it (a double trigger)
  and refuses the stack (:func:`read_frames` only: it needs every frame).
* **Not a file**: an entry named like a frame that is a symbolic link loop, a broken
  link, a FIFO, a device or a socket is refused as what it is (a FIFO is never opened:
  reading one would wait forever).

How frames are read (the readers are in :mod:`fringecal.fringe.frame_files`; decisions
measured by ``benchmarks/image_import.py``, the table is in docs/decoding.md, "Image
import"):

* One thread per core reads whole frames, each decoded straight into its slice of the
  preallocated ``(n_frames, height, width)`` array: there is never a second copy of
  the stack. A thread's scratch (the file's bytes and, for PNG, its zlib stream and
  inflated rows: 16 MB for a 2048 px 16-bit frame) is reused from frame to frame.
* PNG (grey, 8/16-bit, not interlaced: what scanners write) is decoded here: the
  chunks are walked and the IDAT payloads joined, the zlib stream inflated by
  libdeflate (``imagecodecs.deflate_decode``; it checks the stream's Adler-32, so a
  damaged image byte is refused, and chunk CRCs are not checked again) and the rows
  unfiltered and byte-swapped by one numba kernel. Inflating is most of the work, and
  libdeflate inflates twice as fast as zlib 1.2.13 (1.4 times zlib-ng, 1.3 times
  ISA-L); the libpng/libspng decoders (OpenCV, Pillow, ``imagecodecs.png_decode``,
  ``pyspng``) reach 90-100 M px per CPU second, this path 250 (the inflate alone 345).
  Interlaced PNG, rare from scanners, goes through libpng (``imagecodecs.png_decode``);
  colour, palette and alpha PNGs are refused from the header.
* BMP: 8-bit paletted with a grey palette (the palette applied), by
  ``imagecodecs.bmp_decode``; colour palettes and 24/32-bit BMPs are refused. BMP has
  no 16-bit grey form (16-bit BMP is RGB555/565 colour), so a BMP stack must say
  ``bit_depth: 8``. TIFF (uncompressed, LZW, deflate...) by tifffile, with imagecodecs
  for the codecs: fastest for uncompressed and deflate TIFF; for LZW libtiff is 1.3-1.5
  times faster, not worth a second TIFF reader.
* No streaming (decoding the first orientation while the second is read): reading is
  CPU-bound on every core, so overlap can only fill idle moments; decoding a stack side
  by side with reading one finished 0.07-0.21 s (6-13 %) sooner than one after the
  other (``overlap_probe``), and getting even that needs the decoder split by
  orientation (:func:`fringecal.fringe.decode.decode` reads every frame of a row in one
  fused pass) and a reader that reports finished orientations.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import cv2
import numba as nb
import numpy as np
import tifffile
import yaml
from pydantic import Field, ValidationError

from fringecal.config import StrictModel, load_yaml_text, yaml_problem
from fringecal.fringe.frame_files import (
    SEQUENCE_FILE,
    FrameStackError,
    Scratch,
    empty_file,
    probe_bmp,
    probe_png,
    probe_tif,
    read_bmp,
    read_png,
    read_tif,
)
from fringecal.fringe.sequence import FringeSequence, SequenceError
from fringecal.names import not_a_file

__all__ = ["FrameStackError", "StackSpec", "FrameStack", "read_stack_spec", "check_stack", "check_levels",
           "read_frames", "write_frames", "SEQUENCE_FILE", "STACK_FILE", "FRAME_FORMATS", "MAX_SATURATED_FRACTION",
           "DARK_LEVEL", "MIN_LIT_FRACTION", "LEVEL_RATIO", "REPEAT_RATIO"]

STACK_FILE = "frames.npy"
FRAME_FORMATS = ("png", "tif", "bmp")
_FRAME_EXTS = {".png": "png", ".tif": "tif", ".tiff": "tif", ".bmp": "bmp"}
_IMAGE_EXTS = set(_FRAME_EXTS) | {".npy", ".jpg", ".jpeg", ".gif", ".webp", ".jp2", ".pgm", ".ppm"}
_NAME = re.compile(r"^([a-z])_(\d{3})_(\d{2})$")
#: a frame with more of its pixels at full scale is over-exposed
MAX_SATURATED_FRACTION = 0.25
#: fraction of full scale a pixel must reach to count as lit (the decoder's default min_modulation)
DARK_LEVEL = 0.02
#: a frame with at most this fraction of its pixels lit is dark
MIN_LIT_FRACTION = 1e-4


class StackSpec(StrictModel):
    """The contents of ``sequence.yaml``."""

    orientations: list[Literal["x", "y"]] = Field(default_factory=lambda: ["x", "y"])
    fringe_counts: list[int] = Field(default_factory=lambda: [64, 63, 62, 60, 56, 48, 32])
    n_steps: int = 7
    width_px: int = Field(gt=0)
    height_px: int = Field(gt=0)
    bit_depth: int = Field(ge=8, le=16)
    scanner: Optional[str] = None
    measurement: Optional[str] = None

    @property
    def sequence(self) -> FringeSequence:
        return FringeSequence(tuple(self.fringe_counts), self.n_steps, tuple(self.orientations))

    @property
    def dtype(self) -> np.dtype:
        return np.dtype(np.uint8 if self.bit_depth == 8 else np.uint16)

    @property
    def full_scale(self) -> int:
        return 2**self.bit_depth - 1


@dataclass
class FrameStack:
    """Frames of one measurement, shape (n_frames, height, width), uint8 or uint16."""

    folder: Path
    spec: StackSpec
    frames: np.ndarray
    files: list[Path]
    format: str

    @property
    def sequence(self) -> FringeSequence:
        return self.spec.sequence

    @property
    def full_scale(self) -> int:
        return self.spec.full_scale


def read_stack_spec(folder) -> tuple[StackSpec, list[Path], str]:
    """Validate ``sequence.yaml`` and the folder listing without reading any image.

    Returns
    -------
    spec : StackSpec
    files : list of Path
        The frame files in acquisition order (or ``[frames.npy]``).
    format : str
        ``"png"``, ``"tif"``, ``"bmp"`` or ``"npy"``.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise FrameStackError(f"{folder}: not a folder of fringe frames")
    spec = _load_spec(folder / SEQUENCE_FILE)
    seq = spec.sequence
    entries = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_EXTS and not p.is_dir())
    for p in entries:
        if (kind := not_a_file(p)) is not None:
            raise FrameStackError(f"{p}: {kind}, not a frame file; replace it with the frame's image file")
    stack = folder / STACK_FILE
    if stack.exists():
        others = [p for p in entries if p != stack]
        if others:
            raise FrameStackError(f"{others[0]}: the folder holds {STACK_FILE}, so per-frame images are ambiguous; "
                                  "keep one or the other")
        return spec, [stack], "npy"
    expected = {_stem(o, t, k) for o, t, k in seq.frames()}
    found: dict[str, Path] = {}
    formats: dict[str, Path] = {}
    for p in entries:
        fmt = _FRAME_EXTS.get(p.suffix.lower())
        if fmt is None:
            raise FrameStackError(f"{p}: unsupported frame format {p.suffix!r}; use PNG or TIFF (8 or 16 bit, "
                                  f"lossless), 8-bit BMP or one {STACK_FILE}")
        if not _NAME.match(p.stem):
            raise FrameStackError(f"{p}: frame name does not follow {{orientation}}_{{fringes:03d}}_{{step:02d}} "
                                  f"(e.g. {seq.frame_name(*seq.frames()[0])})")
        if p.stem not in expected:
            raise FrameStackError(
                f"{p}: extra frame, not in {SEQUENCE_FILE} (orientations {list(seq.orientations)}, "
                f"fringe counts {list(seq.fringe_counts)}, steps 00..{seq.n_steps - 1:02d})")
        if p.stem in found:
            raise FrameStackError(f"{p}: duplicate of {found[p.stem].name}")
        found[p.stem] = p
        formats.setdefault(fmt, p)
    if len(formats) > 1:
        a, b = formats.values()
        raise FrameStackError(f"{b}: mixed frame formats in one measurement ({a.name} and {b.name})")
    fmt = next(iter(formats), "png")
    if fmt == "bmp" and spec.bit_depth != 8:
        raise FrameStackError(f"{formats['bmp']}: BMP frames are 8-bit (BMP has no 16-bit grey form), but "
                              f"{SEQUENCE_FILE} says bit_depth {spec.bit_depth}; use 16-bit PNG or TIFF")
    missing = [seq.frame_name(o, t, k, fmt) for o, t, k in seq.frames() if _stem(o, t, k) not in found]
    if missing:
        shown = ", ".join(missing[:4]) + (", ..." if len(missing) > 4 else "")
        raise FrameStackError(f"{folder / missing[0]}: missing frame ({len(missing)} of {seq.n_frames} "
                              f"frames missing: {shown})")
    files = [found[_stem(o, t, k)] for o, t, k in seq.frames()]
    return spec, files, fmt


def check_stack(folder) -> tuple[StackSpec, list[Path], str]:
    """:func:`read_stack_spec` and the header of every frame, reading no pixel (see
    "Checked before decoding" in the module notes); same returns."""
    spec, files, fmt = read_stack_spec(folder)
    probe = {"png": probe_png, "tif": probe_tif, "bmp": probe_bmp, "npy": _probe_npy}[fmt]
    for path in files:
        probe(path, spec)
    return spec, files, fmt


def check_levels(folder, max_saturated_fraction: float = MAX_SATURATED_FRACTION) -> None:
    """Decode the first frame of each orientation of a folder that :func:`check_stack`
    accepted and refuse a dark or over-exposed one, or values beyond the bit depth."""
    spec, files, fmt = read_stack_spec(folder)
    seq = spec.sequence
    picked = [seq.frame_index(o, seq.fringe_counts[0], 0) for o in seq.orientations]
    frames = np.empty((len(picked), spec.height_px, spec.width_px), spec.dtype)
    if fmt == "npy":
        try:
            stack = np.load(files[0], mmap_mode="r", allow_pickle=False)
            frames[...] = stack[picked]
        except Exception as err:
            raise FrameStackError(f"{files[0]}: corrupt or unreadable .npy ({type(err).__name__}: {err})") from None
    else:  # the readers of decoding: same checks, same messages (their kernels are compiled once)
        reader, scratch = {"png": read_png, "tif": read_tif, "bmp": read_bmp}[fmt], Scratch()
        for j, i in enumerate(picked):
            reader(files[i], spec, frames[j], scratch)
    peak, n_full, n_lit, total = _frame_stats(frames, spec.full_scale, _lit_level(spec.full_scale))
    labels = [_frame_label(files, spec, i) for i in picked]
    _check_values(peak, n_full, n_lit, labels, spec, max_saturated_fraction)
    _check_same_level(total / (spec.width_px * spec.height_px), labels, spec)


def read_frames(folder, threads: int | None = None,
                max_saturated_fraction: float = MAX_SATURATED_FRACTION) -> FrameStack:
    """Read and check every frame of a measurement folder into one array.

    Parameters
    ----------
    folder : path
    threads : int, optional
        Reader threads, each decoding whole frames (every decoder used releases the
        GIL); default: the cores this process may run on.
    max_saturated_fraction : float
        A frame with more of its pixels at full scale makes the stack unusable (as
        does a dark frame: see the module notes).

    Returns
    -------
    FrameStack
        ``frames`` has shape (n_frames, height, width) and the dtype of the bit depth.
    """
    folder = Path(folder)
    spec, files, fmt = read_stack_spec(folder)
    if fmt == "npy":
        frames = _read_npy(files[0], spec)
    else:
        frames = np.empty((spec.sequence.n_frames, spec.height_px, spec.width_px), spec.dtype)
        reader = {"png": read_png, "tif": read_tif, "bmp": read_bmp}[fmt]
        scratch = Scratch()

        def read(i):
            reader(files[i], spec, frames[i], scratch)

        with ThreadPoolExecutor(max_workers=threads or _cores()) as pool:
            futures = [pool.submit(read, i) for i in range(len(files))]
            errors = [e for e in (f.exception() for f in futures) if e is not None]
        if errors:
            raise errors[0]
    peak, n_full, n_lit, total = _frame_stats(frames, spec.full_scale, _lit_level(spec.full_scale))
    labels = [_frame_label(files, spec, i) for i in range(len(frames))]
    _check_values(peak, n_full, n_lit, labels, spec, max_saturated_fraction)
    _check_same_level(total / (spec.width_px * spec.height_px), labels, spec)
    _check_steps_differ(frames, labels, spec.sequence)
    return FrameStack(folder, spec, frames, files, fmt)


def write_frames(folder, frames: np.ndarray, sequence: FringeSequence, bit_depth: int, fmt: str = "tif",
                 scanner: str | None = None, measurement: str | None = None) -> Path:
    """Write frames (n_frames, H, W) as a measurement folder that :func:`read_frames` reads.

    Parameters
    ----------
    fmt : str
        ``"png"`` (OpenCV's libpng at zlib level 1 with libpng's adaptive row filters:
        2.5 % larger than level 6 on noisy fringes, written 7 times faster, and ~20 %
        faster than ``imagecodecs.png_encode`` at level 1), ``"tif"`` (uncompressed),
        ``"bmp"`` (8-bit only, grey palette) or ``"npy"`` (one stack file). Writing
        keeps OpenCV; reading does not use it.
    """
    folder = Path(folder)
    frames = np.asarray(frames)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    if frames.shape[0] != sequence.n_frames or frames.ndim != 3:
        raise ValueError(f"expected ({sequence.n_frames}, H, W) frames, got {frames.shape}")
    if frames.dtype != dtype:
        raise ValueError(f"{bit_depth}-bit frames must be {np.dtype(dtype).name}, got {frames.dtype}")
    if fmt == "bmp" and bit_depth != 8:
        raise ValueError(f"BMP holds 8-bit grey frames only, not {bit_depth}-bit")
    if fmt not in (*FRAME_FORMATS, "npy"):
        raise ValueError(f"unknown frame format {fmt!r}; use 'png', 'tif', 'bmp' or 'npy'")
    folder.mkdir(parents=True, exist_ok=True)
    spec = {**sequence.to_dict(), "width_px": int(frames.shape[2]), "height_px": int(frames.shape[1]),
            "bit_depth": int(bit_depth)}
    spec.update({k: v for k, v in (("scanner", scanner), ("measurement", measurement)) if v is not None})
    if fmt == "npy":
        np.save(folder / STACK_FILE, frames)
    else:
        def write(i):
            name = folder / sequence.frame_name(*sequence.frames()[i], ext=fmt)
            if fmt == "tif":
                tifffile.imwrite(name, frames[i], compression=None)
                return
            ok, buf = cv2.imencode(f".{fmt}", frames[i], [cv2.IMWRITE_PNG_COMPRESSION, 1] if fmt == "png" else [])
            if not ok:
                raise OSError(f"{name}: {fmt.upper()} encoding failed")
            buf.tofile(name)

        with ThreadPoolExecutor(max_workers=_cores()) as pool:
            list(pool.map(write, range(sequence.n_frames)))
    (folder / SEQUENCE_FILE).write_text(yaml.safe_dump(spec, sort_keys=False))
    return folder


def _cores() -> int:
    """The cores this process may run on (all of them where affinity is unknown)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _stem(orientation: str, fringes: int, step: int) -> str:
    return f"{orientation}_{fringes:03d}_{step:02d}"


def _load_spec(path: Path) -> StackSpec:
    if path.exists() or path.is_symlink():
        if (kind := not_a_file(path)) is not None:
            raise FrameStackError(f"{path}: {kind}, not a file")
    try:
        data = load_yaml_text(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FrameStackError(f"{path}: missing; a frame folder needs {SEQUENCE_FILE} (orientations, fringe_counts, "
                              "n_steps, width_px, height_px, bit_depth)") from None
    except UnicodeDecodeError as err:
        raise FrameStackError(f"{path}: not UTF-8 text (byte 0x{err.object[err.start]:02x})") from None
    except yaml.YAMLError as err:
        raise FrameStackError(f"{path}: {yaml_problem(err)}") from None
    if not isinstance(data, dict):
        raise FrameStackError(f"{path}: expected a mapping, found {type(data).__name__}")
    try:
        spec = StackSpec.model_validate(data)
        spec.sequence  # noqa: B018 - validates the schedule
    except ValidationError as err:
        lines = [f"{'.'.join(map(str, e['loc'])) or '(top level)'}: "
                 f"{'unknown key' if e['type'] == 'extra_forbidden' else e['msg']}" for e in err.errors()]
        raise FrameStackError(f"{path}: " + "; ".join(lines)) from None
    except SequenceError as err:
        raise FrameStackError(f"{path}: {err}") from None
    return spec


def _probe_npy(path: Path, spec: StackSpec) -> None:
    """Shape, dtype and length of a ``frames.npy`` from its header."""
    try:
        size = path.stat().st_size
        if size == 0:
            raise empty_file(path, ".npy stack of")
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(f)
            start = f.tell()
    except FrameStackError:
        raise
    except Exception as err:
        raise FrameStackError(f"{path}: corrupt or unreadable .npy ({type(err).__name__}: {err})") from None
    _check_npy(path, spec, tuple(shape), np.dtype(dtype))
    need = start + int(np.prod(shape)) * np.dtype(dtype).itemsize
    if need > size:
        raise FrameStackError(f"{path}: corrupt or unreadable .npy (truncated: {need} bytes needed, the file has "
                              f"{size})")


def _check_npy(path: Path, spec: StackSpec, shape: tuple, dtype: np.dtype) -> None:
    want = (spec.sequence.n_frames, spec.height_px, spec.width_px)
    if shape != want:
        raise FrameStackError(f"{path}: stack of shape {shape}, {SEQUENCE_FILE} says {want} "
                              "(frames, height, width)")
    if dtype != spec.dtype:
        raise FrameStackError(f"{path}: {dtype.name} stack, but {SEQUENCE_FILE} says bit_depth "
                              f"{spec.bit_depth} ({spec.dtype.name})")


def _read_npy(path: Path, spec: StackSpec) -> np.ndarray:
    try:
        frames = np.load(path, allow_pickle=False)
    except Exception as err:
        raise FrameStackError(f"{path}: corrupt or unreadable .npy ({type(err).__name__}: {err})") from None
    _check_npy(path, spec, frames.shape, frames.dtype)
    return np.ascontiguousarray(frames)


def _lit_level(full_scale: int) -> int:
    """The smallest value that counts as lit (:data:`DARK_LEVEL` of full scale, at least 1)."""
    return max(1, int(np.ceil(DARK_LEVEL * full_scale)))


def _frame_label(files: list[Path], spec: StackSpec, i: int) -> str:
    """Frame ``i`` in messages: its file, or ``frames.npy (frame i, name)``."""
    if len(files) > 1 or files[0].suffix != ".npy":
        return str(files[i])
    o, t, k = spec.sequence.frames()[i]
    return f"{files[0]} (frame {i}, {_stem(o, t, k)})"


def _check_values(peak, n_full, n_lit, labels: list[str], spec: StackSpec, max_saturated_fraction: float) -> None:
    """Refuse values beyond the bit depth, an over-exposed frame, a dark frame (per-frame
    statistics: largest value, pixels at full scale, pixels at or above the lit level)."""
    n_px = spec.width_px * spec.height_px
    over = np.flatnonzero(np.asarray(peak) > spec.full_scale)
    if over.size:
        i = over[0]
        raise FrameStackError(f"{labels[i]}: value {peak[i]} exceeds the {spec.bit_depth}-bit range of "
                              f"{SEQUENCE_FILE} (max {spec.full_scale}); wrong bit_depth?")
    fraction = np.asarray(n_full) / n_px
    i = int(np.argmax(fraction))
    if fraction[i] > max_saturated_fraction:
        raise FrameStackError(f"{labels[i]}: saturated stack: {fraction[i]:.0%} of the pixels are at full scale "
                              f"({spec.full_scale}); reduce the exposure (limit {max_saturated_fraction:.0%})")
    dark = np.flatnonzero(np.asarray(n_lit) <= MIN_LIT_FRACTION * n_px)
    if dark.size:
        i = dark[0]
        level = _lit_level(spec.full_scale)
        raise FrameStackError(f"{labels[i]}: dark frame: {n_lit[i]} of {n_px} pixels reach {level} DN "
                              f"({DARK_LEVEL:.0%} of full scale {spec.full_scale}), the brightest is {peak[i]} DN; "
                              "lens cap on, projector off or exposure far too short? (a frame needs more than "
                              f"{MIN_LIT_FRACTION:.2%} of its pixels lit)")


#: a frame whose mean level is below the stack's median level divided by this (two bits)
#: was saved at another bit depth or exposure than the others
LEVEL_RATIO = 4.0
#: consecutive phase steps whose mean difference is below the stack's median step
#: difference divided by this show the same fringe position: a repeated step
REPEAT_RATIO = 8.0


def _check_same_level(means, labels: list[str], spec: StackSpec) -> None:
    """Refuse a frame far darker than the stack's others: every phase step of a stack
    shows the same mean level (the fringes shift, their average does not), so a frame at
    1/16 of it is 4 bits short -- saved with another bit depth or scaling -- and would
    silently cost valid pixels in decoding."""
    means = np.asarray(means, float)
    if len(means) < 2:
        return
    median = float(np.median(means))
    low = np.flatnonzero(means * LEVEL_RATIO < median)
    if low.size:
        i = int(low[0])
        bits = np.log2(median / max(means[i], 1e-9))
        raise FrameStackError(f"{labels[i]}: mean level {means[i]:.0f} DN against the stack's {median:.0f} DN (median "
                              f"of its frames): about {bits:.0f} bits short; a frame saved at another bit depth or "
                              f"scaling than {SEQUENCE_FILE}'s bit_depth {spec.bit_depth} (or a far shorter "
                              "exposure)? Every frame of a stack must be recorded alike")


def _check_steps_differ(frames: np.ndarray, labels: list[str], sequence: FringeSequence) -> None:
    """Refuse a phase step that repeats the one before it (a double trigger: the camera
    fired twice on one pattern): consecutive steps of a fringe count differ by a phase
    shift of 2 pi / N, so their mean difference is a large part of the modulation, while
    a repeated step differs by noise alone."""
    previous = np.full(len(frames), -1, np.int64)
    for i, (_, _, k) in enumerate(sequence.frames()):
        if k > 0:
            previous[i] = i - 1
    if not (previous >= 0).any():
        return
    diff = _step_differences(frames, previous)
    pairs = np.flatnonzero(previous >= 0)
    median = float(np.median(diff[pairs]))
    # a pair far below the median, in a fringe count whose other steps do move (a count
    # without fringes at all is the decoder's "zero modulation" message, not a repeat)
    group = np.array([i - k for i, (_, _, k) in enumerate(sequence.frames())])
    moving = {g: diff[pairs[group[pairs] == g]].max() * REPEAT_RATIO >= median for g in np.unique(group[pairs])}
    same = [i for i in pairs if diff[i] * REPEAT_RATIO < median and moving[group[i]]]
    if same:
        i = int(same[0])
        raise FrameStackError(f"{labels[i]}: repeats the phase step before it ({labels[previous[i]]}): their mean "
                              f"difference is {diff[i]:.1f} DN against {median:.0f} DN between the stack's other "
                              "consecutive steps; a double trigger (the camera fired twice on one pattern)? Every "
                              "step must show the next phase shift")


@nb.njit(parallel=True, cache=True)
def _frame_stats(frames, full_scale, lit_level):  # pragma: no cover - numba
    """Per frame: the largest value, the number of pixels at or above full scale, the
    number at or above ``lit_level`` and the sum of the values."""
    n, h, w = frames.shape
    peak = np.zeros(n, np.int64)
    n_full = np.zeros(n, np.int64)
    n_lit = np.zeros(n, np.int64)
    total = np.zeros(n, np.int64)
    for i in nb.prange(n):
        m = 0
        s = 0
        q = 0
        t = 0
        for r in range(h):
            for c in range(w):
                v = np.int64(frames[i, r, c])
                m = max(m, v)
                s += v >= full_scale
                q += v >= lit_level
                t += v
        peak[i] = m
        n_full[i] = s
        n_lit[i] = q
        total[i] = t
    return peak, n_full, n_lit, total


@nb.njit(parallel=True, cache=True)
def _step_differences(frames, previous):  # pragma: no cover - numba
    """Mean absolute difference of each frame from frame ``previous[i]`` (the step before
    it in its fringe count; -1: none, the result is -1)."""
    n, h, w = frames.shape
    out = np.full(n, -1.0)
    for i in nb.prange(n):
        j = previous[i]
        if j < 0:
            continue
        t = 0
        for r in range(h):
            for c in range(w):
                t += abs(np.int64(frames[i, r, c]) - np.int64(frames[j, r, c]))
        out[i] = t / (h * w)
    return out
