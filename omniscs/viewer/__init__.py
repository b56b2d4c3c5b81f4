"""``omniscs view``: a browser viewer (viser) of scene stores and fitted scene graphs. ``state`` builds what is
drawn as plain arrays, ``session`` keeps the edits made in the viewer as an edit spec (``paths``: drawn paths,
``placement``: the appearance placement checks on an edited agent), ``targets`` opens what a path holds, ``app`` wires
it all to viser."""
