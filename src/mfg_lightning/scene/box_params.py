"""Named columns of the boxes' ``(M, 8)`` texture parameters (:attr:`.furnishing.Boxes.params`).

The world generator (:mod:`.worlds`) draws them and the shaders (:mod:`.shading`) read them;
both index the columns through these names. What a column means depends on the box's kind:

=======  ===================  ==================================================================
column   facades              parked cars, crates, moving cars, pedestrians
=======  ===================  ==================================================================
0        floor height (m)     ``PARAM_TEXTURE_OFFSET``: shift of the surface noise (m, 0 … 1000)
1        window spacing (m)   ``PARAM_SPARE_OFFSET``: a second shift, drawn but not read
2        window width         crates: rib period (m); pedestrians: skin colour R
3        window height        crates: label (0 / 1); pedestrians: skin colour G
4        wall style           pedestrians: skin colour B
5, 6     texture offsets (m)  zero
7        shop front draw      zero
=======  ===================  ==================================================================

Facade window sizes are fractions (of the spacing and of the floor height); the wall style is
0 plaster, 1 brick, 2 concrete panels; a facade has a shop front on its ground floor where the
shop front draw (uniform in [0, 1)) is below ``SHOP_FRONT_BELOW``.
"""

from __future__ import annotations

__all__ = [
    "NUM_PARAMS",
    "PARAM_CRATE_LABEL",
    "PARAM_CRATE_RIB_PERIOD",
    "PARAM_FACADE_OFFSET_U",
    "PARAM_FACADE_OFFSET_V",
    "PARAM_FACADE_SHOP",
    "PARAM_FACADE_STYLE",
    "PARAM_FLOOR_HEIGHT",
    "PARAM_PEDESTRIAN_SKIN",
    "PARAM_SPARE_OFFSET",
    "PARAM_TEXTURE_OFFSET",
    "PARAM_WINDOW_HEIGHT",
    "PARAM_WINDOW_SPACING",
    "PARAM_WINDOW_WIDTH",
    "SHOP_FRONT_BELOW",
    "STYLE_BRICK",
    "STYLE_CONCRETE",
    "STYLE_PLASTER",
]

#: Number of columns of ``Boxes.params``.
NUM_PARAMS = 8

# Facades.
#: Height of one floor (metres).
PARAM_FLOOR_HEIGHT = 0
#: Distance between window centres along the wall (metres).
PARAM_WINDOW_SPACING = 1
#: Window width as a fraction of the spacing.
PARAM_WINDOW_WIDTH = 2
#: Window height as a fraction of the floor height.
PARAM_WINDOW_HEIGHT = 3
#: Wall style, one of ``STYLE_PLASTER``, ``STYLE_BRICK``, ``STYLE_CONCRETE`` (as a float).
PARAM_FACADE_STYLE = 4
#: Shifts of the wall's texture along the wall and up it (metres).
PARAM_FACADE_OFFSET_U, PARAM_FACADE_OFFSET_V = 5, 6
#: A uniform draw in [0, 1): the facade has a shop front where it is below ``SHOP_FRONT_BELOW``.
PARAM_FACADE_SHOP = 7
SHOP_FRONT_BELOW = 0.4
STYLE_PLASTER, STYLE_BRICK, STYLE_CONCRETE = 0, 1, 2

# Parked cars, crates, moving cars and pedestrians.
#: Shift of the surface noise (metres).
PARAM_TEXTURE_OFFSET = 0
#: A second shift, drawn (it sets the random draws that follow) but read by no shader.
PARAM_SPARE_OFFSET = 1
#: Crates: the period of the wall's corrugation (metres).
PARAM_CRATE_RIB_PERIOD = 2
#: Crates: 1 if a side carries a light label, else 0.
PARAM_CRATE_LABEL = 3
#: Pedestrians: the head's skin colour, RGB 0-255 (a slice of three columns).
PARAM_PEDESTRIAN_SKIN = slice(2, 5)
