"""The heightmap's surface: normals and curvature (:mod:`.differential`), curvature-line strokes."""
