"""Factories that the data configs call: map pairs (real folders or the built-in scene) and
pre-cut CSV pairs, with the ``(length=, seed=)`` interface of :class:`PairDataModule`."""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from .aeroground import CsvPairs, DataError, MapPairs

__all__ = ["BUILTIN_VERSION", "builtin_root", "map_pairs", "csv_pairs"]

log = logging.getLogger("dpcn")

BUILTIN_VERSION = "v3"
# Seven scenes to train and validate on, and scene_c held out for testing: with only two
# training scenes (v2) the learned features fitted those two worlds (README, Benchmarks).
# Scenes a-c are the v2 ones (make_dataset derives each scene's seed from its index).
BUILTIN_SCENES = 8
_announced = False


def builtin_root(cache_dir: str | Path | None = None, n_scenes: int = BUILTIN_SCENES) -> Path:
    """The built-in procedural scenes (``n_scenes`` 1280x2560 scenes with disjoint train and
    val areas, :func:`dpcn.data.scene.make_dataset`'s defaults), generated once and cached.

    Scene ``i`` depends only on ``i`` (and :data:`BUILTIN_VERSION`), so a larger count adds
    scenes and keeps the first ones. The cache is ``$DPCN_CACHE`` or ``~/.cache/dpcn``;
    generation takes ~7 s per scene and is written to a temporary folder first, so
    concurrent or interrupted runs never see half a data set.
    """
    from .scene import make_dataset

    if isinstance(n_scenes, bool) or not isinstance(n_scenes, int) or n_scenes < 1:
        raise DataError(f"data.builtin_scenes must be an integer >= 1, got {n_scenes!r}")
    base = Path(cache_dir or os.environ.get("DPCN_CACHE") or Path.home() / ".cache" / "dpcn")
    root = base / f"builtin-scenes-{BUILTIN_VERSION}-{n_scenes}"
    done = root / "README.txt"  # make_dataset writes it after the last scene
    if done.is_file():
        return root
    base.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".builtin-", dir=base))
    try:
        make_dataset(tmp, n_scenes=n_scenes, seed=0)
        try:
            tmp.rename(root)
        except OSError:  # another process won the race
            if not done.is_file():
                raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return root


def map_pairs(
    length: int,
    seed: int,
    root: str | Path | None = None,
    builtin_scenes: int = BUILTIN_SCENES,
    **kwargs: Any,
) -> MapPairs:
    """:class:`MapPairs` over ``root``, or over the first ``builtin_scenes`` built-in
    procedural scenes if ``root`` is None."""
    global _announced
    if root is None:
        root = builtin_root(n_scenes=builtin_scenes)
        if not _announced:
            log.info(
                "no data.root given: using the %d built-in procedural scenes in %s (python -m dpcn make-data)",
                builtin_scenes,
                root,
            )
            _announced = True
    elif not Path(root).exists():
        raise DataError(f"data.root does not exist: {root}")
    return MapPairs(root, length=length, seed=seed, **kwargs)


def csv_pairs(length: int, seed: int, csv_path: str | Path | None = None, **kwargs: Any) -> CsvPairs:
    """:class:`CsvPairs` (pre-cut pairs); ``length``/``seed`` are ignored: the CSV fixes the pairs."""
    if csv_path is None:
        raise DataError(
            "data=csv needs the ground-truth CSV of each split a command reads: data.train_csv and "
            "data.val_csv to fit, data.val_csv to validate, data.test_csv to test"
        )
    return CsvPairs(csv_path, **kwargs)
