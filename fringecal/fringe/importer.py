"""Image-stack importer: one measurement's fringe frames from a folder.

Layout::

    measurement/
        sequence.yaml          orientations, fringe_counts, n_steps, width_px, height_px,
                               bit_depth (8..16), optional scanner and measurement ids
        x_064_00.png           one grey 8- or 16-bit PNG or TIFF per frame, named
        x_064_01.png           {orientation}_{fringes:03d}_{step:02d}.png (or .tif/.tiff)
        ...
    or, instead of the per-frame files,
        frames.npy             all frames, shape (n_frames, height, width), in acquisition order

Every problem (unreadable YAML, missing/extra/misnamed frames, mixed formats, wrong
size, wrong bit depth, corrupt or colour image, saturated stack) raises one
:class:`FrameStackError` whose message starts with the offending file.
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
from .sequence import FringeSequence, SequenceError

__all__ = ["FrameStackError", "StackSpec", "FrameStack", "read_stack_spec", "read_frames", "write_frames",
           "SEQUENCE_FILE", "STACK_FILE"]

SEQUENCE_FILE = "sequence.yaml"
STACK_FILE = "frames.npy"
_FRAME_EXTS = {".png": "png", ".tif": "tif", ".tiff": "tif"}
_IMAGE_EXTS = set(_FRAME_EXTS) | {".npy", ".jpg", ".jpeg", ".bmp", ".gif", ".webp", ".jp2", ".pgm", ".ppm"}
_NAME = re.compile(r"^([a-z])_(\d{3})_(\d{2})$")


class FrameStackError(ValueError):
    """A frame folder that cannot be decoded; the message names the file (and frame)."""


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

    Returns the spec, the frame files in acquisition order (or ``[frames.npy]``) and
    the format (``"png"``, ``"tif"`` or ``"npy"``).
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
                                  f"lossless) or one {STACK_FILE}")
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
    ext = "tif" if fmt == "tif" else "png"
    missing = [seq.frame_name(o, t, k, ext) for o, t, k in seq.frames() if _stem(o, t, k) not in found]
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
        Reader threads (image decoding releases the GIL); default: all cores.
    max_saturated_fraction : float
        A frame with more of its pixels at full scale makes the stack unusable.
    """
    folder = Path(folder)
    spec, files, fmt = read_stack_spec(folder)
    h, w = spec.height_px, spec.width_px
    if fmt == "npy":
        frames = _read_npy(files[0], spec)
    else:
        frames = np.empty((spec.sequence.n_frames, h, w), spec.dtype)
        reader = _read_png if fmt == "png" else _read_tif

        def read(i):
            reader(files[i], spec, frames[i])

        with ThreadPoolExecutor(max_workers=threads or os.cpu_count() or 1) as pool:
            errors = []
            for i, fut in enumerate([pool.submit(read, i) for i in range(len(files))]):
                if (e := fut.exception()) is not None:
                    errors.append((i, e))
        if errors:
            raise errors[0][1]
    _check_values(frames, files, spec, max_saturated_fraction)
    return FrameStack(folder, spec, frames, files, fmt)


def write_frames(folder, frames: np.ndarray, sequence: FringeSequence, bit_depth: int, fmt: str = "tif",
                 scanner: str | None = None, measurement: str | None = None) -> Path:
    """Write frames (n_frames, H, W) as a measurement folder that :func:`read_frames` reads.

    ``fmt`` is ``"png"``, ``"tif"`` (uncompressed) or ``"npy"`` (one stack file).
    """
    folder = Path(folder)
    frames = np.asarray(frames)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    if frames.shape[0] != sequence.n_frames or frames.ndim != 3:
        raise ValueError(f"expected ({sequence.n_frames}, H, W) frames, got {frames.shape}")
    if frames.dtype != dtype:
        raise ValueError(f"{bit_depth}-bit frames must be {np.dtype(dtype).name}, got {frames.dtype}")
    folder.mkdir(parents=True, exist_ok=True)
    spec = {**sequence.to_dict(), "width_px": int(frames.shape[2]), "height_px": int(frames.shape[1]),
            "bit_depth": int(bit_depth)}
    spec.update({k: v for k, v in (("scanner", scanner), ("measurement", measurement)) if v is not None})
    if fmt == "npy":
        np.save(folder / STACK_FILE, frames)
    elif fmt in ("png", "tif"):
        def write(i):
            name = folder / sequence.frame_name(*sequence.frames()[i], ext=fmt)
            if fmt == "png":
                ok, buf = cv2.imencode(".png", frames[i], [cv2.IMWRITE_PNG_COMPRESSION, 1])
                if not ok:
                    raise OSError(f"{name}: PNG encoding failed")
                buf.tofile(name)
            else:
                tifffile.imwrite(name, frames[i], compression=None)

        with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
            list(pool.map(write, range(sequence.n_frames)))
    else:
        raise ValueError(f"unknown frame format {fmt!r}; use 'png', 'tif' or 'npy'")
    (folder / SEQUENCE_FILE).write_text(yaml.safe_dump(spec, sort_keys=False))
    return folder


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


def _check_image(path: Path, img: np.ndarray, spec: StackSpec) -> None:
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[..., 0]
    if img.ndim != 2:
        raise FrameStackError(f"{path}: expected a single-channel (grey) image, got shape {img.shape}")
    if img.shape != (spec.height_px, spec.width_px):
        raise FrameStackError(f"{path}: image is {img.shape[1]}x{img.shape[0]} px, "
                              f"{SEQUENCE_FILE} says {spec.width_px}x{spec.height_px}")
    if img.dtype != spec.dtype:
        raise FrameStackError(f"{path}: {img.dtype.itemsize * 8}-bit {img.dtype.name} image, but {SEQUENCE_FILE} says "
                              f"bit_depth {spec.bit_depth} ({spec.dtype.itemsize * 8}-bit files)")


def _read_png(path: Path, spec: StackSpec, out: np.ndarray) -> None:
    try:
        img = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    except (OSError, cv2.error) as err:
        raise FrameStackError(f"{path}: cannot read image ({err})") from None
    if img is None:
        raise FrameStackError(f"{path}: corrupt or unreadable PNG")
    _check_image(path, img, spec)
    out[...] = img.reshape(out.shape)


def _read_tif(path: Path, spec: StackSpec, out: np.ndarray) -> None:
    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) != 1:
                raise FrameStackError(f"{path}: {len(tif.pages)} pages; expected one grey frame per file")
            page = tif.pages[0]
            shape, dtype = page.shape, np.dtype(page.dtype)
            if len(shape) == 2 and shape == out.shape and dtype == out.dtype:
                page.asarray(out=out)
                return
            img = page.asarray()
    except FrameStackError:
        raise
    except Exception as err:  # tifffile raises many types on damaged files
        raise FrameStackError(f"{path}: corrupt or unreadable TIFF ({type(err).__name__}: {err})") from None
    _check_image(path, img, spec)
    out[...] = img.reshape(out.shape)


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
