"""Crack and T-junction detection for terrain meshes.

:func:`check_watertight` first merges vertices whose float32 positions are bit-identical (that is
the contract of the tessellator: two patches produce a shared vertex bit-identically, or not at
all), drops triangles that collapse after the merge (zero-area slivers of the fractional_odd
picture frame), then counts

* open edges: undirected edges used by exactly one triangle, each one of four kinds (:data:`EDGE_KINDS`):

  - heightmap border: the surface ends because the terrain does (both endpoints on the same side of the
    border rectangle in x, z; for a frame, an edge with the outside of the heightmap on one side);
  - culled-neighbour border (a frame of selected patches): the patch across the edge was not drawn
    (frustum-culled), so the surface ends there by design;
  - hole border: a no-data hole lies across the edge (its triangles were dropped);
  - crack: anything else: the neighbour across the edge was drawn and does not share the edge.

  Given a frame (or its mesh with ``patches=`` and ``heightmap=``), the kinds come from the frame's
  patches and heightmap (:func:`lod_edge_kinds`); otherwise from ``border`` and an ``allowed`` rule;
* non-manifold edges: used by three or more triangles;
* T-junctions: a vertex of an open edge that lies strictly inside another open edge in the
  horizontal (x, z) projection (a terrain is a height field, so a vertex that the neighbouring patch
  does not have shows up as a point on the neighbour's edge there; its height differs, which is the
  crack). Tolerance: 1e-6 of the edge's length across the edge, and 1e-6 away from both ends.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..heightmap import Heightmap
from ..kernels.checks import check_triangles
from ..lod.quadtree import PatchList
from .pipeline import Frame

__all__ = ["check_watertight", "check_watertight_domain", "WatertightReport", "lod_boundary", "lod_edge_kinds",
           "EDGE_KINDS"]

#: ``rule(a, b) -> (E,)``: for single edges with endpoints a and b (E, 3) float64 in the positions' frame,
#: where the surface legitimately ends: a bool mask (True: a border edge), or each edge's kind (int8, an
#: index into :data:`EDGE_KINDS`, as :func:`lod_edge_kinds` gives).
EdgeRule = Callable[[np.ndarray, np.ndarray], np.ndarray]

#: The kinds of open edge, in the order of their codes: 0 crack, 1 heightmap border, 2 culled-neighbour
#: border, 3 hole border.
EDGE_KINDS = ("crack", "heightmap_border", "culled_border", "hole_border")
CRACK, HEIGHTMAP_BORDER, CULLED_BORDER, HOLE_BORDER = range(4)


@dataclass(frozen=True)
class WatertightReport:
    """What :func:`check_watertight` found.

    Attributes:
        n_vertices: vertices after merging bit-identical positions.
        n_triangles: non-degenerate triangles after merging.
        n_degenerate: triangles dropped because two of their corners merged.
        n_border_edges: edges used once where the surface legitimately ends (the sum of the three kinds
            below).
        n_open_edges: edges used once where the surface should go on: cracks (also :attr:`n_cracks`).
        n_heightmap_border_edges: open edges on the terrain's border (or beyond it, on a patch overhanging
            the heightmap), or accepted by a bool ``allowed`` rule.
        n_culled_border_edges: open edges beside a patch that was not drawn (frustum-culled neighbour).
        n_hole_border_edges: open edges beside a no-data hole.
        n_nonmanifold_edges: edges used by three or more triangles.
        n_t_junctions: (vertex, edge) pairs where a vertex lies inside another open edge.
        open_edges: (n_open_edges, 2, 3) float64 endpoint positions of each crack edge.
        t_junctions: (n_t_junctions, 3, 3) float64: the vertex, then the edge's two endpoints.
    """

    n_vertices: int
    n_triangles: int
    n_degenerate: int
    n_border_edges: int
    n_open_edges: int
    n_nonmanifold_edges: int
    n_t_junctions: int
    open_edges: np.ndarray = field(repr=False)
    t_junctions: np.ndarray = field(repr=False)
    n_heightmap_border_edges: int = 0
    n_culled_border_edges: int = 0
    n_hole_border_edges: int = 0

    @property
    def n_cracks(self) -> int:
        """Open edges whose neighbour across was drawn: :attr:`n_open_edges`."""
        return self.n_open_edges

    @property
    def watertight(self) -> bool:
        """No cracks (a T-junction is one), no non-manifold edges."""
        return self.n_open_edges == 0 and self.n_t_junctions == 0 and self.n_nonmanifold_edges == 0

    def to_dict(self, max_items: int = 100) -> dict:
        """JSON-ready summary (the first ``max_items`` locations of each kind)."""
        return {
            "watertight": self.watertight, "n_vertices": self.n_vertices, "n_triangles": self.n_triangles,
            "n_degenerate": self.n_degenerate, "n_border_edges": self.n_border_edges,
            "n_heightmap_border_edges": self.n_heightmap_border_edges,
            "n_culled_border_edges": self.n_culled_border_edges, "n_hole_border_edges": self.n_hole_border_edges,
            "n_open_edges": self.n_open_edges, "n_nonmanifold_edges": self.n_nonmanifold_edges,
            "n_t_junctions": self.n_t_junctions,
            "open_edges": self.open_edges[:max_items].tolist(),
            "t_junctions": self.t_junctions[:max_items].tolist(),
        }


def _unpack(mesh, triangles):
    if triangles is not None:
        return mesh, triangles
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        return mesh[0], mesh[1]
    if hasattr(mesh, "positions") and hasattr(mesh, "triangles"):
        return mesh.positions, mesh.triangles
    raise TypeError(f"mesh: expected a Mesh, a Tessellation or (positions, triangles), got {type(mesh).__name__}")


def _check_arrays(pos: object, tri: object) -> tuple[np.ndarray, np.ndarray]:
    """Validated (n, 3) float32 positions and (m, 3) indices."""
    pos = np.asarray(pos)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"positions: expected shape (n, 3), got {pos.shape}")
    pos = np.ascontiguousarray(pos, dtype=np.float32)
    return pos, check_triangles("triangles", tri, pos.shape[0])


def _border_mask(merged: np.ndarray, once: np.ndarray, border: object) -> np.ndarray:
    """Single edges with both endpoints on the same side of the border rectangle."""
    if border is None or once.shape[0] == 0:
        return np.zeros(once.shape[0], bool)
    if isinstance(border, str):
        xz = merged[:, [0, 2]]
        bx = (xz[:, 0].min(), xz[:, 0].max(), xz[:, 1].min(), xz[:, 1].max())
    else:
        bx = tuple(float(b) for b in np.asarray(border, dtype=np.float64).reshape(4))
    a, b = merged[once[:, 0]], merged[once[:, 1]]
    on_border = np.zeros(once.shape[0], bool)
    for axis, val in ((0, bx[0]), (0, bx[1]), (2, bx[2]), (2, bx[3])):
        on_border |= (a[:, axis] == val) & (b[:, axis] == val)
    return on_border


def check_watertight(mesh, triangles=None, border="auto", allowed: EdgeRule | None = None, *,
                     patches: PatchList | None = None, heightmap: Heightmap | None = None) -> WatertightReport:
    """Count cracks (open edges where the surface should go on), non-manifold edges and T-junctions, and
    the open edges where it legitimately ends, by kind.

    Args:
        mesh: a :class:`terrainwarp.Frame` (its mesh, classified by its patches and heightmap), a
            :class:`terrainwarp.mesh.Mesh`, a ``Tessellation``, a ``(positions, triangles)`` pair, or positions
            (n, 3) float32 with ``triangles`` given separately (a patch's domain:
            :func:`check_watertight_domain`).
        triangles: (m, 3) int indices when ``mesh`` is a positions array.
        border: ``"auto"``: the x, z bounding rectangle of the positions (not used when a heightmap is known:
            its own border is the terrain's); ``None``: no border; or ``(x_min, x_max, z_min, z_max)`` in the
            positions' frame.
        allowed: a rule (:data:`EdgeRule`) for the single edges where the surface may also end.
        patches: the patches the mesh was tessellated from (a LOD frame's ``Frame.patches``); with
            ``heightmap``, open edges are classified by :func:`lod_edge_kinds` (culled-neighbour borders,
            hole borders, the heightmap's border, cracks). heightmap: the frame's heightmap (without
            ``patches``: a grid mesh, the whole heightmap drawn). Positions are taken relative to the
            mesh's ``eye`` (the origin when it has none).

    Returns:
        A :class:`WatertightReport` (locations in the positions' frame, float64).
    """
    mesh, patches, heightmap = _frame_parts(mesh, patches, heightmap)
    pos, tri = _unpack(mesh, triangles)
    if isinstance(border, str) and border != "auto":
        raise ValueError(f"border: expected 'auto', None or (x_min, x_max, z_min, z_max), got {border!r}")
    pos, tri = _check_arrays(pos, tri)
    if heightmap is not None:
        kinds_of = lod_edge_kinds(patches, heightmap, getattr(mesh, "eye", (0.0, 0.0, 0.0)))
        border = None if isinstance(border, str) else border
    else:
        kinds_of = None

    # merge bit-identical vertices (-0.0 and 0.0 are different bits, but equal positions: canonicalise)
    canon = pos + np.float32(0.0)
    _, inv = np.unique(canon.view(np.uint32).reshape(-1, 3), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    merged = np.zeros((int(inv.max()) + 1 if inv.size else 0, 3), np.float64)
    merged[inv] = pos.astype(np.float64)
    t = inv[tri.astype(np.int64)] if tri.size else np.zeros((0, 3), np.int64)
    good = (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])
    n_deg = int((~good).sum())
    t = t[good]

    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    once = uniq[counts == 1]
    n_nonmanifold = int((counts > 2).sum())

    kind = _edge_kinds(merged, once, border, allowed, kinds_of)
    n_kind = np.bincount(kind, minlength=len(EDGE_KINDS))
    open_e = once[kind == CRACK]
    open_pos = merged[open_e] if open_e.size else np.zeros((0, 2, 3))

    tj = _t_junctions(merged, open_e)
    return WatertightReport(
        n_vertices=int(merged.shape[0]), n_triangles=int(t.shape[0]), n_degenerate=n_deg,
        n_border_edges=int(once.shape[0] - open_e.shape[0]), n_open_edges=int(open_e.shape[0]),
        n_nonmanifold_edges=n_nonmanifold, n_t_junctions=int(tj.shape[0]),
        open_edges=open_pos.reshape(-1, 2, 3), t_junctions=tj.reshape(-1, 3, 3),
        n_heightmap_border_edges=int(n_kind[HEIGHTMAP_BORDER]), n_culled_border_edges=int(n_kind[CULLED_BORDER]),
        n_hole_border_edges=int(n_kind[HOLE_BORDER]))


def _frame_parts(mesh, patches: PatchList | None, heightmap: Heightmap | None):
    """(mesh, patches, heightmap): a Frame gives its own (arguments given explicitly win)."""
    if isinstance(mesh, Frame):
        if mesh.mesh is None:
            raise ValueError("mesh: the frame has no mesh (render it with an output that makes one)")
        patches = mesh.patches if patches is None else patches
        heightmap = mesh.scene.heightmap if heightmap is None else heightmap
        mesh = mesh.mesh
    if patches is not None and heightmap is None:
        raise ValueError("heightmap: required with patches (the frame's heightmap)")
    return mesh, patches, heightmap


def _edge_kinds(merged: np.ndarray, once: np.ndarray, border: object, allowed: EdgeRule | None,
                kinds_of: EdgeRule | None) -> np.ndarray:
    """(E,) int kind of each single edge (:data:`EDGE_KINDS`): the border rectangle, then the ``allowed``
    rule, then the frame's classification; what none of them explains is a crack."""
    kind = np.where(_border_mask(merged, once, border), HEIGHTMAP_BORDER, CRACK).astype(np.int64)
    if once.shape[0] == 0:
        return kind
    a, b = merged[once[:, 0]], merged[once[:, 1]]
    for rule in (allowed, kinds_of):
        if rule is None:
            continue
        r = np.asarray(rule(a, b))
        r = np.where(r, HEIGHTMAP_BORDER, CRACK) if r.dtype == bool else r.astype(np.int64)
        kind = np.where(kind == CRACK, r, kind)
    return kind


def check_watertight_domain(uv: np.ndarray, triangles: np.ndarray) -> WatertightReport:
    """:func:`check_watertight` of one patch's tessellation in its domain: points (n, 2) (u, v) in
    [0, 1]^2 (checked as positions (u, 0, v)); edges on the unit square's sides are its border."""
    uv = np.asarray(uv)
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv: expected shape (n, 2), got {uv.shape}")
    pos = np.stack([uv[:, 0], np.zeros(len(uv), uv.dtype), uv[:, 1]], 1)
    return check_watertight(pos, triangles, border=(0.0, 1.0, 0.0, 1.0))


def lod_edge_kinds(patches: PatchList | None, heightmap: Heightmap, eye: tuple[float, float, float]) -> EdgeRule:
    """Where a frame's surface legitimately ends, and why: a rule for :func:`check_watertight` that gives each
    single edge its kind (:data:`EDGE_KINDS`), from the points just either side of its midpoint (1e-3 of
    the smallest patch, or of the sample spacing, away):

    - heightmap border: one side lies outside the heightmap (on its border, or beyond it where a patch
      overhangs it);
    - culled-neighbour border: one side lies in no drawn patch (the patch there was culled);
    - hole border: one side lies within reach of a no-data hole (a NaN sample within one vertex spacing plus
      one sample spacing), whose triangles were dropped;
    - crack: both sides inside drawn patches, inside the heightmap and away from holes.

    Args:
        patches: the frame's :class:`terrainwarp.lod.PatchList`, or None for a grid mesh (the whole
            heightmap drawn); heightmap: its heightmap; eye: the mesh's ``eye`` (positions are relative to it).
    """
    (gx0, gz0), (gx1, gz1) = heightmap.bounds_xz
    spacing = max(heightmap.dx, heightmap.dz)
    if patches is not None and len(patches):
        ox, oz = patches.origin[:, 0], patches.origin[:, 1]
        sx, sz = patches.size[:, 0], patches.size[:, 1]
        eps = 1e-3 * float(np.min(patches.size))
        reach = float(np.max(patches.size / np.maximum(patches.inner, 1.0))) + spacing
    else:
        eps, reach = 1e-3 * min(heightmap.dx, heightmap.dz), 2.0 * spacing
    hi, hj = np.nonzero(np.isnan(heightmap.heights))
    hole_x = heightmap.origin[0] + hj * heightmap.dx
    hole_z = heightmap.origin[1] + hi * heightmap.dz

    def near_hole(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        out = np.zeros(len(x), bool)
        for k in range(0, len(hole_x), 4096):  # blocks keep (probes x holes) small
            out |= np.any((np.abs(x[:, None] - hole_x[None, k:k + 4096]) <= reach)
                          & (np.abs(z[:, None] - hole_z[None, k:k + 4096]) <= reach), axis=1)
        return out

    def drawn(x: np.ndarray, z: np.ndarray) -> np.ndarray:
        if patches is None:
            return np.ones(len(x), bool)
        return np.any((x[:, None] > ox) & (x[:, None] < ox + sx) & (z[:, None] > oz) & (z[:, None] < oz + sz), axis=1)

    def kinds(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a, b = a + np.asarray(eye, np.float64), b + np.asarray(eye, np.float64)
        mid, d = 0.5 * (a + b), b - a
        ln = np.maximum(np.hypot(d[:, 0], d[:, 2]), 1e-300)
        nx, nz = -d[:, 2] / ln * eps, d[:, 0] / ln * eps
        sides = [(mid[:, 0] + nx, mid[:, 2] + nz), (mid[:, 0] - nx, mid[:, 2] - nz)]
        out = np.full(len(a), CRACK, np.int8)
        for x, z in sides:  # the first reason found on either side, in the order of EDGE_KINDS
            outside = ~((x > gx0) & (x < gx1) & (z > gz0) & (z < gz1))
            out = np.where((out == CRACK) & outside, HEIGHTMAP_BORDER, out)
        for x, z in sides:
            out = np.where((out == CRACK) & ~drawn(x, z), CULLED_BORDER, out)
        if len(hole_x):
            for x, z in sides:
                out = np.where((out == CRACK) & near_hole(x, z), HOLE_BORDER, out)
        return out.astype(np.int8)

    return kinds


def lod_boundary(patches: PatchList, heightmap: Heightmap, eye: tuple[float, float, float]) -> EdgeRule:
    """:func:`lod_edge_kinds` as a bool rule for ``check_watertight(..., allowed=...)``: True where a LOD
    frame's surface legitimately ends (the heightmap's border, a culled neighbour, a no-data hole)."""
    kinds = lod_edge_kinds(patches, heightmap, eye)
    return lambda a, b: kinds(a, b) != CRACK


def _t_junctions(merged: np.ndarray, open_e: np.ndarray, tol: float = 1e-6, chunk: int = 1024) -> np.ndarray:
    """(k, 3, 3): each vertex of an open edge lying strictly inside another open edge (x, z projection)."""
    if open_e.shape[0] == 0:
        return np.zeros((0, 3, 3))
    cand = np.unique(open_e.reshape(-1))
    q = merged[cand][:, [0, 2]]
    order = np.argsort(q[:, 0], kind="stable")
    qs, cs = q[order], cand[order]
    out = []
    for s in range(0, open_e.shape[0], chunk):
        e = open_e[s:s + chunk]
        a = merged[e[:, 0]][:, [0, 2]]
        b = merged[e[:, 1]][:, [0, 2]]
        d = b - a
        length2 = (d * d).sum(1)
        lo = np.minimum(a[:, 0], b[:, 0]) - tol * np.sqrt(length2)
        hi = np.maximum(a[:, 0], b[:, 0]) + tol * np.sqrt(length2)
        i0 = np.searchsorted(qs[:, 0], lo, "left")
        i1 = np.searchsorted(qs[:, 0], hi, "right")
        for j in range(e.shape[0]):
            if i1[j] <= i0[j] or length2[j] == 0:
                continue
            p = qs[i0[j]:i1[j]]
            ids = cs[i0[j]:i1[j]]
            r = p - a[j]
            tpar = (r @ d[j]) / length2[j]
            cross = np.abs(r[:, 0] * d[j, 1] - r[:, 1] * d[j, 0]) / np.sqrt(length2[j])
            hit = (tpar > tol) & (tpar < 1 - tol) & (cross <= tol * np.sqrt(length2[j])) \
                & (ids != e[j, 0]) & (ids != e[j, 1])
            for v in ids[hit]:
                out.append(np.stack([merged[v], merged[e[j, 0]], merged[e[j, 1]]]))
    return np.asarray(out).reshape(-1, 3, 3)
