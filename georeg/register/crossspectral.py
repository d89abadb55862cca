"""Cross-spectral matching front-end: features that survive SWIR vs visible and years.

Measured on the cross-date SWIR -> RGB development set (benchmarks/bench_crossspectral.py,
docs/BENCHMARKS.md "Cross-spectral matching"). The pieces:

* ``flip_polarity``: the SIFT descriptor of the contrast-inverted image at the same keypoint,
  computed by permuting the descriptor (no second extraction). Inverting an image negates every
  gradient: the dominant orientation turns by 180 degrees, the orientation bins relative to it are
  unchanged, and the 4 x 4 spatial cells are visited in the opposite order. So the inverted
  descriptor is the original with its cell grid rotated by 180 degrees (exact; checked in
  tests/test_crossspectral.py). Querying with both polarities is the same as putting both
  polarities of the map in the vocabulary, at no cost on the map side: a roof bright in the
  visible and dark at 2.2 um (or vegetation, dark in the visible, bright at 1.6 um) still matches.
* ``rotation_hypotheses``: a loose ratio test, keypoint-size agreement and a vote on the
  rotation (the ``vote`` matcher, the default: ``register.matcher``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

# descriptor layout of OpenCV SIFT: index = (row_cell * 4 + col_cell) * 8 + orientation_bin
_FLIP = np.arange(128).reshape(4, 4, 8)[::-1, ::-1, :].ravel()


def flip_polarity(desc: np.ndarray) -> np.ndarray:
    """SIFT/RootSIFT descriptors of the contrast-inverted image at the same keypoints."""
    d = np.asarray(desc)
    if d.shape[-1] != 128:
        raise ValueError(f"expected 128-D SIFT descriptors, got {d.shape}")
    return d[..., _FLIP]


def matcher_conf(reg_conf: dict[str, Any] | None) -> dict[str, Any]:
    """``register.matcher`` with the defaults of config/config.yaml: method vote (polarity both)
    | paper (polarity one unless asked)."""
    m = dict((reg_conf or {}).get("matcher") or {})
    m.setdefault("method", "vote")
    m.setdefault("polarity", "both" if m["method"] == "vote" else "one")
    return m


def add_polarity(xy: np.ndarray, desc: np.ndarray, response: np.ndarray):
    """Append the inverted-polarity copy of every feature (same position and response)."""
    return (
        np.concatenate([xy, xy]),
        np.concatenate([desc, flip_polarity(desc)]).astype(np.float32),
        np.concatenate([response, response]),
    )


def _circ_diff(a: np.ndarray, b: float) -> np.ndarray:
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


def rotation_hypotheses(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    q_angle: np.ndarray,
    q_size: np.ndarray,
    m_xy: np.ndarray,
    m_angle: np.ndarray,
    m_size: np.ndarray,
    knn: Any,
    conf: dict[str, Any],
) -> list[tuple[Any, int]]:
    """Loose ratio matches, filtered by keypoint scale and grouped by rotation (Lowe's Hough vote).

    Cross-spectral descriptors are far apart, so the paper's 2-NN ratio 0.7 keeps almost nothing
    on real SWIR vs visible pairs. A loose ratio (``ratio``, 0.9) keeps many, mostly wrong; two
    properties of right matches that do not depend on the spectrum separate them: the keypoint
    sizes agree (both images are at the feature GSD: |log2 size ratio| <= ``max_octaves``) and the
    orientation differences of all right matches equal the query's rotation. The strongest
    ``hypotheses`` peaks of a ``bin_deg`` histogram of orientation differences (weighted by
    distinctiveness 1 - d1/d2) are returned, each with the matches within ``bin_deg`` of it, and
    the number of rotation bins (a multiple-test count for the NFA). Sizes in feature pixels;
    angles in degrees (OpenCV keypoint convention, both images row-down).
    """
    from georeg.register.matching import Matches, _closest_per_key

    ratio = float(conf.get("ratio", 0.9))
    d, ii = knn(q_desc)
    ok = (ii[:, 0] >= 0) & (d[:, 0] < ratio * d[:, 1])
    qi = np.flatnonzero(ok)
    mi = ii[ok, 0].astype(np.int64)
    dist = d[ok, 0]
    w = 1.0 - d[ok, 0] / np.maximum(d[ok, 1], 1e-9)
    oct_max = float(conf.get("max_octaves", 1.0))
    if oct_max > 0:
        lr = np.abs(np.log2(np.maximum(m_size[mi], 1e-6) / np.maximum(q_size[qi], 1e-6)))
        keep = lr <= oct_max
        qi, mi, dist, w = qi[keep], mi[keep], dist[keep], w[keep]
    bin_deg = float(conf.get("bin_deg", 15.0))
    nb = max(1, int(round(360.0 / bin_deg)))
    if len(qi) == 0:
        return []
    delta = (m_angle[mi] - q_angle[qi]) % 360.0
    hist = np.bincount((delta / (360.0 / nb)).astype(int) % nb, weights=w, minlength=nb)
    sm = hist + 0.5 * (np.roll(hist, 1) + np.roll(hist, -1))
    peaks = [
        b
        for b in np.argsort(-sm, kind="stable")
        if sm[b] >= sm[(b - 1) % nb] and sm[b] >= sm[(b + 1) % nb]
    ]
    out = []
    for b in peaks[: int(conf.get("hypotheses", 2))]:
        centre = (b + 0.5) * 360.0 / nb
        sel = np.flatnonzero(_circ_diff(delta, centre) <= bin_deg)
        # one match per map feature and one per query position (a keypoint's polarity copy and
        # its extra orientations sit at one place: several matches there are not independent)
        sel = sel[_closest_per_key(mi[sel], dist[sel])]
        qkey = np.unique(np.round(q_xy[qi[sel]], 1), axis=0, return_inverse=True)[1].ravel()
        sel = sel[_closest_per_key(qkey, dist[sel])]
        order = np.argsort(dist[sel], kind="stable")
        sel = sel[order]
        m = Matches(
            qi[sel],
            mi[sel],
            q_xy[qi[sel]].astype(np.float64),
            m_xy[mi[sel]].astype(np.float64),
            dist[sel],
            len(q_desc),
        )
        out.append((m, nb))
    return out


def guided_matches(
    q_xy: np.ndarray,
    q_desc: np.ndarray,
    H: np.ndarray,
    m_xy: np.ndarray,
    m_desc: np.ndarray,
    radius: float,
    ratio: float = 0.95,
    knn: Any = None,
) -> Any:
    """Matches of every query feature among the map features within ``radius`` (map units) of
    H's prediction: nearest descriptor there, 2-NN ratio among those local candidates only
    (a second neighbour elsewhere on the map says nothing about this place). A feature with a
    single local candidate is compared with its nearest other descriptor over the whole region
    instead (``knn``, a georeg.register.matching.knn2 searcher over ``m_desc``), else it would pass
    unchecked. One match per map feature (the closest descriptor). Returns Matches."""
    from scipy.spatial import cKDTree

    from georeg.register.matching import Matches, _closest_per_key, apply_h

    z = np.zeros(0, np.int64)
    empty = Matches(z, z, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), len(q_desc))
    if len(q_xy) == 0 or len(m_xy) < 2:
        return empty
    pred = apply_h(H, q_xy)
    ok = np.isfinite(pred).all(axis=1)
    tree = cKDTree(np.asarray(m_xy, np.float64))
    lists = tree.query_ball_point(pred[ok], float(radius))
    qi_ok = np.flatnonzero(ok)
    lens = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    if lens.sum() == 0:
        return empty
    qi = np.repeat(qi_ok, lens)
    mi = np.fromiter((j for x in lists for j in x), np.int64, int(lens.sum()))
    d = np.linalg.norm(q_desc[qi].astype(np.float32) - m_desc[mi].astype(np.float32), axis=1)
    # best and second best per query feature
    o = np.lexsort((d, qi))
    qi, mi, d = qi[o], mi[o], d[o]
    first = np.r_[True, qi[1:] != qi[:-1]]
    pos = np.flatnonzero(first)
    second = pos + 1
    has2 = (second < len(qi)) & (np.r_[qi, -1][np.minimum(second, len(qi))] == qi[pos])
    d2 = np.where(has2, d[np.minimum(second, len(qi) - 1)], np.inf)
    if knn is not None and (~has2).any():
        lone = np.flatnonzero(~has2)
        gd, gi = knn(q_desc[qi[pos[lone]]])
        other = np.where(gi[:, 0] == mi[pos[lone]], gd[:, 1], gd[:, 0])
        d2[lone] = np.maximum(other, d[pos[lone]])
    good = d[pos] < ratio * d2
    sel = pos[good]
    keep = sel[_closest_per_key(mi[sel], d[sel])]
    keep = keep[np.argsort(d[keep], kind="stable")]
    return Matches(qi[keep], mi[keep], q_xy[qi[keep]].astype(np.float64),
                   m_xy[mi[keep]].astype(np.float64), d[keep], len(q_desc))  # fmt: skip
