"""The depth range the persistent-world renderer draws: the near plane and the culling distance.

Shared by its stages (ground casting, the frame's boxes, shading's fog, the exact flow), so that
they agree on what is in view. The far plane is the camera rig's (:data:`.camera.FAR_PLANE`).
"""

from __future__ import annotations

__all__ = ["CULL_DISTANCE", "NEAR"]

#: Nearest hit along a ray (metres of depth).
NEAR = 0.1
#: Boxes further than this from the camera (metres) are not drawn (at most the worlds'
#: ``SECTION_MARGIN``, so that a switch of ground sections changes nothing in view).
CULL_DISTANCE = 200.0
