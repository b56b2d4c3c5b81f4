"""Closed-loop testing inside the edited world: render at the ego's pose, let a driving policy plan, track the plan
with a bicycle model, move the other agents, and score the run (NAVSIM's PDMS, HUGSIM's HD-Score). The HTTP server
that HUGSIM's client drives lives on the top floor (``omniscs.server``)."""
