"""Loop detection without a downloaded vocabulary: the survey's own SIFT descriptors build the tree.

COLMAP's sequential matcher finds where a survey crosses itself (a lawnmower line flown back past the previous
one, a forward pass over the lawnmower strip) by querying a vocabulary tree every ``LOOP_PERIOD`` frames. The
usual tree is a download (flickr100k, 32-256 k words) we cannot fetch at run time; pycolmap's ``VisualIndex``
builds one offline from any descriptors, so each survey gets a small tree from a deterministic sample of its
own features. Words are few (about ``DESCRIPTORS_PER_WORD`` training descriptors each, at most ``MAX_WORDS``),
which is plenty to rank a few hundred images of one site; the numbers: docs/DECISIONS.md, "SfM at survey size".
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

MAX_TRAIN_DESCRIPTORS = 40_000  # k-means cost grows with samples x words; 40 k keeps the build at a few seconds
DESCRIPTORS_PER_WORD = 39  # faiss asks for >= 39 training points per centroid
MIN_WORDS, MAX_WORDS = 64, 1024
BUILD_ITERATIONS = 10  # k-means iterations (COLMAP's builder: 100 on millions of descriptors)
LOOP_PERIOD = 5  # query the tree every this many frames
LOOP_NUM_IMAGES = 30  # most similar images matched per query (geometric verification rejects the wrong ones)


def num_words(n_descriptors: int) -> int:
    """Visual words for ``n_descriptors`` training descriptors: the largest power of two with at least
    ``DESCRIPTORS_PER_WORD`` descriptors per word, clamped to [MIN_WORDS, MAX_WORDS]."""
    k = MIN_WORDS
    while k * 2 <= MAX_WORDS and k * 2 * DESCRIPTORS_PER_WORD <= n_descriptors:
        k *= 2
    return k


def build_vocab_tree(db_path: Path, out_path: Path, seed: int) -> int:
    """Build a vocabulary tree from the SIFT descriptors in ``db_path`` and write it to ``out_path``.

    Descriptors are sampled with a fixed stride over images in id order (deterministic), at most
    ``MAX_TRAIN_DESCRIPTORS``. k-means draws from pycolmap's global generator, so it is re-seeded with
    ``seed`` here: unseeded, two builds on one database differed in 157 k of 250 k bytes; seeded they are
    identical. On one thread only: with 2 threads two seeded builds of the same 12-frame database still gave
    different trees (pycolmap 4.2.1 on an AMD EPYC machine; the clustering's threads race), with 1 they are
    byte-identical. Returns the number of visual words.
    """
    import pycolmap  # lazy: native COLMAP (~0.2 s to load), only SfM and COLMAP files need it

    db = pycolmap.Database.open(str(db_path))
    try:
        descs = [db.read_descriptors(im.image_id).data for im in sorted(db.read_all_images(),
                                                                         key=lambda im: im.image_id)]
    finally:
        db.close()
    allf = np.concatenate([d for d in descs if len(d)]).astype(np.float32)  # [N, 128]
    stride = max(1, -(-len(allf) // MAX_TRAIN_DESCRIPTORS))
    train = np.ascontiguousarray(allf[::stride])
    words = num_words(len(train))
    opts = pycolmap.VisualIndex.BuildOptions()
    opts.num_visual_words = words
    opts.num_iterations = BUILD_ITERATIONS
    opts.num_rounds = 1
    opts.num_threads = 1  # deterministic (docstring)
    pycolmap.set_random_seed(seed)
    index = pycolmap.VisualIndex.create(128, 64)  # SIFT: 128-d descriptors, 64-bit Hamming embedding
    index.build(opts, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, train))
    index.write(str(out_path))
    log.info("sfm: vocabulary tree of %d words from %d of %d descriptors", words, len(train), len(allf))
    return words


__all__ = ["LOOP_NUM_IMAGES", "LOOP_PERIOD", "build_vocab_tree", "num_words"]
