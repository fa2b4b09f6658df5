"""Where the input flow comes from (the ``flow`` config group) and how it is stored.

* :mod:`.estimators`: the sources (exact, OpenCV DIS, the user's files, a dataset's ground
  truth), parsed from the ``flow`` config, and the cache of estimated flow;
* :mod:`.io`: reading and writing flow files in their published encodings (``.flo``, KITTI's
  16-bit PNG, Virtual KITTI's PNGs, ``.npy`` / ``.npz``);
* :mod:`.cache`: the cache root (``paths.cache_dir``, ``$MFG_CACHE_DIR``).
"""
