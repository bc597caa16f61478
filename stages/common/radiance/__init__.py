"""The radiance field and its renderer, shared by the stages that train or render a NeRF.

Shaped as nerfacc shapes it: `rays` (camera rays, the scene-box slab test), `marching`
(rays -> samples, empty-space skipping through an `Occupancy`, early stop), one field query
per sample batch returning colour, density and class logits (`field`), `compositing`
(samples, weights -> colour, depth, opacity, classes) and `render` (whole rays and views,
the field given as functions). Importing this package does not import torch; its modules do.
"""
