"""Geodesy: how many metres a degree of longitude and latitude spans on an ellipsoid.

Used where a raster's spacing is given in degrees: GeoTIFFs in a geographic CRS
(:mod:`terrainwarp.io.geotiff`) and the SRTM examples (:meth:`terrainwarp.Heightmap.example`).
"""

from __future__ import annotations

import math

__all__ = ["WGS84_A", "WGS84_F", "WGS84_INV_F", "metres_per_degree"]

# WGS84 ellipsoid: semi-major axis (metres), inverse flattening, flattening
WGS84_A = 6378137.0
WGS84_INV_F = 298.257223563
WGS84_F = 1.0 / WGS84_INV_F


def metres_per_degree(lat_deg: float, *, a: float = WGS84_A, f: float = WGS84_F) -> tuple[float, float]:
    """Metres per degree of (longitude, latitude) at geodetic latitude ``lat_deg`` on the ellipsoid with
    semi-major axis ``a`` metres and flattening ``f`` (default WGS84; f=0 is a sphere).

    Longitude: N(phi) cos(phi) * pi/180 with N the prime-vertical radius of curvature; latitude:
    M(phi) * pi/180 with M the meridional radius of curvature.
    """
    e2 = f * (2.0 - f)
    phi = math.radians(lat_deg)
    s2 = math.sin(phi) ** 2
    n = a / math.sqrt(1.0 - e2 * s2)
    m = a * (1.0 - e2) / (1.0 - e2 * s2) ** 1.5
    return (math.pi / 180.0 * n * math.cos(phi), math.pi / 180.0 * m)
