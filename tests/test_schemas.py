"""Every bad-input class of the table contracts gives one clear message."""

import pytest

from fringecal.artefact import Artefact, load_artefact, load_rods
from fringecal.rig import load_rig
from fringecal.schemas import (
    ArtefactTable,
    PosesTable,
    SensorParametersTable,
    SphereCentresTable,
    TableError,
    ThermalLogTable,
    read_table,
)


def write(tmp_path, text, name="t.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def message(tmp_path, text, model, name="t.csv"):
    p = write(tmp_path, text, name)
    with pytest.raises(TableError) as info:
        read_table(p, model)
    return str(info.value)


def test_missing_column_names_file_and_columns(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm\n1,0,0,0\n", ArtefactTable, "art.csv")
    assert "art.csv" in msg and "missing required column(s) ['diameter_mm']" in msg


def test_non_number_names_line_and_column(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,0,0,0,50\n2,1.5,abc,0,50\n", ArtefactTable)
    assert "line 3, column 'y_mm': value 'abc' is not a number" in msg


def test_nan_and_empty_cells(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,nan,0,0,50\n2,1,,0,50\n", ArtefactTable)
    assert "line 2, column 'x_mm': value is missing" in msg
    assert "line 3, column 'y_mm': value is missing" in msg


def test_duplicate_ids(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,0,0,0,50\n2,1,0,0,50\n1,2,0,0,50\n", ArtefactTable)
    assert "line 4, column 'sphere_id': value '1' is a duplicate (first on line 2)" in msg
    msg = message(tmp_path, "measurement,scanner,sphere_id,x_mm,y_mm,z_mm\nm1,s1,5,0,0,0\nm1,s1,5,1,1,1\nm1,s2,5,1,1,1\n",
                  SphereCentresTable)
    assert "line 3" in msg and "duplicate {'measurement': 'm1', 'scanner': 's1', 'sphere_id': '5'} (first on line 2)" in msg
    assert "line 4" not in msg


def test_range_rules(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,0,0,0,-50\n", ArtefactTable)
    assert "line 2, column 'diameter_mm': value -50.0 must be > 0" in msg
    msg = message(tmp_path, "measurement,scanner,tx_mm,ty_mm,tz_mm,omega_rad,phi_rad,kappa_rad,rms_mm,n_spheres\n"
                            "1,s,0,0,0,0,0,0,0.1,2\n", PosesTable)
    assert "column 'n_spheres': value 2 must be >= 3" in msg
    msg = message(tmp_path, "time_s,temperature_c,length_mm\n0,20,593.4\n10,400,593.4\n", ThermalLogTable)
    assert "line 3, column 'temperature_c'" in msg and "must be <= 150" in msg


def test_all_problems_reported_at_once(tmp_path):
    msg = message(tmp_path, "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,a,0,0,50\n2,0,b,0,0\n", ArtefactTable)
    assert "3 problem(s)" in msg


def test_sensor_table_flags_and_roles(tmp_path, thesis_dir):
    text = (thesis_dir / "sensors_refined_table6-8.csv").read_text().splitlines()
    bad = text[:2] + [text[2].replace(",projector,", ",lidar,")] + [text[3].replace("true", "maybe", 1)] + text[4:]
    msg = message(tmp_path, "\n".join(bad) + "\n", SensorParametersTable)
    assert "line 3, column 'role'" in msg and "must be one of" in msg
    assert "line 4, column 'free_x0': value 'maybe' is not true/false" in msg


def test_scanner_without_projector(tmp_path, thesis_dir):
    text = (thesis_dir / "sensors_refined_table6-8.csv").read_text().splitlines()
    p = write(tmp_path, "\n".join(text[:2] + text[3:]) + "\n")  # drop P1
    with pytest.raises(TableError, match=r"scanner 'scanner1' needs one camera and one projector, found \['camera'\]"):
        load_rig(p)


def test_rods_must_name_known_spheres(tmp_path, thesis_artefact):
    p = write(tmp_path, "rod_id,sphere_a,sphere_b,length_mm\n7,1,2,599.9\n8,1,99,600\n9,3,3,600\n10,2,1,600\n", "rods.csv")
    with pytest.raises(TableError) as info:
        load_rods(p, thesis_artefact)
    msg = str(info.value)
    assert "rods.csv" in msg
    assert "line 3, column 'sphere_b': sphere '99' is not in artefact" in msg
    assert "line 4, column 'sphere_b': rod '9' joins sphere '3' to itself" in msg
    assert "line 5, column 'sphere_a, sphere_b': spheres ['1', '2'] are already joined (line 2)" in msg


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(TableError, match="file not found"):
        read_table(tmp_path / "nope.csv", ArtefactTable)
    p = tmp_path / "bin.csv"
    p.write_bytes(b"\xff\xfe\x00\x01garbage")
    with pytest.raises(TableError, match="bin.csv"):
        read_table(p, ArtefactTable)


def test_duplicate_ids_in_code_paths():
    with pytest.raises(ValueError, match=r"duplicate sphere ids \['1'\]"):
        Artefact(("1", "1"), [[0, 0, 0], [1, 1, 1]], [50, 50])


def test_good_tables_read_with_text_ids(thesis_dir):
    art = load_artefact(thesis_dir / "artefact_cmm2.csv")
    assert art.ids[:3] == ("1", "2", "3")
    bb = load_artefact(thesis_dir / "ballbar.csv")
    assert bb.ids == ("A", "B")


def test_a_table_validated_before_is_a_copy_of_its_result_and_a_bad_one_is_named_every_time(tmp_path, monkeypatch):
    """Validations are kept by content: the same cells under another file name give the
    earlier result without validating again, as a copy the caller may change; a table
    that fails is validated, and named, each time."""
    import fringecal.schemas.tables as tables

    from collections import OrderedDict

    monkeypatch.setattr(tables, "_VALIDATED", OrderedDict())  # what earlier tests validated
    runs = []
    real = tables._validate
    monkeypatch.setattr(tables, "_validate", lambda df, model, source: runs.append(source) or real(df, model, source))
    good = "sphere_id,x_mm,y_mm,z_mm,diameter_mm\n1,0,0,0,50\n2,1.5,2,0,50\n"
    first = read_table(write(tmp_path, good, "a.csv"), ArtefactTable)
    first.loc[0, "x_mm"] = 99.0  # the caller's copy: the kept result does not change
    again = read_table(write(tmp_path, good, "b.csv"), ArtefactTable)
    assert runs == [str(tmp_path / "a.csv")] and again.loc[0, "x_mm"] == 0.0
    assert again.equals(read_table(tmp_path / "a.csv", ArtefactTable)) and len(runs) == 1
    read_table(write(tmp_path, good.replace("1.5", "1.25"), "c.csv"), ArtefactTable)  # one cell differs
    assert len(runs) == 2
    bad = good.replace("1.5", "abc")
    for name in ("d.csv", "e.csv"):
        with pytest.raises(TableError, match=f"{name}.*line 3, column 'y_mm'|line 3, column 'x_mm'"):
            read_table(write(tmp_path, bad, name), ArtefactTable)
    assert runs[-2:] == [str(tmp_path / "d.csv"), str(tmp_path / "e.csv")]
