"""The read side of the tiled map: Mapbox Vector Tiles (``ST_AsMVT`` on PostGIS, the same tile
encoded in Python on SQLite), GeoJSON, TileJSON, and the ETag / cache logic. See docs/tiles.md."""
