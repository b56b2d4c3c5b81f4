"""Background repair: fill what a moved or removed large static object hid (holes, inpainting, relative depth,
DRNet to absolute depth, RoI-guided refit of the background node)."""
