"""Measurement stores: atomic zarr v3 writes, refusal of incomplete or corrupt stores,
atomic variable updates, plain xarray.open_zarr."""

import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from fringecal.fringe.decode import decode
from fringecal.fringe.measurement import decode_to_store, measurement_dataset
from fringecal.fringe.sequence import FringeSequence
from fringecal.store import COMPLETE_ATTR, StoreError, copy_store, is_complete, open_store, write_store
from fringecal.tasks.refs import digest_path

SEQ = FringeSequence((8, 7, 6, 4), 3)


def frames_for(h=24, w=40, seed=0):
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0:h, 0:w]
    w_x, w_y = (u / w - 0.5) * 6, (v / h - 0.5) * 6
    out = [1000 + 700 * np.cos(t * ww + 2 * np.pi * k / 3) + rng.normal(0, 5, (h, w))
           for ww in (w_x, w_y) for t in SEQ.fringe_counts for k in range(3)]
    return np.clip(np.rint(out), 0, 4095).astype(np.uint16), w_x, w_y


def test_store_round_trip_with_plain_open_zarr(tmp_path):
    frames, w_x, w_y = frames_for()
    out = tmp_path / "m.zarr"
    res = decode_to_store(frames, SEQ, out, attrs={"scanner": "scanner1", "measurement": "3", "config_digest": "d" * 64},
                          full_scale=4095, store_frames=True, extra_vars={"true_tau_x": w_x.astype(np.float32)})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # consolidated metadata: no fallback warning
        ds = xr.open_zarr(out)
    assert {"tau_x", "tau_y", "modulation_x", "modulation_y", "phase_error_x", "phase_error_y", "texture", "valid",
            "frames", "true_tau_x"} <= set(ds.data_vars)
    assert ds.tau_x.dtype == np.float32 and ds.valid.dtype == bool and ds.tau_x.dims == ("v", "u")
    assert ds.tau_x.attrs["units"] == "rad" and ds.attrs["sequence"] == SEQ.to_dict()
    assert ds.attrs["scanner"] == "scanner1" and ds.attrs[COMPLETE_ATTR] is True
    assert ds.attrs["decoder"]["full_scale_dn"] == 4095 and 0.9 < ds.attrs["summary"]["valid_fraction"] <= 1
    np.testing.assert_array_equal(ds.tau_x.values, res.tau["x"])
    np.testing.assert_array_equal(ds.frames.values, frames)
    assert list(ds.orientation.values[:4]) == ["x"] * 4 and int(ds.fringes[3]) == 7
    assert np.abs(ds.tau_y.values - w_y).max() < 0.01
    enc = ds.tau_x.encoding
    assert enc["chunks"] == (24, 40) and enc["compressors"][0].cname.value == "lz4"
    assert json.loads((out / "zarr.json").read_text())["zarr_format"] == 3


def test_big_maps_are_chunked_512(tmp_path):
    ds = xr.Dataset({"tau_x": (("v", "u"), np.zeros((1100, 600), np.float32))}, attrs={"a": 1})
    write_store(tmp_path / "b.zarr", ds)
    assert open_store(tmp_path / "b.zarr").tau_x.encoding["chunks"] == (512, 512)


def test_attributes_must_be_json_native(tmp_path):
    ds = xr.Dataset({"a": (("v", "u"), np.zeros((2, 2), np.float32))}, attrs={"when": np.datetime64("2020-01-01")})
    with pytest.raises(StoreError, match="attributes must be JSON-native"):
        write_store(tmp_path / "m.zarr", ds)
    assert not (tmp_path / "m.zarr").exists() and list(tmp_path.iterdir()) == []


def test_crash_mid_write_leaves_no_store(tmp_path, monkeypatch):
    """An exception while the arrays are being written: nothing at the final name."""
    import fringecal.store as store

    frames, *_ = frames_for()
    res = decode(frames, SEQ, full_scale=4095)
    ds = measurement_dataset(res, {"scanner": "s"})

    def crash(tmp):
        raise KeyboardInterrupt("power cut")

    monkeypatch.setattr(store, "_finalise", crash)
    with pytest.raises(KeyboardInterrupt):
        write_store(tmp_path / "m.zarr", ds)
    assert not (tmp_path / "m.zarr").exists() and list(tmp_path.iterdir()) == []


def test_killed_writer_leaves_only_a_hidden_temporary_that_is_refused(tmp_path):
    """A process killed mid-write (os._exit after the arrays, before the marker)."""
    code = f"""
import os, numpy as np, xarray as xr
import fringecal.store as store
store._finalise = lambda tmp: os._exit(9)
store.write_store({str(tmp_path / 'm.zarr')!r}, xr.Dataset({{"tau_x": (("v", "u"), np.ones((30, 30), np.float32))}}))
"""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    proc = subprocess.run([sys.executable, "-c", code], cwd=str(tmp_path), capture_output=True, env=env)
    assert proc.returncode == 9
    assert not (tmp_path / "m.zarr").exists()
    (leftover,) = tmp_path.iterdir()
    assert leftover.name.startswith(".m.zarr.tmp-")
    assert xr.open_zarr(leftover, consolidated=False).tau_x.shape == (30, 30)  # data are there...
    with pytest.raises(StoreError, match=r"\.m\.zarr\.tmp-.*: incomplete store \(no completion marker"):
        open_store(leftover)  # ...but it is never taken for a complete store
    assert not is_complete(leftover)


def test_store_written_without_marker_is_refused(tmp_path):
    out = tmp_path / "m.zarr"
    xr.Dataset({"tau_x": (("v", "u"), np.ones((4, 4), np.float32))}).to_zarr(out, zarr_format=3, consolidated=False)
    with pytest.raises(StoreError, match=r"m\.zarr: incomplete store"):
        open_store(out)


def test_corrupt_stores_are_refused_naming_store_and_variable(tmp_path):
    frames, *_ = frames_for()
    out = tmp_path / "m.zarr"
    decode_to_store(frames, SEQ, out, full_scale=4095)
    assert is_complete(out)
    chunk = out / "phase_error_y" / "c" / "0" / "0"
    data = chunk.read_bytes()
    chunk.write_bytes(data[: len(data) // 2])
    with pytest.raises(StoreError, match=r"m\.zarr: corrupt store: variable 'phase_error_y' has 1 chunk files / "):
        open_store(out)
    chunk.unlink()
    with pytest.raises(StoreError, match=r"variable 'phase_error_y' has 0 chunk files"):
        open_store(out)
    (out / "zarr.json").write_text("{ not json")
    with pytest.raises(StoreError, match=r"m\.zarr: corrupt store metadata"):
        open_store(out)
    with pytest.raises(StoreError, match=r"nothing\.zarr: no such store"):
        open_store(tmp_path / "nothing.zarr")


def test_one_flipped_byte_is_found_on_open_and_named(tmp_path):
    """Same size, same dates, one bit of one chunk changed: the content digest finds it
    (issue 31: a flipped byte of a decoded store moved the ball-bar error silently)."""
    frames, *_ = frames_for()
    out = tmp_path / "m.zarr"
    decode_to_store(frames, SEQ, out, full_scale=4095)
    chunk = out / "tau_x" / "c" / "0" / "0"
    st = chunk.stat()
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x01
    chunk.write_bytes(bytes(data))
    os.utime(chunk, ns=(st.st_atime_ns, st.st_mtime_ns))  # the mtime put back
    assert is_complete(out)  # the manifest's sizes agree
    for read in (open_store, lambda p: copy_store(p, tmp_path / "copy.zarr")):
        with pytest.raises(StoreError, match=r"m\.zarr/tau_x/c/0/0: changed since the store was written"):
            read(out)
    assert not (tmp_path / "copy.zarr").exists()


def test_a_store_without_digests_is_checked_by_reading_every_chunk(tmp_path):
    """A store written before stores carried digests opens (sizes checked); verify=True
    still reads every chunk."""
    frames, *_ = frames_for()
    out = tmp_path / "m.zarr"
    decode_to_store(frames, SEQ, out, full_scale=4095)
    meta = json.loads((out / "zarr.json").read_text())
    del meta["attributes"]["fringecal_digests"]
    (out / "zarr.json").write_text(json.dumps(meta))
    chunk = out / "texture" / "c" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[20:] = bytes(len(data) - 20)  # same size, damaged content: only reading finds it
    chunk.write_bytes(bytes(data))
    open_store(out)
    with pytest.raises(StoreError, match=r"m\.zarr: variable 'texture' is corrupt"):
        open_store(out, verify=True)


def test_copy_store_links_chunks_and_is_atomic(tmp_path, monkeypatch):
    import fringecal.store as store

    frames, *_ = frames_for()
    src = tmp_path / "m.zarr"
    decode_to_store(frames, SEQ, src, attrs={"scanner": "s1"}, full_scale=4095)
    (src / ".m.zarr.tmp-leftover").mkdir()  # hidden entries are not copied
    dst = tmp_path / "run" / "m.zarr"
    dst.parent.mkdir()
    real = store._swap_in
    monkeypatch.setattr(store, "_swap_in", lambda tmp, path: (_ for _ in ()).throw(RuntimeError("crash")))
    with pytest.raises(RuntimeError):
        copy_store(src, dst)
    assert list(dst.parent.iterdir()) == []  # nothing half-copied
    monkeypatch.setattr(store, "_swap_in", real)
    copy_store(src, dst)
    assert digest_path(dst) == digest_path(src) and is_complete(dst)
    assert open_store(dst, verify=True).attrs["scanner"] == "s1"
    chunk = next(p for p in (src / "tau_x").rglob("*") if p.is_file() and p.name != "zarr.json")
    assert os.stat(chunk).st_ino == os.stat(dst / chunk.relative_to(src)).st_ino  # a hard link
    assert not [p for p in dst.iterdir() if p.name.startswith(".")]
    with pytest.raises(StoreError, match="no such store"):
        copy_store(tmp_path / "nothing.zarr", tmp_path / "x.zarr")


def test_overwrite_replaces_a_complete_store(tmp_path):
    out = tmp_path / "m.zarr"
    write_store(out, xr.Dataset({"a": (("v", "u"), np.zeros((3, 3), np.float32))}, attrs={"n": 1}))
    write_store(out, xr.Dataset({"b": (("v", "u"), np.ones((3, 3), np.float32))}, attrs={"n": 2}))
    ds = open_store(out)
    assert list(ds.data_vars) == ["b"] and ds.attrs["n"] == 2
    assert [p.name for p in tmp_path.iterdir()] == ["m.zarr"]
    with pytest.raises(StoreError, match="exists"):
        write_store(out, ds, overwrite=False)
