"""The driver against the simulated control box: protocol, safety, faults, command files,
and moving the artefact through the planned thesis poses."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest
import serial

import fringecal.hexapod  # noqa: F401  (registers hexsim://)
from fringecal.hexapod import (
    HexapodDriver,
    HexapodFault,
    HexapodRig,
    PlatformMover,
    TargetRejected,
    load_hexapod_config,
)
from fringecal.hexapod.driver import read_command_file, write_command_file
from fringecal.hexapod.kinematics import inverse_kinematics
from fringecal.hexapod.planning import counts_from_lengths, frames_from_table, quantisation_bound
from fringecal.hexapod.protocol import frame
from fringecal.hexapod.simulator import get_controller
from fringecal.schemas import PosePlanTable, read_table

CFG = load_hexapod_config()
HOME = CFG.home_pose.vector
_ids = itertools.count()


def new_box(**opts) -> tuple[str, str]:
    """A fresh named simulated box: (url, name)."""
    name = f"test{next(_ids)}"
    query = "&".join(f"{k}={v}" for k, v in opts.items())
    return f"hexsim://{name}" + (f"?{query}" if query else ""), name


def counts_for(pose) -> np.ndarray:
    return counts_from_lengths(CFG, inverse_kinematics(CFG.platform, pose))


TARGET = HOME + np.array([120.0, -80.0, 60.0, 0.02, -0.01, 0.05])


# -- the simulated box itself ---------------------------------------------------------

def test_box_speaks_the_protocol():
    url, name = new_box()
    port = serial.serial_for_url(url)

    def ask(line):
        port.write(line if isinstance(line, bytes) else frame(line))
        return port.read_until(b"\n")

    assert ask("ID?") == frame(f"OK ID {name.upper()} 1.0 10000")
    assert ask("POS?") == frame("OK POS 5000 5000 5000 5000 5000 5000 IDLE")
    assert ask("FLY 3") == frame("ERR 1 unknown command 'FLY'")
    assert ask("MOVE 7 100") == frame("ERR 2 MOVE: leg must be 1..6, got 7")
    assert ask("MOVE 2 ten") == frame("ERR 2 MOVE: arguments must be integers, got '2 ten'")
    assert ask("MOVE 2 10001") == frame("ERR 3 leg 2 target 10001 outside 0..10000")
    assert ask(b"POS?*00\n").startswith(b"ERR 5 checksum mismatch")
    assert ask(b"POS?\r\n").startswith(b"OK POS")  # no checksum: accepted (terminal use)
    assert ask("MOVE 2 5400") == frame("OK MOVE 2 5400")
    assert ask("MOVE 3 5400").startswith(b"ERR 4 busy")
    port.sleep(1.0)  # 1 s at 10 mm/s: 10 mm = 200 counts of the 400
    assert ask("POS?") == frame("OK POS 5000 5200 5000 5000 5000 5000 BUSY")
    port.sleep(1.0)
    assert ask("POS?") == frame("OK POS 5000 5400 5000 5000 5000 5000 IDLE")
    assert ask("MOVEALL 5000 5000 5000 5000 5000 4000") == frame("OK MOVEALL 5000 5000 5000 5000 5000 4000")
    port.sleep(2.5)  # longest leg 1000 counts = 50 mm = 5 s; all legs arrive together
    assert ask("POS?") == frame("OK POS 5000 5200 5000 5000 5000 4500 BUSY")
    assert ask("STOP") == frame("OK STOP")
    port.sleep(5.0)
    assert ask("POS?") == frame("OK POS 5000 5200 5000 5000 5000 4500 IDLE")
    assert len(get_controller(name).log) == 16


def test_bad_url_options_are_refused():
    with pytest.raises(serial.SerialException, match="unknown option.*'speed'"):
        serial.serial_for_url("hexsim://x?speed=3")
    with pytest.raises(serial.SerialException, match="fault must be one of"):
        serial.serial_for_url("hexsim://?fault=fire")


# -- normal operation -----------------------------------------------------------------

def test_move_pose_reaches_the_target_without_wall_time():
    url, name = new_box()
    t0 = time.monotonic()
    with HexapodDriver.open(url, CFG) as drv:
        read = drv.move_pose(TARGET)
    box = get_controller(name)
    assert read.tolist() == counts_for(TARGET).tolist()
    assert drv.sent[:3] == ["ID?", "POS?", "MOVEALL " + " ".join(map(str, counts_for(TARGET)))]
    assert set(drv.sent[3:]) == {"POS?"}
    assert box.motion_log() == [drv.sent[2]]
    travel_s = np.max(np.abs(counts_for(TARGET) - 5000)) / 20 / 10
    assert travel_s <= box.now() <= travel_s + 2 * CFG.serial.poll_interval_s
    assert time.monotonic() - t0 < 5.0  # virtual clock: no real waiting for a ~20 s move
    # the pose from the encoders is the target within the count rounding
    assert np.all(np.abs(drv.pose - TARGET) <= quantisation_bound(CFG, TARGET) * 1.05 + 1e-12)


def test_home_reference_run_and_single_leg_move():
    url, name = new_box()
    with HexapodDriver.open(url, CFG) as drv:
        assert drv.home().tolist() == [0] * 6
        assert drv.move_leg(3, 150).tolist() == [0, 0, 150, 0, 0, 0]
    assert get_controller(name).motion_log() == ["HOME", "MOVE 3 150"]


# -- safety: refused targets send nothing -----------------------------------------------

def test_out_of_stroke_target_is_refused_before_anything_is_sent():
    url, name = new_box()
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(TargetRejected, match=r"outside the stroke 0..10000 counts.*leg 2: 10050 counts"):
        drv.move_counts([5000, 10050, 5000, 5000, 5000, 5000])
    with pytest.raises(TargetRejected, match="leg 6: -1 counts"):
        drv.move_leg(6, -1)
    with pytest.raises(TargetRejected, match="pose outside the workspace: leg .* stroke"):
        drv.move_pose(HOME + np.array([0, 0, 300.0, 0, 0, 0]))
    assert get_controller(name).motion_log() == []
    assert drv.faulted is None  # nothing moved: the driver stays usable
    drv.move_pose(TARGET)
    assert len(get_controller(name).motion_log()) == 1


def test_a_move_through_forbidden_poses_is_refused():
    """Leg counts all in stroke, but the pose they give breaks the joint limits."""
    url, name = new_box()
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(TargetRejected, match="of the way to the target leaves the workspace: top joint 2 at"):
        drv.move_counts([9500, 500, 9500, 500, 9500, 500])
    assert get_controller(name).motion_log() == []


# -- faults: one clear error, STOP, nothing more ---------------------------------------

def test_unplugged_port():
    url, name = new_box(fault="unplugged")
    with pytest.raises(HexapodFault, match="cannot open the hexapod controller at hexsim://.*unplugged") as e:
        HexapodDriver.open(url, CFG)
    assert e.value.kind == "unplugged"
    assert get_controller(name).log == []


@pytest.mark.parametrize("fault, kind, message", [
    ("timeout", "timeout", r"no reply to 'POS\?' within 1 s"),
    ("garbled", "garbled", r"bad reply to 'POS\?': checksum mismatch"),
])
def test_link_faults_during_a_move_stop_everything(fault, kind, message):
    url, name = new_box()
    drv = HexapodDriver.open(url, CFG)  # ID? answered
    serial.serial_for_url(f"hexsim://{name}?fault={fault}&after=4")  # arm: POS?, MOVEALL, POS?, POS? answered
    with pytest.raises(HexapodFault, match=message) as e:
        drv.move_pose(TARGET)
    assert e.value.kind == kind and str(e.value).startswith("hexapod stopped:")
    box = get_controller(name)
    received = [t.split("*")[0] for _, t in box.log]
    assert received[-2:] == ["POS?", "STOP"]
    assert box.motion_log() == [drv.sent[2]]
    # latched: the next request raises at once and sends nothing
    n = len(box.log)
    with pytest.raises(HexapodFault, match="faulted earlier") as e2:
        drv.move_pose(HOME)
    assert e2.value.kind == "latched"
    with pytest.raises(HexapodFault, match="faulted earlier"):
        drv.positions()
    assert len(box.log) == n


def test_encoder_mismatch_stops_and_latches():
    url, name = new_box(fault="mismatch", leg=4, offset=-35)
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(HexapodFault, match=r"encoders disagree with the target beyond 2 counts \(leg 4 -35\)") as e:
        drv.move_pose(TARGET)
    assert e.value.kind == "mismatch"
    box = get_controller(name)
    assert box.motion_log() == [drv.sent[2]]
    assert box.log[-1][1].startswith("STOP")
    with pytest.raises(HexapodFault):
        drv.move_pose(HOME)
    assert len(box.motion_log()) == 1


def test_stalled_leg_is_detected():
    url, name = new_box(fault="stall", leg=2)
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(HexapodFault, match=r"no encoder progress for 25 polls") as e:
        drv.move_pose(TARGET)
    assert e.value.kind == "stall"
    box = get_controller(name)
    assert box.log[-1][1].startswith("STOP") and not box.busy
    assert len(box.motion_log()) == 1


def test_port_disconnected_mid_move():
    url, name = new_box(fault="disconnect", after=5)
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(HexapodFault, match="serial port error during 'POS\\?'.*disconnected") as e:
        drv.move_pose(TARGET)
    assert e.value.kind == "io"
    assert len(get_controller(name).motion_log()) == 1


def test_box_with_another_count_range_is_refused_at_open():
    url, name = new_box(counts_per_mm=40)
    with pytest.raises(HexapodFault, match=r"count range 0..20000 differs from the config's 0..10000"):
        HexapodDriver.open(url, CFG)
    assert get_controller(name).motion_log() == []


# -- command files (section 4.5.1) ------------------------------------------------------

def test_command_file_round_trip(tmp_path):
    poses = [HOME + np.array([d, 0, 0, 0, 0, 0]) for d in (200.0, -200.0, 0.0)]
    counts = np.array([counts_for(p) for p in poses])
    path = write_command_file(tmp_path / "moves.txt", counts, ["+200 x", "-200 x", "home"])
    assert [c.keyword for _, c in read_command_file(path)] == ["MOVEALL"] * 3
    url, name = new_box()
    with HexapodDriver.open(url, CFG) as drv:
        results = drv.run_command_file(path)
    assert np.array(results).tolist() == counts.tolist()
    assert get_controller(name).motion_log() == [f"MOVEALL {' '.join(map(str, c))}" for c in counts]


def test_command_file_is_checked_whole_before_anything_moves(tmp_path):
    ok = counts_for(TARGET)
    path = tmp_path / "bad.txt"
    path.write_text(f"# test\nMOVEALL {' '.join(map(str, ok))}\n\nMOVE 2 5100\nMOVE 3 12000  # too far\n")
    url, name = new_box()
    drv = HexapodDriver.open(url, CFG)
    with pytest.raises(TargetRejected, match=r"bad.txt, line 5 \(MOVE 3 12000\): target outside the stroke"):
        drv.run_command_file(path)
    path.write_text("MOVEALL 1 2 3\n")
    with pytest.raises(ValueError, match=r"bad.txt, line 1: MOVEALL takes 6 argument\(s\), got 3"):
        drv.run_command_file(path)
    assert get_controller(name).motion_log() == []


# -- the acquisition interface ----------------------------------------------------------

def test_moving_through_the_planned_thesis_poses_reaches_them(thesis_dir):
    """Must-show: simulated moves through table 6-1 return reached artefact poses equal to
    the planned ones within the effect of the encoder resolution."""
    rig = HexapodRig.from_config(CFG)
    planned = frames_from_table(read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable))
    url, name = new_box()
    with PlatformMover.open(url, rig) as mover:
        moves = [mover.move_artefact_to(T) for T in planned]
        final = mover.reached_artefact_pose()
    assert len(get_controller(name).motion_log()) == 12
    for mv, T in zip(moves, planned):
        assert mv.planned is T
        assert mv.counts_read.tolist() == mv.counts_target.tolist()
        bound = quantisation_bound(CFG, mv.platform_pose_planned) * 1.05 + 1e-9
        assert np.all(np.abs(mv.platform_pose_reached - mv.platform_pose_planned) <= bound)
        # artefact origin: |dp| + |d angles| x lever arm from the TOP origin
        lever = np.linalg.norm(rig.T_top_artefact.t)
        assert mv.translation_error_mm <= np.linalg.norm(bound[:3]) + bound[3:].sum() * lever
        assert mv.rotation_error_rad <= bound[3:].sum()
        assert mv.translation_error_mm < 0.1 and mv.rotation_error_rad < 1e-4
    assert final.t == pytest.approx(moves[-1].reached.t, abs=1e-9)


def test_mover_refuses_an_unreachable_artefact_pose(thesis_dir):
    rig = HexapodRig.from_config(CFG)
    T = frames_from_table(read_table(thesis_dir / "poses_scanner1_table6-1.csv", PosePlanTable))[0]
    far = type(T)(T.t + np.array([0.0, 0.0, -1000.0]), T.angles)
    url, name = new_box()
    with PlatformMover.open(url, rig) as mover:
        with pytest.raises(TargetRejected, match="outside the workspace"):
            mover.move_artefact_to(far)
    assert get_controller(name).motion_log() == []
