"""Where a ball-bar length's error comes from, over the kept run directories of
``benchmarks/length_coverage.py --keep --workdir W``: per position, the error with the
calibrated rig (``verification.json``), the error with the TRUE rig (the evaluate step's
``verification_true_params``: the sphere fits alone) and their difference (the
calibration's part), each against the budget's stated term (``sphere fits``,
``calibration``). A mean beyond its standard error (sd / sqrt(n)) is a bias the budget
does not hold.

    PYTHONPATH=. python benchmarks/coverage_split.py W [W2 ...]
"""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

rows = []
for d in sorted(Path(p) for a in sys.argv[1:] for p in Path(a).glob("*-seed*")):
    if not (d / "verification.json").exists():
        continue
    if not (d / "evaluation.json").exists():
        subprocess.run([str(Path(sys.executable).with_name("fringecal")), "step", "evaluate", "--run", str(d)], capture_output=True)
    ev = json.loads((d / "evaluation.json").read_text())["verification_true_params"]
    tr = {p["measurement"]: p["error_mm"] for p in ev["positions"]}
    ver = json.loads((d / "verification.json").read_text())["uncertainty"]
    for length in ver["lengths"]:
        m = length["measurement"]
        rows.append((d.name, m, length["error_mm"], tr.get(m, np.nan), length["u_mm"], length["budget_mm"].get("sphere fits", 0), length["budget_mm"].get("calibration", 0)))
for m in sorted({r[1] for r in rows}):
    R = np.array([r[2:] for r in rows if r[1] == m])
    e, et, u, uf, uc = R.T
    print(f"{m}: n={len(e)} calibrated err mean {1000*e.mean():+.1f} um rms z {np.sqrt(np.mean((e/u)**2)):.2f} | "
          f"true-rig err mean {1000*np.nanmean(et):+.1f} sd {1000*np.nanstd(et):.1f} vs u_fits {1000*np.sqrt(np.mean(uf**2)):.1f} | "
          f"calibration part (err - true-rig err) mean {1000*np.nanmean(e-et):+.1f} sd {1000*np.nanstd(e-et):.1f} vs u_cal {1000*np.sqrt(np.mean(uc**2)):.1f}")
