"""Level of detail: what to draw. The quadtree (:mod:`.quadtree`, re-exported here), the bintree, the
polytree, visibility tables and the peer meshers (Martini, Delatin)."""

from .quadtree import (
    MAX_TESS,
    ContinuousPolicy,
    DistancePolicy,
    LodState,
    NodeMetrics,
    PatchList,
    ScreenErrorPolicy,
    Terrain,
    node_metrics,
    select,
    tile_from_key,
    tile_key,
    tile_name,
)

__all__ = ["Terrain", "DistancePolicy", "ScreenErrorPolicy", "ContinuousPolicy", "PatchList", "LodState",
           "NodeMetrics", "node_metrics", "select", "tile_key", "tile_from_key", "tile_name", "MAX_TESS"]
