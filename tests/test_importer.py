"""Image-stack importer: frames written here with cv2 / tifffile / numpy directly
(the test's own formula, not a simulator), then read and decoded."""

import cv2
import numpy as np
import pytest
import tifffile
import yaml

from fringecal.fringe.decode import decode
from fringecal.fringe.importer import FrameStackError, read_frames, read_stack_spec, write_frames
from fringecal.fringe.measurement import NoFringesError, decode_folder
from fringecal.fringe.sequence import FringeSequence
from fringecal.store import open_store

H, W = 12, 20
SEQ = FringeSequence((16, 15, 14, 12), 4)


def truth():
    v, u = np.mgrid[0:H, 0:W]
    return (u - (W - 1) / 2) / W * 2 * 3.0, (v - (H - 1) / 2) / H * 2 * 3.0


def frame(w, t, k, n, bits):
    full = 2**bits - 1
    img = 0.5 * full + 0.4 * full * np.cos(t * w + 2 * np.pi * k / n)
    return np.rint(img).astype(np.uint8 if bits == 8 else np.uint16)


def write_folder(folder, bits=16, fmt="png", seq=SEQ, spec=None, skip=(), image=None):
    """One file per frame with the test's own writer; returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    w_x, w_y = truth()
    for o in seq.orientations:
        for t in seq.fringe_counts:
            for k in range(seq.n_steps):
                name = f"{o}_{t:03d}_{k:02d}.{fmt}"
                if name in skip:
                    continue
                img = frame(w_x if o == "x" else w_y, t, k, seq.n_steps, bits) if image is None else image(o, t, k)
                if fmt == "png":
                    assert cv2.imwrite(str(folder / name), img)
                else:
                    tifffile.imwrite(folder / name, img)
    doc = {"orientations": list(seq.orientations), "fringe_counts": list(seq.fringe_counts),
           "n_steps": seq.n_steps, "width_px": W, "height_px": H, "bit_depth": bits, **(spec or {})}
    (folder / "sequence.yaml").write_text(yaml.safe_dump(doc))
    return folder


@pytest.mark.parametrize("n_steps", [3, 4, 7])
@pytest.mark.parametrize("fmt", ["png", "tif"])
@pytest.mark.parametrize("bits", [8, 12, 16])
def test_png_and_tiff_stacks_decode_to_the_known_phase(tmp_path, fmt, bits, n_steps):
    folder = write_folder(tmp_path / "m1", bits=bits, fmt=fmt, seq=FringeSequence((16, 15, 14, 12), n_steps))
    stack = read_frames(folder)
    assert stack.format == fmt and stack.frames.dtype == (np.uint8 if bits == 8 else np.uint16)
    assert stack.full_scale == 2**bits - 1
    res = decode(stack.frames, stack.sequence, full_scale=stack.full_scale)
    w_x, w_y = truth()
    # 8-bit quantisation limits the phase; tau = phase / t over 4 counts
    tol = 2e-3 if bits == 8 else 2e-4
    assert np.abs(res.tau["x"] - w_x).max() < tol and np.abs(res.tau["y"] - w_y).max() < tol
    assert res.valid.all()


@pytest.mark.parametrize("fmt", ["png", "tif", "npy"])
def test_write_frames_round_trips(tmp_path, fmt):
    frames = np.random.default_rng(0).integers(0, 4096, (SEQ.n_frames, H, W), dtype=np.uint16)
    write_frames(tmp_path / "m", frames, SEQ, bit_depth=12, fmt=fmt, scanner="scanner1", measurement="3")
    stack = read_frames(tmp_path / "m")
    assert np.array_equal(stack.frames, frames) and stack.spec.scanner == "scanner1" and stack.format == fmt


def test_decode_folder_writes_a_store(tmp_path):
    folder = write_folder(tmp_path / "m1", bits=16, fmt="tif", spec={"scanner": "scanner2", "measurement": "7"})
    decode_folder(folder, tmp_path / "m1.zarr", attrs={"config_digest": "abc"})
    ds = open_store(tmp_path / "m1.zarr")
    assert ds.attrs["scanner"] == "scanner2" and ds.attrs["measurement"] == "7" and ds.attrs["config_digest"] == "abc"
    assert ds.attrs["sequence"] == SEQ.to_dict() and ds.attrs["bit_depth"] == 16
    assert np.abs(ds.tau_x.values - truth()[0]).max() < 2e-4


def errors(tmp_path, **kw):
    with pytest.raises(FrameStackError) as info:
        read_frames(write_folder(tmp_path / "m", **kw))
    return str(info.value)


def test_missing_frame(tmp_path):
    msg = errors(tmp_path, skip=("y_014_02.png",))
    assert msg.startswith(str(tmp_path / "m" / "y_014_02.png")) and "missing frame (1 of 32" in msg


def test_extra_frame_and_wrong_names(tmp_path):
    folder = write_folder(tmp_path / "m")
    cv2.imwrite(str(folder / "x_016_04.png"), np.zeros((H, W), np.uint16))  # step 4 of a 4-step sequence
    with pytest.raises(FrameStackError, match=r"x_016_04\.png: extra frame, not in sequence\.yaml"):
        read_stack_spec(folder)
    (folder / "x_016_04.png").unlink()
    cv2.imwrite(str(folder / "x_16_0.png"), np.zeros((H, W), np.uint16))
    with pytest.raises(FrameStackError, match=r"x_16_0\.png: frame name does not follow"):
        read_stack_spec(folder)
    (folder / "x_16_0.png").unlink()
    (folder / "notes.txt").write_text("ignored")  # not an image: fine
    cv2.imwrite(str(folder / "x_016_00.jpg"), np.zeros((H, W), np.uint8))
    with pytest.raises(FrameStackError, match=r"x_016_00\.jpg: unsupported frame format"):
        read_stack_spec(folder)


def test_mixed_formats(tmp_path):
    folder = write_folder(tmp_path / "m", skip=("y_012_03.png",))
    tifffile.imwrite(folder / "y_012_03.tif", np.zeros((H, W), np.uint16))
    with pytest.raises(FrameStackError, match=r"mixed frame formats"):
        read_stack_spec(folder)


def test_mixed_sizes(tmp_path):
    def image(o, t, k):
        return np.zeros((H, W + (o == "y" and t == 15 and k == 1)), np.uint16) + 1000
    msg = errors(tmp_path, image=image)
    assert "y_015_01.png: image is 21x12 px, sequence.yaml says 20x12" in msg


def test_wrong_bit_depth(tmp_path):
    msg = errors(tmp_path, image=lambda o, t, k: np.full((H, W), 100, np.uint8))  # 8-bit files, yaml says 16
    assert "x_016_00.png: 8-bit uint8 image, but sequence.yaml says bit_depth 16" in msg
    msg = errors(tmp_path / "b", bits=12, fmt="tif",
                 image=lambda o, t, k: np.full((H, W), 5000 if (o, t, k) == ("x", 14, 2) else 100, np.uint16))
    assert "x_014_02.tif: value 5000 exceeds the 12-bit range of sequence.yaml (max 4095)" in msg


def test_corrupt_images(tmp_path):
    folder = write_folder(tmp_path / "p")
    (folder / "x_015_03.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(FrameStackError, match=r"x_015_03\.png: corrupt or unreadable PNG"):
        read_frames(folder)
    folder = write_folder(tmp_path / "t", fmt="tif")
    data = (folder / "y_016_01.tif").read_bytes()
    (folder / "y_016_01.tif").write_bytes(data[:40])
    with pytest.raises(FrameStackError, match=r"y_016_01\.tif: corrupt or unreadable TIFF"):
        read_frames(folder)


def test_colour_image(tmp_path):
    msg = errors(tmp_path, image=lambda o, t, k: np.zeros((H, W, 3), np.uint16))
    assert "x_016_00.png: expected a single-channel (grey) image" in msg


def test_saturated_stack(tmp_path):
    msg = errors(tmp_path, bits=8,
                 image=lambda o, t, k: np.full((H, W), 255 if (o, t, k) == ("y", 12, 3) else 90, np.uint8))
    assert "y_012_03.png: saturated stack: 100% of the pixels are at full scale (255)" in msg


def test_zero_modulation_everywhere(tmp_path):
    w_x, _ = truth()
    folder = write_folder(tmp_path / "m", image=lambda o, t, k: frame(w_x, t, k, 4, 16) if o == "x"
                          else np.full((H, W), 30000, np.uint16))
    with pytest.raises(NoFringesError, match=r"zero modulation everywhere in orientation y: frames "
                                             r"y_016_00\.\.y_012_03 have modulation below"):
        decode_folder(folder, tmp_path / "m.zarr")
    assert not (tmp_path / "m.zarr").exists()


def test_no_valid_pixel_names_the_folder(tmp_path):
    rng = np.random.default_rng(0)  # noise instead of fringes: inconsistent phases everywhere
    folder = write_folder(tmp_path / "m", seq=FringeSequence(),
                          image=lambda o, t, k: rng.integers(10000, 50000, (H, W), dtype=np.uint16))
    with pytest.raises(NoFringesError, match=r"m: no valid pixel .*median phase error x"):
        decode_folder(folder, tmp_path / "m.zarr")


@pytest.mark.parametrize("content, match", [
    (None, r"sequence\.yaml: missing"),
    ("orientations: [x, y\n", r"sequence\.yaml: not valid YAML"),
    ("- 1\n- 2\n", r"sequence\.yaml: expected a mapping"),
    ("width_px: 20\nheight_px: 12\nbit_depth: 16\nexposure: 3\n", r"sequence\.yaml: exposure: unknown key"),
    ("width_px: 20\nheight_px: 12\nbit_depth: 16\nfringe_counts: [16, 15, 13]\n",
     r"sequence\.yaml: fringe counts \(16, 15, 13\) are not a reverse-exponential schedule"),
    ("width_px: 20\nheight_px: 12\nbit_depth: 16\nn_steps: 2\n", r"sequence\.yaml: phase stepping needs at least 3"),
    ("width_px: 20\nheight_px: 12\nbit_depth: 17\n", r"sequence\.yaml: bit_depth: Input should be less than"),
])
def test_bad_sequence_yaml(tmp_path, content, match):
    folder = write_folder(tmp_path / "m")
    if content is None:
        (folder / "sequence.yaml").unlink()
    else:
        (folder / "sequence.yaml").write_text(content)
    with pytest.raises(FrameStackError, match=match):
        read_stack_spec(folder)


def test_npy_stack_errors(tmp_path):
    folder = tmp_path / "m"
    frames = np.zeros((SEQ.n_frames, H, W), np.uint16)
    write_frames(folder, frames, SEQ, bit_depth=16, fmt="npy")
    np.save(folder / "frames.npy", frames[:-1])
    with pytest.raises(FrameStackError, match=r"frames\.npy: stack of shape \(31, 12, 20\)"):
        read_frames(folder)
    (folder / "frames.npy").write_bytes(b"not numpy")
    with pytest.raises(FrameStackError, match=r"frames\.npy: corrupt or unreadable \.npy"):
        read_frames(folder)
    np.save(folder / "frames.npy", frames)
    cv2.imwrite(str(folder / "x_016_00.png"), frames[0])
    with pytest.raises(FrameStackError, match=r"x_016_00\.png: the folder holds frames\.npy"):
        read_frames(folder)
