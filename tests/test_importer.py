"""Image-stack importer: frames written here with libpng (imagecodecs), tifffile, numpy and
the test's own PNG and BMP writers (the test's own formula, not a simulator), then read
and decoded."""

import struct
import zlib

import imagecodecs
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


ADAM7 = [(0, 0, 8, 8), (4, 0, 8, 8), (0, 4, 4, 8), (2, 0, 4, 4), (0, 2, 2, 4), (1, 0, 2, 2), (0, 1, 1, 2)]


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def filtered_rows(img, filters):
    """PNG scanlines of a grey image, row r filtered with filters[r % len(filters)]
    (the formulas of the PNG specification, section 9)."""
    bpp = img.dtype.itemsize
    rows = img.astype(f">u{bpp}").view(np.uint8).reshape(img.shape[0], -1).astype(np.int64)
    out, up = [], np.zeros(rows.shape[1], np.int64)
    for r, x in enumerate(rows):
        ft = filters[r % len(filters)]
        left = np.r_[np.zeros(bpp, np.int64), x[:-bpp]]
        upleft = np.r_[np.zeros(bpp, np.int64), up[:-bpp]]
        p = left + up - upleft
        pa, pb, pc = np.abs(p - left), np.abs(p - up), np.abs(p - upleft)
        paeth = np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, upleft))
        pred = [np.zeros_like(x), left, up, (left + up) // 2, paeth][ft]
        out.append(bytes([ft]) + ((x - pred) % 256).astype(np.uint8).tobytes())
        up = x
    return b"".join(out)


def png_bytes(img, filters=(0,), interlace=False, idat_bytes=50, header=None, raw=None):
    """A grey PNG written by the test: given row filters, Adam7 if ``interlace``, the
    zlib stream split over IDAT chunks of ``idat_bytes``, a tEXt chunk between them;
    ``header`` overrides (bit depth, colour type) and ``raw`` the scanlines."""
    h, w = img.shape
    depth, colour = header or (8 * img.dtype.itemsize, 0)
    if raw is not None:
        pass
    elif interlace:
        raw = b"".join(filtered_rows(img[y0::dy, x0::dx], filters) for x0, y0, dx, dy in ADAM7
                       if img[y0::dy, x0::dx].size)
    else:
        raw = filtered_rows(img, filters)
    z = zlib.compress(raw, 6)
    idat = [png_chunk(b"IDAT", z[i:i + idat_bytes]) for i in range(0, len(z), idat_bytes)]
    ihdr = png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, depth, colour, 0, 0, int(interlace)))
    return (b"\x89PNG\r\n\x1a\n" + ihdr + png_chunk(b"tEXt", b"Software\0test") + b"".join(idat)
            + png_chunk(b"IEND", b""))


def bmp_bytes(img, palette=None, top_down=False):
    """An uncompressed BMP written by the test: 8-bit paletted (grey identity palette
    unless ``palette`` (256, 3) RGB is given) for (H, W) uint8, 24-bit BGR for (H, W, 3)."""
    h, w = img.shape[:2]
    if img.ndim == 2:
        bits, pal = 8, np.arange(256, dtype=np.uint8)[:, None].repeat(3, 1) if palette is None else palette
        table, pixels = np.c_[pal[:, ::-1], np.zeros(256, np.uint8)].tobytes(), img
    else:
        bits, table, pixels = 24, b"", img[..., ::-1].reshape(h, w * 3)
    stride = (pixels.shape[1] + 3) // 4 * 4
    body = np.zeros((h, stride), np.uint8)
    body[:, :pixels.shape[1]] = pixels
    body = body if top_down else body[::-1]
    offset = 14 + 40 + len(table)
    info = struct.pack("<IiiHHIIiiII", 40, w, -h if top_down else h, 1, bits, 0, body.size, 2835, 2835,
                       256 if bits == 8 else 0, 0)
    return b"BM" + struct.pack("<IHHI", offset + body.size, 0, 0, offset) + info + table + body.tobytes()


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
                if fmt == "tif":
                    tifffile.imwrite(folder / name, img)
                else:
                    (folder / name).write_bytes(bmp_bytes(img) if fmt == "bmp" else imagecodecs.png_encode(img))
    doc = {"orientations": list(seq.orientations), "fringe_counts": list(seq.fringe_counts),
           "n_steps": seq.n_steps, "width_px": W, "height_px": H, "bit_depth": bits, **(spec or {})}
    (folder / "sequence.yaml").write_text(yaml.safe_dump(doc))
    return folder


@pytest.mark.parametrize("n_steps", [3, 4, 7])
@pytest.mark.parametrize("fmt, bits", [("png", 8), ("png", 12), ("png", 16), ("tif", 8), ("tif", 12), ("tif", 16),
                                       ("bmp", 8)])
def test_png_tiff_and_bmp_stacks_decode_to_the_known_phase(tmp_path, fmt, bits, n_steps):
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


@pytest.mark.parametrize("fmt, bits", [("png", 12), ("tif", 12), ("npy", 12), ("png", 8), ("bmp", 8)])
def test_write_frames_round_trips(tmp_path, fmt, bits):
    frames = np.random.default_rng(0).integers(0, 2**bits, (SEQ.n_frames, H, W)).astype(np.uint8 if bits == 8
                                                                                        else np.uint16)
    write_frames(tmp_path / "m", frames, SEQ, bit_depth=bits, fmt=fmt, scanner="scanner1", measurement="3")
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
    # step 4 of a 4-step sequence
    (folder / "x_016_04.png").write_bytes(imagecodecs.png_encode(np.zeros((H, W), np.uint16)))
    with pytest.raises(FrameStackError, match=r"x_016_04\.png: extra frame, not in sequence\.yaml"):
        read_stack_spec(folder)
    (folder / "x_016_04.png").unlink()
    (folder / "x_16_0.png").write_bytes(imagecodecs.png_encode(np.zeros((H, W), np.uint16)))
    with pytest.raises(FrameStackError, match=r"x_16_0\.png: frame name does not follow"):
        read_stack_spec(folder)
    (folder / "x_16_0.png").unlink()
    (folder / "notes.txt").write_text("ignored")  # not an image: fine
    (folder / "x_016_00.jpg").write_bytes(b"\xff\xd8\xff\xe0 a JPEG")
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
    (folder / "x_016_00.png").write_bytes(imagecodecs.png_encode(frames[0]))
    with pytest.raises(FrameStackError, match=r"x_016_00\.png: the folder holds frames\.npy"):
        read_frames(folder)


def frames_folder(folder, frames, writer, bits, ext):
    """A measurement folder of ``frames`` (n, H, W), each file's bytes from ``writer(i, frame)``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, (o, t, k) in enumerate(SEQ.frames()):
        (folder / SEQ.frame_name(o, t, k, ext)).write_bytes(writer(i, frames[i]))
    doc = {**SEQ.to_dict(), "width_px": frames.shape[2], "height_px": frames.shape[1], "bit_depth": bits}
    (folder / "sequence.yaml").write_text(yaml.safe_dump(doc))
    return folder


def random_frames(bits, shape=(H, W), seed=0):
    full = 2**bits - 1
    return np.random.default_rng(seed).integers(0, full + 1, (SEQ.n_frames, *shape)).astype(
        np.uint8 if bits == 8 else np.uint16)


@pytest.mark.parametrize("bits", [8, 16])
def test_png_every_row_filter_decodes_exactly(tmp_path, bits):
    # full-range random samples: every byte value, every Paeth branch; each frame cycles
    # through the five filters starting at a different one (so row 0 sees all five)
    frames = random_frames(bits)

    def writer(i, img):
        return png_bytes(img, filters=[(i + j) % 5 for j in range(5)], idat_bytes=97)

    assert np.array_equal(imagecodecs.png_decode(writer(3, frames[3])), frames[3])  # libpng agrees with the writer
    stack = read_frames(frames_folder(tmp_path / "m", frames, writer, bits, "png"))
    assert stack.frames.dtype == frames.dtype and np.array_equal(stack.frames, frames)
    assert np.array_equal(read_frames(tmp_path / "m", threads=1).frames, frames)


def test_interlaced_png_is_read_through_libpng(tmp_path):
    frames = random_frames(16, shape=(H, 13))
    folder = frames_folder(tmp_path / "m", frames, lambda i, img: png_bytes(img, filters=(1, 4, 2, 3, 0),
                                                                             interlace=True), 16, "png")
    assert np.array_equal(read_frames(folder).frames, frames)


def png_errors(tmp_path, damage, bits=16):
    """The message for a folder whose frame y_014_02 is ``damage(png bytes, image)``."""
    frames = random_frames(bits)
    bad = SEQ.frame_index("y", 14, 2)
    folder = frames_folder(tmp_path / "m", frames, lambda i, img: damage(png_bytes(img, filters=(2,)), img)
                           if i == bad else png_bytes(img), bits, "png")
    with pytest.raises(FrameStackError) as info:
        read_frames(folder)
    msg = str(info.value)
    assert msg.startswith(str(folder / "y_014_02.png") + ": "), msg
    return msg


def test_damaged_png_is_refused_naming_the_file(tmp_path):
    assert "corrupt or unreadable PNG (truncated: the chunk at byte" in png_errors(tmp_path / "a", lambda d, img:
                                                                                    d[:len(d) // 2])
    assert "corrupt or unreadable PNG (truncated: no IEND chunk)" in png_errors(tmp_path / "b", lambda d, img: d[:-12])
    assert "corrupt or unreadable PNG (truncated: 20 bytes, no complete header)" in png_errors(tmp_path / "c",
                                                                                          lambda d, img: d[:20])
    assert "corrupt or unreadable PNG (no PNG signature)" in png_errors(tmp_path / "h", lambda d, img: b"GIF89a" + d)

    def flip(data, img):  # one bit of the image data (the first IDAT payload starts after tEXt)
        i = data.index(b"IDAT") + 30
        return data[:i] + bytes([data[i] ^ 0x10]) + data[i + 1:]
    assert "corrupt or unreadable PNG (image data: " in png_errors(tmp_path / "d", flip)

    def filter7(data, img):
        raw = bytearray(filtered_rows(img, (0,)))
        raw[5 * (2 * W + 1)] = 7
        return png_bytes(img, raw=bytes(raw))
    assert "corrupt or unreadable PNG (invalid filter type 7 in row 5)" in png_errors(tmp_path / "e", filter7)
    short = png_errors(tmp_path / "f", lambda d, img: png_bytes(img, raw=filtered_rows(img[:-1], (0,))))
    assert f"image data inflates to {11 * (2 * W + 1)} bytes, 20x12 px need {12 * (2 * W + 1)}" in short
    no_idat = png_errors(tmp_path / "g", lambda d, img: d[:d.index(b"IDAT") - 4] + png_chunk(b"IEND", b""))
    assert "corrupt or unreadable PNG (no image data (IDAT) before IEND)" in no_idat


def test_colour_and_low_depth_png_are_refused(tmp_path):
    def rgb(d, img):
        return imagecodecs.png_encode(np.zeros((H, W, 3), np.uint8))
    assert "expected a single-channel (grey) image, got a RGB PNG" in png_errors(tmp_path / "a", rgb, bits=8)
    for colour, name in [(3, "palette (colour-mapped)"), (4, "grey+alpha")]:
        msg = png_errors(tmp_path / f"c{colour}", lambda d, img, c=colour: png_bytes(img, header=(8, c)), bits=8)
        assert f"expected a single-channel (grey) image, got a {name} PNG" in msg
    msg = png_errors(tmp_path / "d", lambda d, img: png_bytes(img, header=(4, 0)), bits=8)
    assert "4-bit grey PNG, but sequence.yaml says bit_depth 8 (8-bit files)" in msg


def test_bmp_palette_row_padding_and_top_down_rows(tmp_path):
    frames = random_frames(8, shape=(H, 13))  # 13-byte rows are padded to 16 in the file
    inverted = (255 - np.arange(256, dtype=np.uint8))[:, None].repeat(3, 1)  # grey, but not the identity

    def writer(i, img):
        return bmp_bytes(img, palette=inverted, top_down=i % 2 == 1)

    stack = read_frames(frames_folder(tmp_path / "m", frames, writer, 8, "bmp"))
    assert stack.format == "bmp" and np.array_equal(stack.frames, 255 - frames)  # the palette is applied


def bmp_errors(tmp_path, damage, bits=8):
    frames = random_frames(8)
    bad = SEQ.frame_index("x", 15, 3)
    folder = frames_folder(tmp_path / "m", frames, lambda i, img: damage(bmp_bytes(img), img) if i == bad
                           else bmp_bytes(img), bits, "bmp")
    with pytest.raises(FrameStackError) as info:
        read_frames(folder)
    msg = str(info.value)
    assert msg.startswith(str(folder / "x_015_03.bmp") + ": "), msg
    return msg


def test_bad_bmp_is_refused_naming_the_file(tmp_path):
    assert "corrupt or unreadable BMP" in bmp_errors(tmp_path / "a", lambda d, img: d[:len(d) - 7])
    assert "corrupt or unreadable BMP" in bmp_errors(tmp_path / "b", lambda d, img: d[:30])
    assert "corrupt or unreadable BMP" in bmp_errors(tmp_path / "c", lambda d, img: b"not a bitmap at all")
    colour = bmp_errors(tmp_path / "d", lambda d, img: bmp_bytes(np.dstack([img, img // 2, img])))
    assert "expected a single-channel (grey) image, got shape (12, 20, 3)" in colour
    palette = np.random.default_rng(1).integers(0, 256, (256, 3)).astype(np.uint8)
    colour_palette = bmp_errors(tmp_path / "e", lambda d, img: bmp_bytes(img, palette=palette))
    assert "expected a single-channel (grey) image, got shape (12, 20, 3)" in colour_palette
    size = bmp_errors(tmp_path / "f", lambda d, img: bmp_bytes(np.zeros((H, W + 1), np.uint8)))
    assert "image is 21x12 px, sequence.yaml says 20x12" in size


def test_bmp_stack_must_be_8_bit(tmp_path):
    folder = write_folder(tmp_path / "m", bits=8, fmt="bmp")
    spec = yaml.safe_load((folder / "sequence.yaml").read_text())
    (folder / "sequence.yaml").write_text(yaml.safe_dump({**spec, "bit_depth": 12}))
    with pytest.raises(FrameStackError, match=r"x_012_00\.bmp: BMP frames are 8-bit \(BMP has no 16-bit grey form\)"):
        read_stack_spec(folder)
