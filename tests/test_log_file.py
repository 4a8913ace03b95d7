"""The run's log file (:mod:`fringecal.flows.prefect_logs`): fringecal's info lines --
such as the bundle step's share of each sensor's format its control points covered --
reach ``fringecal.log`` but not the terminal, its warnings both, at Prefect's quiet
level (``PREFECT_LOGGING_LEVEL`` WARNING leaves the root logger at WARNING)."""

import logging
import sys

from fringecal.flows import prefect_logs


def test_info_lines_reach_the_log_file_and_warnings_the_terminal_too(tmp_path, capsys):
    root = logging.getLogger()
    terminal = logging.StreamHandler(sys.stderr)  # stands for Prefect's console handler
    root.addHandler(terminal)
    level = root.level
    root.setLevel(logging.WARNING)
    bundle = logging.getLogger("fringecal.steps.bundle")
    ours = logging.getLogger("fringecal")
    before = ours.level
    try:
        path = prefect_logs.to_file(tmp_path / "fringecal.log")
        bundle.info("image plane observed by the control points: C1 62 %, P1 36 %")
        bundle.warning("the control points covered less than 20 % of the image of P9 (12 %)")
        logging.getLogger("fringecal.other").debug("not kept")
        prefect_logs.restore()
    finally:
        prefect_logs.restore()
        root.removeHandler(terminal)
        root.setLevel(level)
    text = path.read_text()
    assert "INFO    | fringecal.steps.bundle - image plane observed by the control points: C1 62 %, P1 36 %" in text
    assert "WARNING | fringecal.steps.bundle - the control points covered less than 20 %" in text
    assert "not kept" not in text
    err = capsys.readouterr().err
    assert err.splitlines() == ["warning: the control points covered less than 20 % of the image of P9 (12 %)"]
    assert ours.level == before  # restore() puts the level back
