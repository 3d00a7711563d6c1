"""The hybrid method: skinned where the cloth follows the body, generated where it hangs free."""

from pocoloco.methods.hybrid.assemble import assemble_hybrid
from pocoloco.methods.hybrid.method import HybridConfig, HybridMethod, HybridModel
from pocoloco.methods.hybrid.regions import FreeRegionMaps, learn_free_maps, point_regions, render_free_maps

__all__ = ["FreeRegionMaps", "HybridConfig", "HybridMethod", "HybridModel", "assemble_hybrid", "learn_free_maps",
           "point_regions", "render_free_maps"]
