"""Geometry in and out: signed distance grids from masks and images, contours and vector files.

``from_mask(mask, bounds)`` and ``from_image(image, bounds, threshold)`` turn pixels into a
:class:`fastsdf.grid.GridSDF` through an exact, parallel Euclidean distance transform
(:mod:`fastsdf.geometry.edt`). ``contours(f, level, bounds, resolution)`` returns a level
set as polylines whose vertices are refined on the function itself; ``to_svg`` and ``to_dxf``
write them to vector files.
"""

from .contours import Contour, contours
from .edt import distance_transform, signed_distance_transform
from .mask import from_image, from_mask
from .vector import to_dxf, to_svg

__all__ = ["Contour", "contours", "distance_transform", "from_image", "from_mask",
           "signed_distance_transform", "to_dxf", "to_svg"]
