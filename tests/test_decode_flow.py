"""The decode flow and `fringecal decode` on tiny frame folders (own formula, 16-bit TIFF/PNG)."""

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fringecal.flows.cli import app
from fringecal.fringe.importer import write_frames
from fringecal.fringe.sequence import FringeSequence
from fringecal.store import open_store
from fringecal.tasks.refs import Ref

runner = CliRunner()
SEQ = FringeSequence((8, 7, 6, 4), 3)
H, W = 10, 16


def measurement(folder, shift=0.0, fmt="tif", scanner="scanner1", name="1"):
    v, u = np.mgrid[0:H, 0:W]
    w_x, w_y = (u / W - 0.5) * 6 + shift, (v / H - 0.5) * 6
    frames = np.stack([30000 + 20000 * np.cos(t * w + 2 * np.pi * k / 3)
                       for w in (w_x, w_y) for t in SEQ.fringe_counts for k in range(3)])
    write_frames(folder, np.rint(frames).astype(np.uint16), SEQ, 16, fmt=fmt, scanner=scanner, measurement=name)
    return w_x, w_y


@pytest.mark.flow
def test_decode_flow_one_task_per_measurement_and_caching(prefect_harness, tmp_path):
    from fringecal.flows.decode_flow import decode_flow

    truths = [measurement(tmp_path / "frames" / f"m{i}", shift=0.1 * i, name=str(i)) for i in range(2)]
    dirs = [str(tmp_path / "frames" / f"m{i}") for i in range(2)]
    outs = [str(tmp_path / "stores" / f"m{i}.zarr") for i in range(2)]
    (tmp_path / "stores").mkdir()
    refs = decode_flow(dirs, outs)
    assert all(isinstance(r, Ref) and r.exists_unchanged() for r in refs)
    for ref, (w_x, _) in zip(refs, truths):
        ds = open_store(ref.path)
        assert np.abs(ds.tau_x.values - w_x).max() < 1e-3 and ds.attrs["frames_digest"]
    written = (Path(outs[0]) / "zarr.json").stat().st_mtime_ns

    again = decode_flow(dirs, outs)  # cache hits: nothing rewritten
    assert again == refs and (Path(outs[0]) / "zarr.json").stat().st_mtime_ns == written

    import shutil

    shutil.rmtree(outs[1])  # a deleted store is rebuilt despite the cache
    rebuilt = decode_flow(dirs, outs)
    assert open_store(outs[1]).attrs["measurement"] == "1" and rebuilt[0] == refs[0]

    changed = decode_flow(dirs, outs, settings={"min_modulation": 0.25, "max_phase_error": 0.3})
    assert open_store(outs[0]).attrs["decoder"]["min_modulation"] == 0.25 and changed[0].digest != refs[0].digest


def test_cli_decode_json_and_folder_of_measurements(tmp_path):
    """No Prefect server configured: the stores are decoded directly."""
    measurement(tmp_path / "run" / "a", fmt="png", name="a")
    measurement(tmp_path / "run" / "b", fmt="tif", name="b")
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "run"), "--out", str(tmp_path / "stores"),
                              "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout[res.stdout.index("{"):])
    assert [r["measurement"] for r in doc["stores"]] == ["a", "b"]
    assert all(r["valid_fraction"] == 1.0 and r["median_phase_error_x_rad"] < 1e-3 for r in doc["stores"])
    assert (tmp_path / "stores" / "a.zarr").is_dir() and (tmp_path / "stores" / "b.zarr").is_dir()


def test_cli_decode_corrupt_frame_found_while_decoding(tmp_path):
    measurement(tmp_path / "m", fmt="png")
    (tmp_path / "m" / "y_006_01.png").write_bytes(b"\x89PNG broken")
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "m.zarr")])
    assert res.exit_code == 2, res.output
    assert "y_006_01.png: corrupt or unreadable PNG" in res.output and not (tmp_path / "m.zarr").exists()


def test_cli_decode_bad_input_fails_before_prefect(tmp_path):
    measurement(tmp_path / "m")
    (tmp_path / "m" / "x_008_02.tif").unlink()
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "m.zarr")])
    assert res.exit_code == 2 and "x_008_02.tif: missing frame (1 of 24 frames missing" in res.output
    (tmp_path / "empty").mkdir()
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "empty"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "neither a measurement folder" in res.output
    res = runner.invoke(app, ["decode", "--frames", str(tmp_path / "m"), "--out", str(tmp_path / "m.zarr"),
                              "--min-modulation", "2"])
    assert res.exit_code == 2 and "--min-modulation: Input should be less than or equal to 1" in res.output
