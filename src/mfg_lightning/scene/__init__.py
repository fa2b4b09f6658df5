"""Synthetic scenes: the camera rig, seeded randomness, ray casting, worlds and their renderer.

* :mod:`.camera`: KITTI-like intrinsics, the camera height and far plane, procedural driving
  trajectories; :mod:`.seeding`: random generators seeded from keys;
* :mod:`.raycast`: the slab maths and ray casting against axis-aligned boxes;
* :mod:`.boxes`: the per-frame box scene of ``flow=exact`` (drawn anew for every frame);
* :mod:`.worlds`: persistent worlds along a trajectory (``flow=dis``), and the renderer that
  draws them (ray casting, textures, shading, exact flow; ``docs/rendering.md``).

Nothing here knows about datasets, flow estimation or models; :mod:`mfg_lightning.data` builds
its synthetic datasets on it.
"""
