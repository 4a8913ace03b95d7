"""What the decoder's phase-ripple step finds and corrects, and what it costs.

One measurement of the thesis artefact (scanner 1, pose 1 of thesis table 6-1) is
rendered at ``--width`` px for each case below and decoded twice, with
``phase_ripple: off`` and ``auto``; the script records the fit's evidence Z, the
ripple's excess RMS against the phase noise, whether ``auto`` corrected it, the RMS
error of tau against the renderer's true tau (lit, unsaturated pixels valid in both
decodings) either way, and the decode times (median of ``--repeats``).

Cases (projector gamma 2.2 is the realistic profile's; the render's noise and defocus
are the default ``RenderConfig``'s unless "noise-free"):

* 3 steps, counts 16..8, gamma 2.2, sharp (no defocus): harmonic 2 aliases (0.25 rad);
* the same, noise-free (``RenderConfig.ideal()``, 16 bits): the ripple alone;
* 3 steps, gamma 1: noise alone (must not be corrected);
* 4 steps, counts 16..8, gamma 2.2, sharp: harmonics 3 and 5 alias (0.008 rad);
* the thesis's 7 steps, counts 64..32, gamma 2.2 and the realistic profile's camera
  response (0.003), default defocus: harmonics 6 and 8 alias, blurred.

Prints one JSON object::

    PYTHONPATH=. python benchmarks/phase_ripple.py --out benchmarks/results/phase_ripple.json

``--smoke``: 96 px, one repeat.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from _common import add_options, conditions, finish  # noqa: E402

CASES = (
    {"name": "3 steps, gamma 2.2, sharp", "steps": 3, "counts": (16, 5), "gamma": 2.2, "render": "sharp"},
    {"name": "3 steps, gamma 2.2, noise-free", "steps": 3, "counts": (16, 5), "gamma": 2.2, "render": "exact"},
    {"name": "3 steps, gamma 1 (noise alone)", "steps": 3, "counts": (16, 5), "gamma": 1.0, "render": "sharp"},
    {"name": "4 steps, gamma 2.2, sharp", "steps": 4, "counts": (16, 5), "gamma": 2.2, "render": "sharp"},
    {"name": "thesis 7 steps, gamma 2.2, camera response 0.003, defocus", "steps": 7, "counts": (64, 7),
     "gamma": 2.2, "linearity": 0.003, "render": "default"},
)


def scene_of(width: int):
    import pandas as pd

    from fringecal.artefact import load_artefact, load_rods
    from fringecal.frames import Frame
    from fringecal.rig import load_rig, scaled_scanner
    from fringecal.simulate import artefact_scene, backdrop

    thesis = ROOT / "configs" / "thesis"
    rig, art = load_rig(thesis / "sensors_refined_table6-8.csv"), load_artefact(thesis / "artefact_cmm2.csv")
    row = pd.read_csv(thesis / "poses_scanner1_table6-1.csv").iloc[0]
    pose = Frame.from_params(row[["tx_mm", "ty_mm", "tz_mm", "omega_rad", "phi_rad", "kappa_rad"]].to_numpy(float))
    scanner = scaled_scanner(rig.scanner("scanner1"), width)
    return scanner, artefact_scene(art, load_rods(thesis / "rods.csv", art), pose, background=backdrop(scanner, 3500.0))


def run_case(case: dict, scanner, scene, repeats: int) -> dict:
    from fringecal.fringe.decode import DecodeSettings, decode
    from fringecal.fringe.sequence import FringeSequence, reverse_exponential_counts
    from fringecal.simulate import Material, RenderConfig, render_measurement
    from fringecal.simulate.unmodelled import RenderErrors

    seq = FringeSequence(fringe_counts=reverse_exponential_counts(*case["counts"]), n_steps=case["steps"])
    cfg = RenderConfig()
    if case["render"] == "sharp":
        cfg = cfg.model_copy(update={"blur_at_focus_mm": 0.0, "blur_per_mm": 0.0})
    elif case["render"] == "exact":
        cfg = RenderConfig(bit_depth=16, materials={"background": Material(albedo=1.0)}).ideal()
    errors = RenderErrors(projector_gamma=case["gamma"], camera_linearity_error=case.get("linearity", 0.0))
    m = render_measurement(scanner, scene, cfg, np.random.default_rng(3), seq, errors)
    times = {"off": [], "auto": []}
    out = {}
    for mode in ("off", "auto"):
        for _ in range(repeats):
            t0 = time.perf_counter()
            out[mode] = decode(m.frames, seq, DecodeSettings(phase_ripple=mode), full_scale=cfg.max_dn)
            times[mode].append(time.perf_counter() - t0)
    truth = m.truth
    lit = np.isfinite(truth.tau_x_centre) & (truth.irradiance > 0.3) & (truth.irradiance < 1.0)
    mask = lit & out["off"].valid & out["auto"].valid
    row = {**case, "counts": list(seq.fringe_counts), "pixels_compared": int(mask.sum()),
           "decode_seconds": {k: statistics.median(v) for k, v in times.items()}, "orientations": {}}
    for o in seq.orientations:
        r = out["auto"].ripple.get(o)
        err = {}
        for mode in ("off", "auto"):
            e = out[mode].tau[o][mask] - getattr(truth, f"tau_{o}_centre")[mask]
            err[mode] = float(np.sqrt(np.mean(((e + np.pi) % (2 * np.pi) - np.pi) ** 2)))
        row["orientations"][o] = {
            "z": None if r is None else r.z, "applied": bool(r is not None and r.applied),
            "excess_rms_rad": None if r is None else r.excess_rms_rad,
            "noise_rms_rad": None if r is None else r.noise_rms_rad,
            "tau_error_rms_rad": err, "tau_error_ratio": err["auto"] / err["off"] if err["off"] > 0 else None}
    return row


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=512, help="camera width in px (default 512)")
    ap.add_argument("--repeats", type=int, default=3)
    args = add_options(ap).parse_args(argv)
    doc = conditions("phase_ripple", argv, args.smoke)
    width, repeats = (96, 1) if args.smoke else (args.width, args.repeats)
    t0 = time.perf_counter()
    scanner, scene = scene_of(width)
    doc.update(width_px=width, repeats=repeats, cases=[run_case(c, scanner, scene, repeats) for c in CASES],
               wall_seconds=time.perf_counter() - t0)
    return finish(doc, args.out)


if __name__ == "__main__":
    main()
