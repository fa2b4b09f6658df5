"""Synthetic scenes: the camera rig, seeded randomness, ray casting, worlds and their renderer.

* :mod:`.camera`: KITTI-like intrinsics, the camera height and far plane, procedural driving
  trajectories; :mod:`.seeding`: random generators seeded from keys;
* :mod:`.raycast`: the slab maths and ray casting against axis-aligned boxes;
* :mod:`.boxes`: the per-frame box scene of ``flow=exact`` (drawn anew for every frame);
* :mod:`.worlds`: persistent worlds along a trajectory (``flow=dis``), with their settings
  (:mod:`.world_config`), road and ground grid (:mod:`.road`) and the named columns of the boxes'
  shading parameters (:mod:`.box_params`);
* the renderer, split by stage as pytorch3d splits its own: :mod:`.render` (the public face:
  :func:`~.render.render_frame`, :func:`~.render.exact_flow`, and the camera rays),
  :mod:`.ground_casting` and :mod:`.frame_boxes` (what each ray hits), :mod:`.clipping`,
  :mod:`.textures` and :mod:`.shading` (its colour), :mod:`.optical_flow` (the exact flow
  between two frames). ``docs/rendering.md`` describes it.

Nothing here knows about datasets, flow estimation or models; :mod:`mfg_lightning.data` builds
its synthetic datasets on it.
"""
