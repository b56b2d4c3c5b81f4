"""``omniscs view``: a browser viewer (viser) of scene stores and fitted scene graphs. ``state`` builds what is
drawn as plain arrays, ``session`` keeps the edits made in the viewer as an edit spec, ``app`` wires both to viser."""
