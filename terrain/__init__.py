"""Sortie terrain: DEM readers, procedural terrain, and batched queries.

Modules hold pure array functions over the concept they are named after
(raster, geodesy, dem, mosaic, procedural, detail, pyramid, los, profile);
:class:`terrain.terrain.Terrain` stacks sources and answers queries.
"""
