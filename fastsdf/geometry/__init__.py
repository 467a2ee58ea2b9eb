"""Geometry in and out: signed distance grids from masks and images, contours and vector files.

``from_mask(mask, bounds)`` and ``from_image(image, bounds, threshold)`` turn pixels into a
:class:`fastsdf.fields.grid.GridSDF` through an exact, parallel Euclidean distance transform
(:mod:`fastsdf.geometry.edt`). ``contours(f, level, bounds, resolution)`` returns a level
set as polylines whose vertices are refined on the function itself; ``to_svg`` and ``to_dxf``
write them to vector files. ``SvgPath(d)``, ``SvgFile(path)`` and ``Text("word")`` are exact
SDFs of SVG path data, SVG files and text (:class:`fastsdf.shapes.Outline`: lines and quadratic
Beziers exact, cubics and arcs within a stated tolerance).
"""

from fastsdf.geometry.contours import Contour, contours
from fastsdf.geometry.edt import distance_transform, signed_distance_transform
from fastsdf.geometry.mask import from_image, from_mask
from fastsdf.geometry.outline import SvgFile, SvgPath, Text
from fastsdf.geometry.vector import to_dxf, to_svg

__all__ = [
    "Contour",
    "SvgFile",
    "SvgPath",
    "Text",
    "contours",
    "distance_transform",
    "from_image",
    "from_mask",
    "signed_distance_transform",
    "to_dxf",
    "to_svg",
]
