"""Bad frames, refused before decoding starts.

Each case damages one stack of the small simulated data set (a copy of hard links, the
damaged files rewritten) and runs ``fringecal run --dataset`` and ``fringecal decode``:
exit status 2, one line naming the frame file and what is wrong, no traceback, nothing
written, and for ``run`` before Prefect starts (its flow call is replaced by a trap).
Then the header probes of the other frame formats (TIFF, BMP, frames.npy) on tiny stacks.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import tifffile
import yaml
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.fringe.importer import FrameStackError, check_levels, check_stack, write_frames
from fringecal.fringe.sequence import FringeSequence

runner = CliRunner()


def _replace(path: Path, data: bytes) -> None:
    """Rewrite a frame of the hard-linked copy (unlinked first: never through the link)."""
    path.unlink()
    path.write_bytes(data)


def _spec(stack: Path) -> dict:
    return yaml.safe_load((stack / "sequence.yaml").read_text())


def _frames(stack: Path) -> list[Path]:
    return sorted(stack.glob("*.png"))


def _first(stack: Path, orientation: str = "x") -> Path:
    """The first frame of an orientation: the one check_levels decodes."""
    s = _spec(stack)
    return stack / FringeSequence.frame_name(orientation, s["fringe_counts"][0], 0)


def _middle(stack: Path) -> Path:
    """A frame check_levels does not decode (the fourth step of the first fringe count)."""
    s = _spec(stack)
    return stack / FringeSequence.frame_name("x", s["fringe_counts"][0], 3)


def _png(img: np.ndarray) -> bytes:
    return imagecodecs.png_encode(img, level=1)


def _size(stack):
    s = _spec(stack)
    return s["height_px"], s["width_px"]


def other_size(stack):
    h, w = _size(stack)
    f = _middle(stack)
    _replace(f, _png(np.full((h, w + 2), 800, np.uint16)))
    return f, f"image is {w + 2}x{h} px, sequence.yaml says {w}x{h}"


def truncated(stack):
    f = _middle(stack)
    data = f.read_bytes()
    _replace(f, data[: len(data) // 2])
    return f, "corrupt or unreadable PNG (truncated: the"


def colour(stack):
    h, w = _size(stack)
    f = _middle(stack)
    _replace(f, _png(np.full((h, w, 3), 800, np.uint16)))
    return f, "expected a single-channel (grey) image, got a RGB PNG"


def zero_bytes(stack):
    f = _middle(stack)
    _replace(f, b"")
    return f, "empty file (0 bytes); expected a grey PNG frame"


def not_a_png(stack):
    f = _middle(stack)
    _replace(f, b"GIF89a, renamed to .png")
    return f, "corrupt or unreadable PNG (no PNG signature)"


def eight_bit(stack):
    h, w = _size(stack)
    f = _middle(stack)
    _replace(f, _png(np.full((h, w), 80, np.uint8)))
    return f, "8-bit uint8 image, but sequence.yaml says bit_depth 12 (16-bit files)"


def beyond_bit_depth(stack):
    f = _first(stack)
    img = imagecodecs.png_decode(f.read_bytes())
    img[:4, :4] = 5000
    _replace(f, _png(img))
    return f, "value 5000 exceeds the 12-bit range of sequence.yaml (max 4095); wrong bit_depth?"


def all_dark(stack):
    """Lens cap on: every frame read noise of a few DN."""
    h, w = _size(stack)
    rng = np.random.default_rng(3)
    for f in _frames(stack):
        _replace(f, _png(rng.integers(0, 12, (h, w)).astype(np.uint16)))
    return _first(stack), "dark frame: 0 of"


def over_exposed(stack):
    h, w = _size(stack)
    for f in _frames(stack):
        _replace(f, _png(np.full((h, w), 4095, np.uint16)))
    return _first(stack), "saturated stack: 100% of the pixels are at full scale (4095)"


def dark_middle_frame(stack):
    """One dark frame in the middle of a stack: found when the stack is read for decoding."""
    h, w = _size(stack)
    f = _middle(stack)
    _replace(f, _png(np.zeros((h, w), np.uint16)))
    return f, "dark frame: 0 of"


# (name, group of the damaged stack, damage, commands); "run" refuses before Prefect starts;
# a single dark frame among the stack's others is found when the stack is read for decoding
# (after Prefect has started, for `fringecal run`), still exit 2 naming the frame
CASES = [
    ("other-size", "measurements", other_size, ("run", "decode")),
    ("truncated", "measurements", truncated, ("run", "decode")),
    ("colour", "measurements", colour, ("run", "decode")),
    ("0-byte", "measurements", zero_bytes, ("run", "decode")),
    ("not-a-png", "measurements", not_a_png, ("run", "decode")),
    ("8-bit", "measurements", eight_bit, ("run", "decode")),
    ("beyond-bit-depth", "measurements", beyond_bit_depth, ("run", "decode")),
    ("all-dark", "measurements", all_dark, ("run", "decode")),
    ("over-exposed", "measurements", over_exposed, ("run", "decode")),
    ("0-byte-ballbar", "verification", zero_bytes, ("run", "decode")),
    ("all-dark-ballbar", "verification", all_dark, ("run", "decode")),
    ("dark-middle-frame", "measurements", dark_middle_frame, ("decode",)),
]


def _listing(root: Path) -> list[tuple[str, int]]:
    return sorted((str(p.relative_to(root)), p.stat().st_size if p.is_file() else -1) for p in root.rglob("*"))


def _stack(data: Path, group: str) -> Path:
    """The first stack of the group: a measurement's or a ball-bar position's first scanner."""
    folders = sorted(p for p in (data / group).iterdir() if p.is_dir() and p.name != "acceptance")
    return sorted(p for p in folders[0].iterdir() if p.is_dir())[0]


PARAMS = [pytest.param(command, group, damage, id=f"{command}-{name}")
          for name, group, damage, commands in CASES for command in commands]


@pytest.mark.parametrize("command, group, damage", PARAMS)
def test_bad_frame_stops_before_decoding(small_dataset, tmp_path, monkeypatch, command, group, damage):
    def trap(*args, **kwargs):
        raise AssertionError("the command went on to decode")

    monkeypatch.setattr("fringecal.flows.cli_run._execute", trap)  # Prefect would start here
    if damage is not dark_middle_frame:  # that one is found by the decode's own read
        monkeypatch.setattr("fringecal.flows.cli_decode._decode", trap)
    data = tmp_path / "ds"
    shutil.copytree(small_dataset[0], data, copy_function=os.link)
    stack = _stack(data, group)
    frame, expected = damage(stack)
    before = _listing(tmp_path)
    out = tmp_path / "out"
    args = (["run", "--dataset", str(data), "--out", str(out)] if command == "run"
            else ["decode", "--frames", str(stack), "--out", str(out / "m.zarr")])
    res = runner.invoke(app, args)
    lines = res.stderr.strip().splitlines()  # stdout: what `run` checks and where the run goes
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and len(lines) == 1, res.output
    assert lines[0].startswith(f"error: {frame}: "), lines[0]
    assert expected in lines[0], lines[0]
    assert _listing(tmp_path) == before and not out.exists()


def test_check_levels_of_the_small_data_set_pass(small_dataset):
    """Every stack of the simulated data set passes (no false alarm), 2 frames each."""
    from fringecal.dataset import DataSet

    ds = DataSet.open(small_dataset[0])
    ds.check_frames()
    assert len(ds.stacks()) >= 8


# -- the header probes of the other formats, on tiny stacks --------------------------------------

SEQ = FringeSequence((16, 15, 14, 12), 3)
H, W = 12, 20


def _tiny(folder: Path, fmt: str, bits: int = 16) -> Path:
    v, u = np.mgrid[0:H, 0:W]
    full = 2**bits - 1
    frames = np.stack([0.5 * full + 0.4 * full * np.cos(t * (u - W / 2) / W * 6 + 2 * np.pi * k / SEQ.n_steps)
                       for _, t, k in SEQ.frames()])
    return write_frames(folder, np.rint(frames).astype(np.uint8 if bits == 8 else np.uint16), SEQ, bits, fmt=fmt)


def _refused(folder: Path, name: str) -> str:
    with pytest.raises(FrameStackError) as info:
        check_stack(folder)
    msg = str(info.value)
    assert msg.startswith(f"{folder / name}: "), msg
    return msg


def test_tiff_headers(tmp_path):
    folder = _tiny(tmp_path / "t", "tif")
    check_stack(folder)
    check_levels(folder)
    f = folder / "x_015_01.tif"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 100])
    assert "corrupt or unreadable TIFF (truncated: its image data runs to byte" in _refused(folder, f.name)
    f.write_bytes(b"")
    assert "empty file (0 bytes)" in _refused(folder, f.name)
    tifffile.imwrite(f, np.zeros((H, W, 3), np.uint16))
    assert "expected a single-channel (grey) image, got shape (12, 20, 3)" in _refused(folder, f.name)
    tifffile.imwrite(f, np.zeros((H, W), np.float32))
    assert "32-bit float32 image, but sequence.yaml says bit_depth 16" in _refused(folder, f.name)


def test_bmp_headers(tmp_path):
    folder = _tiny(tmp_path / "b", "bmp", bits=8)
    check_stack(folder)
    check_levels(folder)
    f = folder / "y_014_02.bmp"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) - 30])
    assert "corrupt or unreadable BMP (truncated: 20x12 px need" in _refused(folder, f.name)
    f.write_bytes(b"BM" + b"\0" * 10)
    assert "corrupt or unreadable BMP (no BMP header)" in _refused(folder, f.name)


def test_npy_headers_and_levels(tmp_path):
    folder = _tiny(tmp_path / "n", "npy")
    check_stack(folder)
    f = folder / "frames.npy"
    frames = np.load(f)
    f.write_bytes(f.read_bytes()[:-10])
    assert "corrupt or unreadable .npy (truncated" in _refused(folder, f.name)
    dark = frames.copy()
    dark[SEQ.frame_index("y", 16, 0)] = 3
    np.save(f, dark)
    check_stack(folder)
    with pytest.raises(FrameStackError, match=r"frames\.npy \(frame 12, y_016_00\): dark frame: 0 of 240 pixels"):
        check_levels(folder)
