"""Seeded FLANN kd-trees: every approximate nearest-neighbour search of the project that is not
faiss (the map index's large candidate sets, its optional kd-tree vocabulary, the register
stage's 2-NN and Hough searches above ``georeg.register.matching.FLAT_MAX``)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

#: leaves a kd-tree search visits: 512 returns more of the true neighbours than 128 at the same
#: CPU s a query; on SRIF wide optical-optical its effect is within the RANSAC seed's noise
#: (docs/experiments/benchmark-history.md "Session 19")
KDTREE_CHECKS = 512


def kdtree(desc: np.ndarray) -> Any:
    """A FLANN randomised kd-tree index (4 trees) over ``desc``. Its split dimensions are drawn
    from OpenCV's process-wide generator, reseeded here (0) at every build: otherwise an index,
    and every match through it, depends on what the process drew before (a library user's
    earlier queries: SRIF wide optical-optical 131 was accepted or not depending on the query
    registered before it)."""
    cv2.setRNGSeed(0)
    return cv2.flann_Index(np.ascontiguousarray(desc, np.float32), {"algorithm": 1, "trees": 4})


def knn_search(index: Any, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(ids int64, squared distances float32), each (n, k), of ``q`` in a ``kdtree`` index (no
    query rows: empty arrays; FLANN itself returns None for them)."""
    if len(q) == 0:
        return np.empty((0, int(k)), np.int64), np.empty((0, int(k)), np.float32)
    ii, d2 = index.knnSearch(np.ascontiguousarray(q, np.float32), int(k),
                             params={"checks": KDTREE_CHECKS})  # fmt: skip
    return np.asarray(ii, np.int64), np.asarray(d2, np.float32)
