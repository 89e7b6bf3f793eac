"""``codecsplat eval``: the paper's evaluation (Tables 1, 2 and 4).

* :mod:`~codecsplat_warp.eval.protocols`: protocols (image size, view counts), the scenes under ``--data`` and
  the samples (context and target views) taken from them, the copy-the-nearest-view prediction;
* :mod:`~codecsplat_warp.eval.evaluate`: running CodecSplat and the baselines on the samples (:func:`evaluate`);
* :mod:`~codecsplat_warp.eval.geometry`: reference (MVS) depth of the context views on a sample's grid, and the
  depth errors against it;
* :mod:`~codecsplat_warp.eval.report`: rows, means, the paper's tables, the Markdown file and the plots;
* :mod:`~codecsplat_warp.eval.shards`: work over worker processes, one per GPU, and the evaluation split that way
  (``codecsplat eval --workers``).
"""
