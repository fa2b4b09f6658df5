"""Trajectories: chaining per-frame motions into poses and snippets (:mod:`.trajectories`) and
reading / writing KITTI and TUM trajectory files (:mod:`.pose_io`)."""
