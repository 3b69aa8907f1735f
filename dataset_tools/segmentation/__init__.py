"""Hand and object masks and the green-paint contact truth (DESIGN.md stage 5; docs/segmentation.md)."""

from manus_core.errors import SegmentationError

from .background import BackgroundModel, fill_holes, remove_small
from .colour import ColourModel, PaintKey, chromaticity, dominant_colour_key
from .edges import refine_edges
from .multiview import Occupancy, carve, consistent_masks, project_occupancy
from .paint import contact_votes, paint_masks
from .pngs import load_png_masks
from .views import foreground_masks, hand_object_masks, object_colour, paint_key_from_object

__all__ = ["BackgroundModel", "SegmentationError", "fill_holes", "remove_small", "ColourModel", "PaintKey",
           "chromaticity", "dominant_colour_key", "Occupancy", "carve", "consistent_masks", "project_occupancy",
           "contact_votes", "paint_masks", "load_png_masks", "foreground_masks", "hand_object_masks",
           "object_colour", "paint_key_from_object", "refine_edges"]
