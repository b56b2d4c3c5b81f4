"""Appearance-level SCS: mining what a detector misses, placing and compositing objects into a scene graph."""
