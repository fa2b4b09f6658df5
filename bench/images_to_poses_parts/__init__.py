"""The parts of ``bench/images_to_poses.py`` beside the script: :mod:`.timing`, what it times
(a ``predict`` call, and each stage alone). ``bench/images_to_poses.py`` puts ``bench/`` on the
path."""
