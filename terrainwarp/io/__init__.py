"""File I/O: images (OpenImageIO) and GeoTIFFs (rasterio). Nothing here knows about the pipeline's types."""
