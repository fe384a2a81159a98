"""Level of detail: what to draw. The quadtree (:mod:`.quadtree`, re-exported here), its policies and the
map from a ``LodConfig`` to a policy (:mod:`.policies`, re-exported here), the schemes engines ship
(:class:`Cdlod`, :class:`Clipmap`, :class:`ChunkedLod`, re-exported here), and, each in its module, the
bintree, the polytree, visibility tables and the peer meshers (Martini, Delatin)."""

from .cdlod import Cdlod
from .chunked import ChunkedLod
from .clipmaps import Clipmap
from .policies import (
    MAX_TESS,
    POLICY_CLASSES,
    ContinuousPolicy,
    DistancePolicy,
    Policy,
    ScreenErrorPolicy,
    check_policy,
    continuous_factors,
    edge_pixels,
    make_policy,
)
from .quadtree import (
    LodState,
    NodeMetrics,
    PatchList,
    Terrain,
    node_metrics,
    select,
    tile_from_key,
    tile_key,
    tile_name,
)

__all__ = ["Terrain", "DistancePolicy", "ScreenErrorPolicy", "ContinuousPolicy", "Policy", "POLICY_CLASSES",
           "make_policy", "check_policy", "edge_pixels", "continuous_factors", "PatchList", "LodState",
           "NodeMetrics", "node_metrics", "select", "tile_key", "tile_from_key", "tile_name", "MAX_TESS",
           "Cdlod", "Clipmap", "ChunkedLod"]
