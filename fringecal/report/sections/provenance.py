"""Provenance: what made the run (configuration, code, inputs, packages) and the
digests of the calibration files handed out."""

from __future__ import annotations

import hashlib
from pathlib import Path

from fringecal.report.rundata import SOURCES, Missing, RunData
from fringecal.report.tables import table

__all__ = ["build"]


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _inputs(inputs: dict) -> list[tuple]:
    """(path, SHA-256) of each input; the manifest holds a digest or ``{"path", "sha256"}``."""
    rows = []
    for path, digest in inputs.items():
        if isinstance(digest, dict):
            path, digest = digest.get("path", path), digest.get("sha256", "")
        rows.append((path, digest))
    return rows


def build(run: RunData, execution: dict) -> dict:
    """The manifest's digests, versions, inputs and configuration, the execution and the
    calibration files' SHA-256; ``missing`` says why when there is no manifest."""
    import yaml

    rd = run.rd
    out = {"started": execution.get("created_utc") or "not recorded", "command": execution.get("command"),
           "files": [(f.rel, _sha256(f.path)) for f in (rd.calibration.xml, rd.calibration) if f.path.is_file()],
           "missing": None}
    try:
        man = run.json(rd.manifest)
    except Missing as why:
        return out | {"missing": f"Not available: {why}."}
    src = man.get("source")
    cfg = man.get("config")
    return out | {
        "config_digest": man.get("config_digest", "n/a"), "code_digest": man.get("code_digest") or None,
        "source": SOURCES.get(src, src) if src else None,
        "versions": table(["Package", "Version"], sorted((man.get("versions") or {}).items()), left=2),
        "inputs": _inputs(man.get("inputs") or {}),
        "config": None if cfg is None else yaml.safe_dump(cfg, sort_keys=False, allow_unicode=True,
                                                           default_flow_style=False)}
