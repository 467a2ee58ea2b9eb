"""Geometry in and out: signed distance grids from masks and images, contours and vector files.

``from_mask(mask, bounds)`` and ``from_image(image, bounds, threshold)`` turn pixels into a
:class:`fastsdf.grid.GridSDF` through an exact, parallel Euclidean distance transform
(:mod:`fastsdf.geometry.edt`).
"""

from .edt import distance_transform, signed_distance_transform
from .mask import from_image, from_mask

__all__ = ["distance_transform", "from_image", "from_mask", "signed_distance_transform"]
