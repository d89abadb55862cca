"""Where the index coarse search ranks the true region of a real frame on a padded map (issue 32).

    python benchmarks/diag_frames_rank.py /work/bigmaps/odm_16 odm 0136

Prints the rank among distinct regions (``rank_regions`` top 400) of the regions holding the
truth footprint centre, for the nadir features and for all tilt hypotheses, with and without a
0.8 ratio test on the two nearest words.
"""
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from georeg.frames.coarse import (
    DEFAULTS,
    INDEX_DEFAULTS,
    _distinct_regions,
    frame_keys,
    index_window_m,
)
from georeg.frames.localize import MapSources, camera_matrix

m = Path(sys.argv[1])
case, fid = sys.argv[2], sys.argv[3]
D = Path(__file__).resolve().parents[1] / '..' / 'shared' / 'data' / 'frames_dev'
maps = MapSources(m / "index", m / "ortho.vrt", m / "dsm.vrt")
truth = json.loads((D / case / "truth" / f"{fid}.json").read_text())
cam = {k: truth["intrinsics"][k] for k in ("fx", "fy", "cx", "cy")}
cam["dist"] = truth["intrinsics"].get("dist") or [0]*5
rgb = cv2.cvtColor(cv2.imread(str(D / case / "queries" / f"{fid}.png")), cv2.COLOR_BGR2RGB)
h, w = rgb.shape[:2]
K, dist = camera_matrix(cam, w, h)
gray = cv2.cvtColor(cv2.undistort(rgb, K, dist), cv2.COLOR_RGB2GRAY)
c = {**DEFAULTS, **INDEX_DEFAULTS}
fc = {**maps.index.meta["features_conf"], "max_features_per_mpx": c["frame_features_per_mpx"]}
fp = np.asarray(truth["footprint_xyz"])[:, :2].mean(axis=0) if "footprint_xyz" in truth else np.asarray(truth["camera_center_xyz"][:2])
win, stride = index_window_m(w, h, maps.gsd, c)
for name, hyps in (("nadir", [(0.0, 0.0)]), ("all", [(0.0, 0.0)] + [(40.0, d) for d in (0, 90, 180, 270)])):
    keys = [frame_keys(gray, {**c, "scales": c["index_scales"]}, fc, K, hy) for hy in hyps]
    desc = np.concatenate([k[0].desc for k in keys])
    for ratio in (None, 0.8):
        dsel = desc
        if ratio:
            dd, _ = maps.index.quantize(desc, 2)
            dsel = desc[dd[:, 0] < ratio * dd[:, 1]]
        regs = maps.index.rank_regions(dsel, win, stride, top=400)
        regs = _distinct_regions(regs, win, 100)
        hit = [i for i, (b, s) in enumerate(regs) if b[0] - 0.25*win <= fp[0] <= b[2] + 0.25*win and b[1] - 0.25*win <= fp[1] <= b[3] + 0.25*win]
        print(name, ratio, len(dsel), "true region rank (distinct):", hit[:3], "scores", [round(s, 4) for _, s in regs[:3]], [round(regs[i][1], 4) for i in hit[:1]])
