"""Trajectories: chaining per-frame motions into poses and snippets (:mod:`.trajectories`),
reading / writing KITTI and TUM trajectory files (:mod:`.pose_io`) and matching an estimate's
poses to the ground truth's by frame index or timestamp (:mod:`.association`)."""
