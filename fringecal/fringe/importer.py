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
size, wrong bit depth, corrupt, truncated or colour image, saturated stack) raises one
:class:`FrameStackError` whose message starts with the offending file.

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

from ..config import StrictModel
from .frame_files import SEQUENCE_FILE, FrameStackError, Scratch, read_bmp, read_png, read_tif
from .sequence import FringeSequence, SequenceError

__all__ = ["FrameStackError", "StackSpec", "FrameStack", "read_stack_spec", "read_frames", "write_frames",
           "SEQUENCE_FILE", "STACK_FILE", "FRAME_FORMATS"]

STACK_FILE = "frames.npy"
FRAME_FORMATS = ("png", "tif", "bmp")
_FRAME_EXTS = {".png": "png", ".tif": "tif", ".tiff": "tif", ".bmp": "bmp"}
_IMAGE_EXTS = set(_FRAME_EXTS) | {".npy", ".jpg", ".jpeg", ".gif", ".webp", ".jp2", ".pgm", ".ppm"}
_NAME = re.compile(r"^([a-z])_(\d{3})_(\d{2})$")


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
    entries = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in _IMAGE_EXTS)
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


def read_frames(folder, threads: int | None = None, max_saturated_fraction: float = 0.25) -> FrameStack:
    """Read and check every frame of a measurement folder into one array.

    Parameters
    ----------
    folder : path
    threads : int, optional
        Reader threads, each decoding whole frames (every decoder used releases the
        GIL); default: the cores this process may run on.
    max_saturated_fraction : float
        A frame with more of its pixels at full scale makes the stack unusable.

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
    _check_values(frames, files, spec, max_saturated_fraction)
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
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise FrameStackError(f"{path}: missing; a frame folder needs {SEQUENCE_FILE} (orientations, fringe_counts, "
                              "n_steps, width_px, height_px, bit_depth)") from None
    except (yaml.YAMLError, UnicodeDecodeError) as err:
        raise FrameStackError(f"{path}: not valid YAML ({str(err).splitlines()[0]})") from None
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


def _read_npy(path: Path, spec: StackSpec) -> np.ndarray:
    n = spec.sequence.n_frames
    try:
        frames = np.load(path, allow_pickle=False)
    except Exception as err:
        raise FrameStackError(f"{path}: corrupt or unreadable .npy ({type(err).__name__}: {err})") from None
    want = (n, spec.height_px, spec.width_px)
    if frames.shape != want:
        raise FrameStackError(f"{path}: stack of shape {frames.shape}, {SEQUENCE_FILE} says {want} "
                              "(frames, height, width)")
    if frames.dtype != spec.dtype:
        raise FrameStackError(f"{path}: {frames.dtype.name} stack, but {SEQUENCE_FILE} says bit_depth "
                              f"{spec.bit_depth} ({spec.dtype.name})")
    return np.ascontiguousarray(frames)


def _check_values(frames: np.ndarray, files: list[Path], spec: StackSpec, max_saturated_fraction: float) -> None:
    peak, n_full = _frame_stats(frames, spec.full_scale)
    seq = spec.sequence
    names = [_stem(o, t, k) for o, t, k in seq.frames()]

    def where(i):
        return files[i] if len(files) == len(names) else f"{files[0]} (frame {i}, {names[i]})"

    over = np.flatnonzero(peak > spec.full_scale)
    if over.size:
        i = over[0]
        raise FrameStackError(f"{where(i)}: value {peak[i]} exceeds the {spec.bit_depth}-bit range of "
                              f"{SEQUENCE_FILE} (max {spec.full_scale}); wrong bit_depth?")
    fraction = n_full / (frames.shape[1] * frames.shape[2])
    i = int(np.argmax(fraction))
    if fraction[i] > max_saturated_fraction:
        raise FrameStackError(f"{where(i)}: saturated stack: {fraction[i]:.0%} of the pixels are at full scale "
                              f"({spec.full_scale}); reduce the exposure (limit {max_saturated_fraction:.0%})")


@nb.njit(parallel=True, cache=True)
def _frame_stats(frames, full_scale):  # pragma: no cover - numba
    """Per frame: the largest value and the number of pixels at or above full scale."""
    n, h, w = frames.shape
    peak = np.zeros(n, np.int64)
    n_full = np.zeros(n, np.int64)
    for i in nb.prange(n):
        m = 0
        s = 0
        for r in range(h):
            for c in range(w):
                v = np.int64(frames[i, r, c])
                m = max(m, v)
                s += v >= full_scale
        peak[i] = m
        n_full[i] = s
    return peak, n_full
