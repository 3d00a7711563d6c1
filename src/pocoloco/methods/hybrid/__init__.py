"""The hybrid method: skinned where the cloth follows the body, generated where it hangs free."""

from pocoloco.methods.hybrid.regions import FreeRegionMaps, learn_free_maps, point_regions, render_free_maps

__all__ = ["FreeRegionMaps", "learn_free_maps", "point_regions", "render_free_maps"]
